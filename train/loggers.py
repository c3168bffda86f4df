"""Where a training run's curves go besides log.csv: TensorBoard event files and Weights & Biases.

`TrainConfig.loggers` (`dmcr-train --logger csv,tensorboard,wandb`) names the sinks;
"csv" is always among them: it is the run's `log.csv` (and `eval_curve.csv`), written
by `dmcr_jax.train.runlog.RunLog` and `dmcr_jax.train.eval_curve` as the run's truth
(a resumed run continues from it). `open_loggers` makes the other sinks from the
config at one place, and `RunLog` is their only caller: each sink is a `Logger`
(scalars of one agent at a training step, that agent's hyperparameters, close).

What is written, per agent, against the training step per agent (transitions):

- at every step where episodes of the agent end: `episode/return` (the mean return of
  the agent's episodes that ended there, its N envs ending together; log.csv holds
  each), `episode/length` (their length in agent steps: DMC episodes end at the
  task's time limit, so it is the env's `episode_length`, the time limit in
  control steps over the action repeat), the latest update means
  `train/critic_loss`, `train/actor_loss`, `train/alpha_loss`, `train/alpha`,
  `train/q`, `train/entropy` (−mean log π), `train/lam_loss` and `train/aux_loss`
  where the learner has them (once updates have run), `perf/transitions_per_s`
  (transitions of all agents per second of this process's loop, log.csv's
  `agent_steps_per_s`) and `perf/updates_per_s` (gradient updates of all agents
  per second of that loop, counted by the learner: `sac.AgentState.step`; 0
  during the warm-up; log.csv's `updates_per_s`);
- every `log_every` steps (when the progress moves), for every agent whose episodes
  did not end there: the same `train/*` update means and `perf/*` speeds, so the
  losses are logged between episodes too (`RunLog.report`);
- at each evaluation during training (`--eval-every`): `eval/<condition>` (the mean
  held-out return), `eval/train` (the return at the agent's training looks) and
  `eval/e_g/<condition>` (E_G, where defined);
- once: the run's config (flattened, `sac.aug` …) and the agent's seed,
  augmentation and training looks as hyperparameters.

K agents are K runs (`run_names`: "agent_0-seed_0-drq", …), not K tag prefixes:
TensorBoard draws runs of one tag in one chart, in its own colours, and W&B
overlays the runs of a group in one panel and can average them over seeds, so
agents compare at a glance; with tag prefixes each agent would get its own chart.
TensorBoard: one folder per agent under `<out>/tensorboard/`. W&B: one run per
agent, grouped by WANDB_RUN_GROUP or else the run folder's name (`dmcr-sweep` groups
a method's runs across seeds), in project WANDB_PROJECT (default "dmcr_jax"), files
under `<out>/wandb/`; mode WANDB_MODE when set, else
"online" with an API key (WANDB_API_KEY or `wandb login`'s netrc entry), else
"offline" (`wandb sync <out>/wandb/offline-run-*` uploads it later).

Resume: the TensorBoard folders are the same, and their writer purges the events
past the restored checkpoint (`purge_step`, as log.csv drops its rows); the W&B
runs' ids are kept in `<out>/wandb_runs.json` and resumed (`resume="allow"`),
each logging against its own `step` metric so a resumed segment's steps need not
exceed the last ones logged.
"""

from __future__ import annotations

import dataclasses
import json
import math
import netrc
import os
import sys
import time
from typing import Protocol

LOGGERS = ("csv", "tensorboard", "wandb")
"""What `TrainConfig.loggers` accepts."""
PACKAGES = {"tensorboard": ("tensorboardX", "tensorboard"), "wandb": ("wandb", "wandb")}
"""Logger → (the module it imports, the dmcr_jax extra that installs it)."""
TRAIN_METRICS = ("critic_loss", "actor_loss", "alpha_loss", "alpha", "q", "entropy",
                 "lam_loss", "aux_loss")
