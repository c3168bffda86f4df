"""A protocol pass's results (`Results`): returns per agent and condition, and E_G.

`Results` holds the returns of every agent at its training look and under every
condition, with the protocol's config; `summary()` is the dict the reports read
(`dmcr_jax.protocol_report`: `markdown`, `plot`, `write`), `to_json()` its JSON.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from dmcr_jax.protocol_report import generalization_error


@dataclasses.dataclass(frozen=True)
class Results:
  """A pass's returns, per agent (K = 1 without an agent axis).

  Attributes:
    task: the task.
    conditions: the conditions, in order.
    train: float64 (K, T) returns at the training look.
    returns: {condition: float64 (K, V·D) returns}, episode i of look i // D.
    test_visual_seeds: int64 (V,) held-out seeds.
    train_looks: per agent its training look's label (`look_label`).
    config: the protocol's options (JSON-safe).
    labels: per agent its name in tables.
    device: the device kind the pass ran on.
    wall_s: seconds of the pass (of every attempt, when resumed).
    compile_s: seconds of its first block (compilation included); None if resumed.
    agent_steps: agent steps run (every env's, every block's, padding included).
  """
  task: str
  conditions: tuple[str, ...]
  train: np.ndarray
  returns: dict
  test_visual_seeds: np.ndarray
  train_looks: tuple[str, ...]
  config: dict
  labels: tuple[str, ...]
  device: str
  wall_s: float
  compile_s: float | None
  agent_steps: int

  @property
  def train_mean(self) -> np.ndarray:
    """(K,) mean train return per agent."""
    return self.train.mean(axis=1)

  def mean(self, condition: str) -> np.ndarray:
    """(K,) mean return per agent under `condition`."""
    return self.returns[condition].mean(axis=1)

  def e_g(self, condition: str) -> np.ndarray:
    """(K,) E_G = (train − test) / train per agent (NaN where train is 0)."""
    return np.array([generalization_error(float(tr), float(te))
                     for tr, te in zip(self.train_mean, self.mean(condition))])

  def summary(self) -> dict:
    """The results as `dmcr_jax.protocol_report`'s summary (E_G NaN where undefined):
    per agent ("agents") its train return and each condition's mean, std,
    episodes and E_G (a moving condition's cell also its "factor" and
    "intensity"); "moving": those of every moving condition; "mean" over agents;
    the protocol's config and seeds."""
    from dmcr_jax import protocol_report
    agents = []
    for k, label in enumerate(self.labels):
      train = self.train[k]
      row = dict(agent=k, label=label, train_look=self.train_looks[k],
                 train=dict(mean=float(train.mean()), std=float(train.std()),
                            episodes=train.tolist()), conditions={})
      for c in self.conditions:
        r = self.returns[c][k]
        row["conditions"][c] = dict(mean=float(r.mean()), std=float(r.std()),
                                    episodes=r.tolist(),
                                    e_g=generalization_error(row["train"]["mean"],
                                                             float(r.mean())),
                                    **_moving_fields(c))
      agents.append(row)
    out = dict(task=self.task, conditions=list(self.conditions), config=dict(self.config),
               test_visual_seeds=self.test_visual_seeds.tolist(),
               train_look=", ".join(dict.fromkeys(self.train_looks)), device=self.device,
               wall_s=self.wall_s, compile_s=self.compile_s, agent_steps=self.agent_steps,
               agents=agents)
    out["moving"] = [dict(condition=c, **_moving_fields(c)) for c in self.conditions
                     if _moving_fields(c)]
    out["mean"] = protocol_report.mean_row(agents, self.conditions)
    out["augs"] = protocol_report.aug_groups(out)
    return out

  def to_json(self) -> str:
    """`summary()` as JSON text (an undefined E_G is null)."""
    from dmcr_jax import protocol_report
    return json.dumps(protocol_report.json_safe(self.summary()), indent=1, allow_nan=False)

  def markdown(self) -> str:
    """The table of returns per condition and E_G (`protocol_report.markdown`)."""
    from dmcr_jax import protocol_report
    return protocol_report.markdown(self.summary())

  def plot(self, path: str) -> None:
    """The bar chart of returns and E_G per condition (`protocol_report.plot`), a PNG."""
    from dmcr_jax import protocol_report
    protocol_report.plot(self.summary(), path)

  def write(self, out_dir: str) -> dict:
    """Writes eval.json, eval.md and eval.png into `out_dir` (made); returns the summary."""
    from dmcr_jax import protocol_report
    summary = self.summary()
    protocol_report.write(summary, out_dir)
    return summary


def _moving_fields(condition: str) -> dict:
  """{"factor", "intensity"} of a moving condition (`protocol_plan.moving_of`), else {}."""
  from dmcr_jax.protocol_plan import moving_of
  m = moving_of(condition)
  return {} if m is None else dict(factor=m[0], intensity=m[1])
