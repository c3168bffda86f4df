"""Evaluation during training: a reduced zero-shot protocol on the current agents every
`TrainConfig.eval_every` training steps, as a curve of held-out returns per condition.

`EvalCurve` builds the run's `dmcr_jax.protocol.Protocol` once (`build`: each
agent's greedy policy, `dmcr_jax.train.evaluate.greedy_policy`, at its training
looks; `eval_looks` held-out looks × `eval_dynamics` initial states per condition,
`eval_train_episodes` at the training looks; the protocol's seed is the run's first
seed, so every evaluation of a run meets the same looks and initial states and the
curve shows the agents change, not the sampling). `due` says when the loop
evaluates: at each multiple of `eval_every` a step crosses, and once at the last
step when no multiple fell there. Each evaluation appends one row per (step,
agent, condition) to `<out>/eval_curve.csv` (`FIELDS`: the mean held-out return,
the agent's train return and E_G = (train − test) / train, and the evaluation's
wall seconds) and prints one line on stderr; `plot` draws `<out>/eval_curve.png`
(one panel per agent: each condition's return and the train return against the
training step, where the generalisation gap opens). A resumed run first drops the
rows past the checkpoint it restored, as the episode log does
(`dmcr_jax.train.runlog.truncate_log`).
"""

from __future__ import annotations

import csv
import os
import sys
import time

import numpy as np

from dmcr_jax.train import runlog

CSV = "eval_curve.csv"
"""The curve's file in a run folder."""
PNG = "eval_curve.png"
"""The curve's plot in a run folder."""
FIELDS = ("step", "agent", "label", "condition", "mean_return", "train_return", "e_g",
          "eval_s")
"""The columns of eval_curve.csv: training step per agent, agent index and label,
condition, mean held-out return, the agent's train return, E_G (empty where the
train return is 0), and the wall seconds of the evaluation the row came from."""


def build(plan):
  """The run's reduced `dmcr_jax.protocol.Protocol` (host work only; nothing compiles).

  Args:
    plan: the run's `dmcr_jax.train.config.Plan` (K agents and their looks).

  Returns:
    The protocol for params with a leading axis of K agents
    (`dmcr_jax.train.evaluate.policy_params`).
  """
  from dmcr_jax import protocol
  from dmcr_jax.train.evaluate import greedy_policy
  cfg = plan.cfg
  render = dict(quality=cfg.quality, workers=cfg.workers,
                egl_devices=cfg.egl_devices) if cfg.eval_renderer == "pool" else {}
  return protocol.prepare(
      cfg.task, greedy_policy, agents=len(plan.agents), renderer=cfg.eval_renderer,
      visual_seeds=cfg.eval_looks, dynamics_seeds=cfg.eval_dynamics,
      train_episodes=cfg.eval_train_episodes, conditions=cfg.eval_conditions,
      train_look=list(plan.agent_looks), train_vary=cfg.vary, seed=int(cfg.seeds[0]),
      image_size=cfg.image_size, frame_stack=cfg.frame_stack,
      action_repeat=cfg.action_repeat, **render)


def agent_labels(plan) -> list[str]:
  """Each agent's name in the curve (`dmcr_jax.train.runlog.agent_label`)."""
  augs = sorted({aug for _, aug in plan.agents})
  looks = plan.look_labels or [None] * len(plan.agents)
  return [runlog.agent_label(seed, aug, augs, look)
          for (seed, aug), look in zip(plan.agents, looks)]


def rows(step: int, results, labels, eval_s: float) -> list[dict]:
  """eval_curve.csv's rows (`FIELDS`) of one evaluation's `dmcr_jax.protocol.Results`."""
  out = []
  train = results.train_mean
  for c in results.conditions:
    means, e_g = results.mean(c), results.e_g(c)
    for a, label in enumerate(labels):
      out.append(dict(step=int(step), agent=a, label=label, condition=c,
                      mean_return=round(float(means[a]), 4),
                      train_return=round(float(train[a]), 4),
                      e_g="" if not np.isfinite(e_g[a]) else round(float(e_g[a]), 4),
                      eval_s=round(eval_s, 3)))
  return out