"""The learner's update metrics a sink writes as `train/<name>` (those it has)."""
TENSORBOARD_DIR = "tensorboard"
"""The folder of a run's event files (one subfolder per agent)."""
WANDB_RUNS = "wandb_runs.json"
"""The file in a run folder holding its W&B run ids, one per agent."""


class Logger(Protocol):
  """A sink for one run's K agents (module doc)."""

  def scalars(self, agent: int, step: int, values: dict[str, float]) -> None:
    """Writes `values` (tag → float) of `agent` at training step `step`."""

  def hparams(self, agent: int, values: dict) -> None:
    """Writes `agent`'s hyperparameters (name → bool, int, float or str)."""

  def close(self) -> None:
    """Flushes and closes every agent's writer."""


def parse_loggers(text: str) -> tuple[str, ...]:
  """`--logger`'s comma-separated names as `TrainConfig.loggers`: "csv" first
  (always written), then the others given, each once.

  Raises:
    ValueError: an unknown name, naming the valid choices.
  """
  names = [p.strip() for p in str(text).split(",") if p.strip()]
  check_names(names)
  return ("csv",) + tuple(n for n in dict.fromkeys(names) if n != "csv")


def check_names(names) -> None:
  """ValueError naming the valid choices for any name not in `LOGGERS`."""
  if isinstance(names, str):
    raise ValueError(f"loggers must be a tuple of names, e.g. ('csv', 'tensorboard'), got "
                     f"{names!r}")
  bad = [n for n in names if n not in LOGGERS]
  if bad:
    raise ValueError(f"logger {', '.join(map(repr, bad))} unknown; valid: "
                     f"{', '.join(LOGGERS)} (comma-separated; csv is always written)")


def check_loggers(names) -> None:
  """ValueError for an unknown name, or for a logger whose package is not installed
  (saying which extra installs it); nothing is created."""
  import importlib.util
  check_names(names)
  for name in names:
    if name in PACKAGES:
      module, extra = PACKAGES[name]
      if importlib.util.find_spec(module) is None:
        raise ValueError(f"logger {name!r} needs the {module} package, which is not "
                         f"installed: pip install 'dmcr-jax[{extra}]' (or pip install "
                         f"{module}), or drop {name} from --logger")


def run_names(specs, looks=None) -> list[str]:
  """Each agent's run name (a folder name): "agent_<k>-seed_<s>-<aug>" and
  "-levels_<n>" when the run has several training-look ranges."""
  names = []
  for k, (seed, aug) in enumerate(specs):
    parts = [f"agent_{k}", f"seed_{seed}", str(aug)]
    if looks is not None:
      parts.append(str(looks[k]))
    names.append("-".join(p.replace(" ", "_").replace(":", "_").replace("/", "_")
                          for p in parts))
  return names


def flat_config(cfg) -> dict:
  """`cfg` (a `TrainConfig`) as flat hyperparameters: nested fields joined by "."
  (`sac.aug`), tuples and None as their text."""
  out = {}

  def walk(prefix, value):
    if isinstance(value, dict):
      for k, v in value.items():
        walk(f"{prefix}{k}.", v)
    elif isinstance(value, (bool, int, float, str)):
      out[prefix[:-1]] = value
    else:
      out[prefix[:-1]] = str(value)

  walk("", dataclasses.asdict(cfg))
  return out


def agent_hparams(cfg, specs, looks=None) -> list[dict]:
  """Each agent's hyperparameters: `flat_config` with its seed, augmentation and
  training looks (`agent.seed`, `agent.aug`, `agent.looks`)."""
  base = flat_config(cfg)
  return [dict(base, **{"agent.index": k, "agent.seed": int(seed), "agent.aug": str(aug),
                        "agent.looks": str(cfg.visual_seeds if looks is None else looks[k])})
          for k, (seed, aug) in enumerate(specs)]


