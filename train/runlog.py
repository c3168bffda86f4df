"""What a training run reports: its episode log, its progress, its segments and summary.

`RunLog` is the one place a run reports to between steps (or chunks): `report`
(a driver's step and its finished episodes) logs each episode (a row of
`<out>/log.csv`, flushed at once; the episodes' scalars to the run's other
sinks, `dmcr_jax.train.loggers`) and moves the progress (a tqdm bar on a
terminal, else a progress line on stderr every few percent); `evaluated` passes
an evaluation during training to those sinks; `checkpointed` records each
checkpoint (`<out>/segments.json`); `stopped` is the flag that SIGINT/SIGTERM
set.

log.csv has one row per finished episode: step, agent, seed, aug (and looks
with several training-look ranges), episode_return, episode_length (agent steps:
DMC episodes end at the task's time limit), wall_s, agent_steps_per_s
(transitions of all agents per second of this segment's loop), updates_per_s
(gradient updates of all agents per second of it) and the latest update means
(`METRICS`, and aux_loss for CURL and SAC+AE).

The log is the run's truth: a resumed run first drops the rows logged past
the checkpoint it restored (a killed process logs episodes after its last
checkpoint; they belong to a past that the run no longer has), so `step`
never goes backwards; `wall_s` counts the loop time of every segment so far
(the processes that trained the run: each a {"start", "steps", "wall_s",
"device"}, recorded in segments.json at each checkpoint, so a killed one is
kept up to its last checkpoint). `finish` writes summary.json (with every
segment) and learning_curve.png.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import sys
import time

import jax
import numpy as np

from dmcr_jax._files import json_safe  # noqa: F401 (re-exported)
from dmcr_jax._progress import progress_bar

PROGRESS_FRACTION = 0.02
"""`RunLog.due` reports progress at least every this fraction of a run's steps,
whatever `log_every` says, so a run shorter than `log_every` still shows
progress."""
SEGMENTS = "segments.json"
"""The file in a run folder listing its segments (module doc)."""
METRICS = ("critic_loss", "actor_loss", "alpha", "q")
"""The update metrics each log row carries (and "aux_loss" for CURL and SAC+AE)."""


def progress_every(cfg) -> int:
  """Steps between progress reports: `log_every`, at most `PROGRESS_FRACTION` of
  the run (at least 1)."""
  return max(1, min(cfg.log_every, int(cfg.steps * PROGRESS_FRACTION)))


def crossed(every: int, before: int, step: int) -> bool:
  """Whether `step` passed a multiple of `every` since `before` (0: never)."""
  return bool(every) and step // every != before // every


def read_json(path: str):
  """The JSON document in the file at `path`."""
  with open(path) as f:
    return json.load(f)


def earlier_segments(out_dir: str, start: int) -> list[dict]:
  """The segments of a run before a process that starts at step `start` (0: none):
  those in segments.json (or an older run's summary.json) that began before
  `start`, each ending at most at `start`."""
  if start <= 0:
    return []
  old = None
  for name in (SEGMENTS, "summary.json"):
    path = os.path.join(out_dir, name)
    if os.path.exists(path):
      old = read_json(path)
      break
  if old is None:
    return []
  if isinstance(old, dict):
    old = old.get("segments", [dict(start=None, steps=old.get("steps"),
                                    wall_s=old.get("wall_s"), device=None)])
  return [dict(s, steps=min(s["steps"], start)) for s in old
          if s.get("steps") is not None and (s.get("start") or 0) < start]


def log_header(path: str, fields: list[str]) -> list[str]:
  """The header of the log.csv at `path` made to hold `fields`: a log written
  before one of them existed is rewritten (atomically) with it, empty in its
  earlier rows. Returns the file's header: `fields`, then any other columns it
  has."""
  with open(path, newline="") as f:
    reader = csv.DictReader(f)
    old, rows = list(reader.fieldnames or []), list(reader)
  header = list(fields) + [c for c in old if c not in fields]
  if old and header != old:
    with open(path + ".tmp", "w", newline="") as f:
      writer = csv.DictWriter(f, fieldnames=header)
      writer.writeheader()
      writer.writerows(rows)
    os.replace(path + ".tmp", path)
  return header if old else list(fields)


def truncate_log(path: str, step: int) -> int:
  """Drops the rows of log.csv at `path` past training step `step` (rewritten
  atomically); the number dropped."""
  with open(path, newline="") as f:
    reader = csv.DictReader(f)
    fields, rows = reader.fieldnames, list(reader)
  keep = [r for r in rows if int(r["step"]) <= step]
  if len(keep) == len(rows):
    return 0
  with open(path + ".tmp", "w", newline="") as f:
    writer = csv.DictWriter(f, fieldnames=fields)
    writer.writeheader()
    writer.writerows(keep)
  os.replace(path + ".tmp", path)
  return len(rows) - len(keep)


class RunLog:
  """A run's reports between steps (module doc). A context manager: `close`
  restores the signal handlers and closes the log and the bar.

  Args:
    cfg: the run's `TrainConfig`.
    specs: (seed, augmentation) per agent; looks: each agent's training-look
      label when the run has several ranges, else None.
    start: the step the run starts at (a resumed run's checkpoint).
    resume: whether it continues a run (log.csv is then kept up to `start`).
    progress: show progress (a bar when stderr is a terminal, else lines).
    episode_length: agent steps per episode (the env's `episode_length`: the
      task's time limit at the run's action repeat), logged with each episode;
      None: not known, left empty.
  """

  def __init__(self, cfg, specs, looks, start: int, resume: bool, progress: bool,
               episode_length: int | None = None):
    self.cfg, self.specs, self.start = cfg, list(specs), start
    self.looks = None if looks is None else list(looks)
    self.episode_length = episode_length
    self.every = progress_every(cfg)
    self._last_line = None
    self.stop = {"signal": None}
    self._previous = {s: signal.signal(s, lambda sig, _: self.stop.update(signal=sig))
                      for s in (signal.SIGINT, signal.SIGTERM)}
    self.path = os.path.join(cfg.out_dir, "log.csv")
    self.metric_fields = list(METRICS) + (["aux_loss"] if cfg.sac.algo != "sac_aug" else [])
    self.fields = ["step", "agent", "seed", "aug", *(["looks"] if looks is not None else []),
                   "episode_return", "episode_length", "wall_s", "agent_steps_per_s",
                   "updates_per_s", *self.metric_fields]
    keep = resume and os.path.exists(self.path)
    if keep:  # an older run's log gains the columns added since
      self.fields = log_header(self.path, self.fields)
    if keep and truncate_log(self.path, start):
      print(f"{cfg.task}: dropped the log rows past step {start:,}, the checkpoint "
            "resumed from", file=sys.stderr, flush=True)
    self.before = earlier_segments(cfg.out_dir, start) if resume else []
    self.offset = sum(s.get("wall_s") or 0.0 for s in self.before)
    self._file = open(self.path, "a" if keep else "w", newline="")
    self._writer = csv.DictWriter(self._file, fieldnames=self.fields)
    if not keep:
      self._writer.writeheader()
    self._bar = None
    print(f"{cfg.task}: compiling the agents' act and update steps on the first steps "
          f"({jax.default_backend()}); this can take a minute or more on a CPU",
          file=sys.stderr, flush=True)
    self._bar = progress_bar(progress, total=cfg.steps, initial=start, desc=cfg.task,
                             unit="step")
    from dmcr_jax.train import loggers
    self.sinks = []
    try:
      self.sinks = loggers.open_loggers(cfg, self.specs, self.looks, start, resume)
    except BaseException:
      self.close()
      raise
    self.t0 = time.perf_counter()
    self.recent: list[float] = []

  @property
  def stopped(self) -> bool:
    """Whether SIGINT or SIGTERM arrived."""
    return self.stop["signal"] is not None

  def wall(self) -> float:
    """Seconds since this segment's loop started."""
    return time.perf_counter() - self.t0

  def episode(self, step: int, agent: int, episode_return: float, wall: float,
              metrics: dict, updates: int | None = None) -> dict:
    """One finished episode of `agent` at `step` (`wall`: this segment's seconds;
    metrics: name → (K,) latest update means; NaN entries, no update yet, are
    left out; updates: the gradient updates of all agents in this segment so
    far, None: not known, updates_per_s left empty); its log.csv row."""
    self.recent.append(episode_return)
    row = dict(step=step, agent=agent, seed=self.specs[agent][0], aug=self.specs[agent][1],
               episode_return=episode_return, wall_s=round(self.offset + wall, 2),
               **self.speeds(step, wall, updates))
    if self.episode_length is not None:
      row["episode_length"] = int(self.episode_length)
    if self.looks is not None:
      row["looks"] = self.looks[agent]
    for f in self.metric_fields:
      if f in metrics and np.isfinite(np.mean(metrics[f][agent])):
        row[f] = float(np.mean(metrics[f][agent]))
    self._writer.writerow(row)
    self._file.flush()
    if self._bar is not None and step > self._bar.n:
      self._bar.update(min(step, self.cfg.steps) - self._bar.n)
    return row

  def speeds(self, step: int, wall: float, updates: int | None = None) -> dict:
    """log.csv's speed fields at `step` after `wall` seconds of this segment:
    `agent_steps_per_s` (transitions of all agents per second) and, when the
    segment's `updates` are known, `updates_per_s` (four significant digits: a
    slow run's fraction of an update per second too)."""
    out = dict(agent_steps_per_s=round((step - self.start) * len(self.specs)
                                       / max(wall, 1e-9), 1))
    if updates is not None:
      out["updates_per_s"] = float(f"{updates / max(wall, 1e-9):.4g}")
    return out

  def report(self, before: int, step: int, episodes, updates: int | None = None,
             metrics: dict | None = None) -> None:
    """The one call a driver makes per step (or chunk) that moved the run from
    `before` to `step`: each finished episode (step, agent, return, update
    metrics) logged, the sinks given each agent's episodes per step
    (`dmcr_jax.train.loggers.episode_values`), then, when `due`, the progress and
    the sinks given every agent's latest update metrics and speeds at `step`
    (so the losses are logged every `log_every` steps, not only where episodes end).
    `updates`: the gradient updates all agents have run in this segment by
    `step` (the learner's count; None: not known). `metrics`: name → (K,) latest
    update means at `step` (None: not read at this step)."""
    from dmcr_jax.train.loggers import episode_values, perf_values, train_values
    wall = self.wall()
    ended: dict[tuple[int, int], list] = {}
    for at, agent, episode_return, episode_metrics in episodes:
      row = self.episode(at, agent, episode_return, wall, episode_metrics, updates)
      ended.setdefault((at, agent), []).append((row, episode_metrics))
    for (at, agent), done in ended.items():
      values = episode_values(done[-1][0], done[-1][1], agent,
                              [r["episode_return"] for r, _ in done])
      for sink in self.sinks:
        sink.scalars(agent, at, values)
    if self.due(before, step):
      self.progress(step)
      if metrics is not None:
        perf = perf_values(self.speeds(step, wall, updates))
        for agent in range(len(self.specs)):
          if (step, agent) not in ended:
            for sink in self.sinks:
              sink.scalars(agent, step, dict(perf, **train_values(metrics, agent)))

  def evaluated(self, rows) -> None:
    """An evaluation during training (`dmcr_jax.train.eval_curve.EvalCurve.evaluate`'s
    rows, one step) given to the sinks (`dmcr_jax.train.loggers.eval_values`)."""
    from dmcr_jax.train.loggers import eval_values
    if not rows:
      return
    step = int(rows[0]["step"])
    for agent, values in eval_values(rows).items():
      for sink in self.sinks:
        sink.scalars(agent, step, values)

  def due(self, before: int, step: int) -> bool:
    """Whether the loop should call `progress` after moving from `before` to `step`:
    every `every` steps (`log_every`, at most 2 % of the run) and at the end."""
    return crossed(self.every, before, step) or step >= self.cfg.steps

  def progress(self, step: int) -> None:
    """Flushes the log and moves the progress bar to `step` (without a bar, when
    progress is shown: a progress line on stderr)."""
    self._file.flush()
    sps = (step - self.start) * len(self.specs) / max(self.wall(), 1e-9)
    ret = f"{np.mean(self.recent[-10 * len(self.specs):]):.1f}" if self.recent else None
    done = min(step, self.cfg.steps)
    if self._bar is not None:
      self._bar.update(done - self._bar.n)
      self._bar.set_postfix(**({"ret": ret} if ret else {}), sps=f"{sps:.1f}")
    elif step != self._last_line:
      print(f"{self.cfg.task}: step {done:,}/{self.cfg.steps:,} "
            f"({100 * done / self.cfg.steps:.0f} %), {sps:.1f} transitions/s, "
            f"{self.wall():.0f} s" + (f", recent return {ret}" if ret else ""),
            file=sys.stderr, flush=True)
    self._last_line = step

  def segments(self, step: int) -> list[dict]:
    """Every segment of the run, this one up to `step`, oldest first."""
    return self.before + [dict(start=self.start, steps=step, wall_s=self.wall(),
                               device=jax.devices()[0].device_kind)]

  def checkpointed(self, step: int) -> None:
    """Records that checkpoint `step` was saved: segments.json then holds this
    segment up to it (what a resumed run continues)."""
    path = os.path.join(self.cfg.out_dir, SEGMENTS)
    with open(path + ".tmp", "w") as f:
      json.dump(json_safe(self.segments(step)), f, indent=1, allow_nan=False)
    os.replace(path + ".tmp", path)

  def close(self) -> None:
    for s, handler in self._previous.items():
      signal.signal(s, handler)
    self._file.close()
    for sink in self.sinks:
      sink.close()
    self.sinks = []
    if self._bar is not None:
      self._bar.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()


def agent_label(seed: int, aug: str, augs, looks: str | None = None) -> str:
  """How logs and plots name an agent: "seed 0", or "seed 0, cj+drq" when several
  augmentations are trained (then ", levels:10", its training looks, when given)."""
  label = f"seed {seed}" if len(augs) == 1 else f"seed {seed}, {aug}"
  return label if looks is None else f"{label}, {looks}"


def plot_learning_curve(log_path: str, png_path: str, specs, looks=None) -> dict:
  """Episode return against training step per agent (PNG).

  Episodes that end at the same step (the agent's N envs) are averaged into one
  point.

  Args:
    log_path: the run's log.csv.
    png_path: where the plot goes.
    specs: (seed, augmentation) per agent (`TrainConfig.agents`).
    looks: each agent's training looks (`look_label`) when the run has several
      ranges, else None.

  Returns:
    {agent label: mean return of the agent's episodes that ended last}.
  """
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  with open(log_path) as f:
    rows = list(csv.DictReader(f))
  augs = sorted({aug for _, aug in specs})
  fig, ax = plt.subplots(figsize=(6, 3.5))
  last = {}
  for a, (seed, aug) in enumerate(specs):
    look = None if looks is None else looks[a]
    by_step: dict[int, list[float]] = {}
    for r in rows:
      if int(r["agent"]) == a:
        by_step.setdefault(int(r["step"]), []).append(float(r["episode_return"]))
    if by_step:
      steps = sorted(by_step)
      means = [float(np.mean(by_step[t])) for t in steps]
      label = agent_label(seed, aug, augs, look)
      # Markers: a run with one finished episode per agent still shows its point.
      ax.plot(steps, means, marker="o", ms=4, label=label)
      last[label] = means[-1]
  ax.set_xlabel("training step (transitions per agent)")
  ax.set_ylabel("episode return")
  if last:
    ax.legend()
  fig.tight_layout()
  fig.savefig(png_path, dpi=100)
  plt.close(fig)
  return last


def finish(cfg, step: int, log: RunLog, extra: dict | None = None) -> dict:
  """The run's summary (also summary.json) and learning_curve.png.

  summary.json's `wall_s` is this process's loop time; `segments` lists every
  process of the run (module doc), `train_wall_s` their total; `extra` (a
  driver's timings) is added as it is."""
  segments = log.segments(step)
  summary = dict(task=cfg.task, seeds=list(cfg.seeds), augs=list(cfg.sac.aug_names),
                 steps=step, num_envs=cfg.num_envs, interrupted=log.stopped,
                 wall_s=log.wall(), segments=segments,
                 train_wall_s=sum(s["wall_s"] or 0.0 for s in segments),
                 **(extra or {}),
                 final_return=plot_learning_curve(log.path, os.path.join(
                     cfg.out_dir, "learning_curve.png"), log.specs, log.looks))
  if log.looks is not None:
    summary["looks"] = log.looks
  with open(os.path.join(cfg.out_dir, "summary.json"), "w") as f:
    json.dump(json_safe(summary), f, indent=1, allow_nan=False)
  return summary