class EvalCurve:
  """A run's evaluations during training (module doc); inert when `eval_every` is 0
  or None.
  A context manager: `close` closes the CSV.

  Args:
    plan: the run's `Plan`.
    start: the step the run starts at (a resumed run's checkpoint).
    resume: whether it continues a run (eval_curve.csv is then kept up to `start`).
  """

  def __init__(self, plan, start: int, resume: bool):
    cfg = plan.cfg
    self.cfg, self.every, self.seconds, self.last = cfg, int(cfg.eval_every or 0), 0.0, None
    self.path = os.path.join(cfg.out_dir, CSV)
    self._file = None
    if not self.every:
      return
    self.protocol = build(plan)
    self.labels = agent_labels(plan)
    self.agents = len(plan.agents)
    keep = resume and os.path.exists(self.path)
    if keep and runlog.truncate_log(self.path, start):
      print(f"{cfg.task}: dropped the eval curve's rows past step {start:,}, the "
            "checkpoint resumed from", file=sys.stderr, flush=True)
    self._file = open(self.path, "a" if keep else "w", newline="")
    self._writer = csv.DictWriter(self._file, fieldnames=FIELDS)
    if not keep:
      self._writer.writeheader()
      self._file.flush()

  def due(self, before: int, step: int) -> bool:
    """Whether the loop evaluates after moving from `before` to `step`: a multiple of
    `eval_every` crossed, or the run's last step not yet evaluated."""
    if not self.every:
      return False
    return (runlog.crossed(self.every, before, step)
            or (step >= self.cfg.steps and self.last != step))

  def evaluate(self, step: int, agents) -> list[dict]:
    """Runs the protocol on `agents` (the learner's, leading axis K) at `step`;
    appends its rows to the CSV and prints one line on stderr; the rows."""
    from dmcr_jax.train.evaluate import policy_params
    t0 = time.perf_counter()
    results = self.protocol(policy_params(agents, list(range(self.agents))),
                            labels=self.labels)
    eval_s = time.perf_counter() - t0
    self.seconds += eval_s
    self.last = step
    new = rows(step, results, self.labels, eval_s)
    self._writer.writerows(new)
    self._file.flush()
    means = ", ".join(f"{c} {float(np.mean(results.mean(c))):.1f}" for c in results.conditions)
    print(f"eval at step {step:,}: {means} ({eval_s:.1f} s)", file=sys.stderr, flush=True)
    return new

  def summary(self) -> dict:
    """summary.json's "eval_seconds": this process's seconds of evaluation."""
    return dict(eval_seconds=self.seconds) if self.every else {}

  def close(self) -> None:
    """Closes the CSV and draws the PNG (when the CSV holds rows)."""
    if self._file is None:
      return
    self._file.close()
    self._file = None
    plot(self.path, os.path.join(self.cfg.out_dir, PNG))

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()


def step_panels(count: int, cols: int):
  """(figure, the first `count` axes) of a grid of panels of return against training
  step, at most `cols` wide, sharing their y axis; `save_panels` finishes it."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  cols = min(count, cols)
  rows = -(-count // cols)
  fig, axes = plt.subplots(rows, cols, figsize=(4.4 * cols, 3.2 * rows), squeeze=False,
                           sharey=True)
  for ax in list(axes.flat)[count:]:
    ax.axis("off")
  for ax in list(axes.flat)[:count]:
    ax.set_xlabel("training step (transitions per agent)")
    ax.set_ylabel("mean return")
  return fig, list(axes.flat)[:count]


def save_panels(fig, axes, png_path: str) -> None:
  """Writes a `step_panels` figure to `png_path` (the legend in its first panel)."""
  import matplotlib.pyplot as plt
  axes[0].legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(png_path, dpi=100)
  plt.close(fig)


def plot(csv_path: str, png_path: str) -> bool:
  """eval_curve.png from eval_curve.csv: one panel per agent, the mean return of
  each condition (and the train return, dashed) against the training step.

  Returns:
    Whether a plot was written (False when the CSV holds no rows).
  """
  with open(csv_path, newline="") as f:
    data = list(csv.DictReader(f))
  if not data:
    return False
  agents = sorted({int(r["agent"]) for r in data})
  conditions = list(dict.fromkeys(r["condition"] for r in data))
  fig, axes = step_panels(len(agents), cols=3)
  for ax, a in zip(axes, agents):
    mine = [r for r in data if int(r["agent"]) == a]
    for c in conditions:
      pts = sorted((int(r["step"]), float(r["mean_return"])) for r in mine
                   if r["condition"] == c)
      ax.plot(*zip(*pts), marker="o", ms=3, label=c)
    train = sorted({(int(r["step"]), float(r["train_return"])) for r in mine})
    ax.plot(*zip(*train), "k--", marker="s", ms=3, label="train")
    ax.set_title(mine[0]["label"], fontsize=9)
  save_panels(fig, axes, png_path)
  return True