def episode_values(row: dict, metrics: dict, agent: int, returns: list[float]) -> dict:
  """The scalars of an agent's episodes that ended at one step: `returns` (their
  returns, log.csv's rows) averaged, the row's episode length (agent steps),
  transitions and gradient updates per second (each where the row has it), and
  the learner's update metrics (name → (K,) means; NaN ones left out)."""
  import numpy as np
  values = {"episode/return": float(np.mean(returns)), **perf_values(row)}
  if row.get("episode_length", "") != "":
    values["episode/length"] = float(row["episode_length"])
  return dict(values, **train_values(metrics, agent))


def perf_values(row: dict) -> dict:
  """A log.csv row's speeds (`RunLog.speeds`) as `perf/transitions_per_s` and, where
  the row has it, `perf/updates_per_s`."""
  values = {"perf/transitions_per_s": float(row["agent_steps_per_s"])}
  if row.get("updates_per_s", "") != "":
    values["perf/updates_per_s"] = float(row["updates_per_s"])
  return values


def train_values(metrics: dict, agent: int) -> dict:
  """The learner's latest update means of one agent as `train/<name>` scalars
  (metrics: name → (K,) means; NaN ones, no update yet, left out)."""
  import numpy as np
  values = {}
  for name in TRAIN_METRICS:
    if name in metrics:
      v = float(np.mean(metrics[name][agent]))
      if math.isfinite(v):
        values[f"train/{name}"] = v
  return values


def eval_values(rows) -> dict[int, dict[str, float]]:
  """One evaluation's rows (`dmcr_jax.train.eval_curve.rows`) as scalars per agent:
  `eval/<condition>`, `eval/train` and `eval/e_g/<condition>` (where defined)."""
  out: dict[int, dict[str, float]] = {}
  for r in rows:
    values = out.setdefault(int(r["agent"]), {})
    values[f"eval/{r['condition']}"] = float(r["mean_return"])
    values["eval/train"] = float(r["train_return"])
    if r["e_g"] != "":
      values[f"eval/e_g/{r['condition']}"] = float(r["e_g"])
  return out


class TensorBoardLogger:
  """Event files of one run, one folder per agent under `<out>/tensorboard/`
  (tensorboardX). A resumed run appends to the same folders, and TensorBoard drops
  the earlier events at `purge_step` (the step after the restored checkpoint) and
  past it."""

  def __init__(self, out_dir: str, names: list[str], purge_step: int | None = None):
    from tensorboardX import SummaryWriter
    self.root = os.path.join(out_dir, TENSORBOARD_DIR)
    # A suffix of its own per writer: the event file's name otherwise holds only the
    # second it was made, and a resumed segment started within that second would
    # write over the earlier segment's file (names sort in the order they were made).
    suffix = f".{time.time_ns()}.{os.getpid()}"
    self.writers = [SummaryWriter(os.path.join(self.root, n), purge_step=purge_step,
                                  flush_secs=30, filename_suffix=suffix) for n in names]

  def scalars(self, agent, step, values):
    w = self.writers[agent]
    for tag, v in values.items():
      w.add_scalar(tag, v, int(step))

  def hparams(self, agent, values):
    from tensorboardX.summary import hparams
    metrics = {"episode/return": math.nan, "eval/all": math.nan}
    writer = self.writers[agent].file_writer
    for summary in hparams(values, metrics):  # in this agent's run, beside its scalars
      writer.add_summary(summary)

  def close(self):
    for w in self.writers:
      w.close()


def wandb_mode(environ=None, netrc_path: str | None = None) -> str:
  """W&B's mode for a run: WANDB_MODE when set; else "online" where an API key is
  known (WANDB_API_KEY, or a netrc entry for api.wandb.ai as `wandb login` writes);
  else "offline"."""
  environ = os.environ if environ is None else environ
  if environ.get("WANDB_MODE"):
    return environ["WANDB_MODE"]
  if environ.get("WANDB_API_KEY"):
    return "online"
  path = netrc_path or environ.get("NETRC") or os.path.expanduser("~/.netrc")
  try:
    host = environ.get("WANDB_BASE_URL", "https://api.wandb.ai").split("://")[-1]
    if os.path.exists(path) and netrc.netrc(path).authenticators(host.split("/")[0]):
      return "online"
  except (OSError, netrc.NetrcParseError):
    pass
  return "offline"


class WandbLogger:
  """One W&B run per agent (module doc), grouped by the run folder's name; ids kept
  in `<out>/wandb_runs.json` and resumed by a resumed run."""

  def __init__(self, out_dir: str, names: list[str], hparams: list[dict], resume: bool):
    import wandb
    self.mode = wandb_mode()
    path = os.path.join(out_dir, WANDB_RUNS)
    ids = {}
    if resume and os.path.exists(path):
      with open(path) as f:
        ids = json.load(f)
    group = os.environ.get("WANDB_RUN_GROUP") or os.path.basename(os.path.abspath(out_dir))
    project = os.environ.get("WANDB_PROJECT", "dmcr_jax")
    self.runs = []
    for k, name in enumerate(names):
      run = wandb.init(project=project, group=group, name=f"{group}/{name}",
                       id=ids.get(str(k)), resume="allow" if str(k) in ids else None,
                       dir=out_dir, mode=self.mode, config=hparams[k],
                       reinit="create_new",
                       settings=wandb.Settings(console="off", silent=True))
      run.define_metric("step")
      run.define_metric("*", step_metric="step")
      self.runs.append(run)
    with open(path + ".tmp", "w") as f:
      json.dump({str(k): r.id for k, r in enumerate(self.runs)}, f, indent=1)
    os.replace(path + ".tmp", path)
    where = os.path.join(out_dir, "wandb")
    print(f"wandb: {len(self.runs)} run{'s' if len(self.runs) > 1 else ''} ({self.mode}) "
          f"in project {project!r}, group {group!r}"
          + (f"; upload later with: wandb sync {where}/offline-run-*"
             if self.mode == "offline" else ""), file=sys.stderr, flush=True)

  def scalars(self, agent, step, values):
    self.runs[agent].log(dict(values, step=int(step)))

  def hparams(self, agent, values):
    self.runs[agent].config.update(values, allow_val_change=True)

  def close(self):
    """Finishes the runs, then W&B's service process of this one, which writes the
    last run's records to its file only as it ends (the files are complete when
    `close` returns; a later `wandb.init` starts a new service)."""
    import wandb
    for run in self.runs:
      run.finish()
    self.runs = []
    wandb.teardown()


def open_loggers(cfg, specs, looks, start: int, resume: bool) -> list[Logger]:
  """The sinks `cfg.loggers` names besides csv (checked by `check_loggers` with the
  config), each given every agent's hyperparameters.

  Args:
    cfg: the run's `TrainConfig`.
    specs: (seed, augmentation) per agent; looks: each agent's training-look label
      when the run has several ranges, else None.
    start: the step the run starts at; resume: whether it continues a run.
  """
  names = run_names(specs, looks)
  hp = agent_hparams(cfg, specs, looks)
  sinks: list[Logger] = []
  try:
    for name in getattr(cfg, "loggers", ("csv",)):
      if name == "tensorboard":
        # Events past the restored checkpoint are dropped (log.csv keeps step `start`).
        sinks.append(TensorBoardLogger(cfg.out_dir, names, start + 1 if resume else None))
      elif name == "wandb":
        sinks.append(WandbLogger(cfg.out_dir, names, hp, resume))
        continue  # its config came with the runs
      else:
        continue
      for k, values in enumerate(hp):
        sinks[-1].hparams(k, values)
  except BaseException:
    for s in sinks:
      s.close()
    raise
  return sinks
