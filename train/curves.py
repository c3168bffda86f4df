"""Learning curves of several training runs, compared at equal transition counts.

Used to check that a change to how training collects its data (more envs per
agent, a policy one step stale, …) leaves learning as it was: run the old and
the new setting with the same seeds, then

    python -m dmcr_jax.train.curves --out cmp old=runs/cartpole-16 new=runs/cartpole-32

Each ``LABEL=RUN`` names a `train` run folder (or its log.csv); every agent of
the run is one seed of that label, and several runs may share a label (seeds
trained in separate processes). Episodes are binned by the training step
(transitions per agent) at which they ended into `bins` windows of equal width
over the steps every run reached. Per window and label:

- each agent's mean return over its episodes in the window;
- the label's mean over its agents, and their spread (max − min): the seed noise;
- for every label after the first, its difference from the first label's mean,
  and whether it is within seed noise: |difference| ≤ the larger of the two
  labels' spreads (with one agent per label the spread is 0, so only equal
  curves pass: run two seeds at least).

Writes ``curves.png`` (each label's mean, and its agents thin), ``curves.json``
and ``curves.md`` into `--out`, and prints the table.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import sys
import warnings

import numpy as np


def read_log(path: str) -> list[dict]:
  """A run's log.csv rows: step (int), agent (int), episode_return (float).

  Args:
    path: a `train` run folder or its log.csv.

  Raises:
    ValueError: no log.csv there, or one without the needed columns.
  """
  log = os.path.join(path, "log.csv") if os.path.isdir(path) else path
  if not os.path.isfile(log):
    raise ValueError(f"{path}: no log.csv (give a train run folder or its log.csv)")
  with open(log) as f:
    reader = csv.DictReader(f)
    missing = {"step", "agent", "episode_return"} - set(reader.fieldnames or ())
    if missing:
      raise ValueError(f"{log}: not a train log (missing columns {sorted(missing)})")
    return [dict(step=int(r["step"]), agent=int(r["agent"]),
                 episode_return=float(r["episode_return"])) for r in reader]


def agent_returns(runs: list[list[dict]]) -> list[tuple[np.ndarray, np.ndarray]]:
  """(steps, returns) of every agent of `runs` (runs' log rows), run by run."""
  out = []
  for rows in runs:
    for agent in sorted({r["agent"] for r in rows}):
      mine = [r for r in rows if r["agent"] == agent]
      out.append((np.array([r["step"] for r in mine]),
                  np.array([r["episode_return"] for r in mine], np.float64)))
  return out


def window_means(steps: np.ndarray, returns: np.ndarray, edges: np.ndarray) -> np.ndarray:
  """Mean return of the episodes ending in each window (edges[i], edges[i+1]];
  NaN where none ended (the first window also takes step edges[0])."""
  index = np.searchsorted(edges, steps, side="left") - 1
  index[steps == edges[0]] = 0
  means = np.full(len(edges) - 1, np.nan)
  for i in range(len(edges) - 1):
    hit = index == i
    if hit.any():
      means[i] = returns[hit].mean()
  return means


def compare(labelled_runs: dict[str, list[list[dict]]], bins: int = 10) -> dict:
  """The comparison of the module docstring.

  Args:
    labelled_runs: label → the log rows of each of its runs (the first label is
      the reference).
    bins: the number of windows.

  Returns:
    {"edges": window edges (steps), "labels": {label: {"agents": per-agent window
    means, "mean", "spread"}}, "diff": {label: {"delta", "within_noise"}}} (lists;
    NaN where a window has no episode).
  """
  if not labelled_runs:
    raise ValueError("no runs to compare")
  agents = {label: agent_returns(runs) for label, runs in labelled_runs.items()}
  for label, curves in agents.items():
    if not curves or all(len(s) == 0 for s, _ in curves):
      raise ValueError(f"{label}: no finished episode in its logs")
  end = min(int(s.max()) for curves in agents.values() for s, _ in curves if len(s))
  start = min(int(s.min()) for curves in agents.values() for s, _ in curves if len(s))
  edges = np.linspace(start, end, bins + 1)
  out = {"edges": edges.tolist(), "labels": {}, "diff": {}}
  for label, curves in agents.items():
    per_agent = np.array([window_means(s, r, edges) for s, r in curves])
    with warnings.catch_warnings():  # all-NaN windows stay NaN, quietly
      warnings.simplefilter("ignore", RuntimeWarning)
      mean = np.nanmean(per_agent, axis=0)
      spread = np.nanmax(per_agent, axis=0) - np.nanmin(per_agent, axis=0)
    out["labels"][label] = dict(agents=per_agent.tolist(), mean=mean.tolist(),
                                spread=spread.tolist())
  first = next(iter(agents))
  ref = out["labels"][first]
  for label in list(agents)[1:]:
    mine = out["labels"][label]
    delta = np.array(mine["mean"]) - np.array(ref["mean"])
    noise = np.maximum(np.array(mine["spread"]), np.array(ref["spread"]))
    out["diff"][label] = dict(delta=delta.tolist(),
                              within_noise=[bool(abs(d) <= n) if np.isfinite(d) else None
                                            for d, n in zip(delta, noise)])
  return out


def markdown(result: dict) -> str:
  """The comparison as one Markdown table: a row per window in which an episode of
  some run ended (the others are counted below the table), then each label's count
  of windows within seed noise."""
  labels = list(result["labels"])
  first = labels[0]
  head = ["steps"] + [f"{label} mean (spread)" for label in labels]
  head += [f"{label} − {first}" for label in labels[1:]]
  lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  edges = result["edges"]
  fmt = lambda v: "–" if not np.isfinite(v) else f"{v:.1f}"
  empty = 0
  for i in range(len(edges) - 1):
    if not any(np.isfinite(result["labels"][label]["mean"][i]) for label in labels):
      empty += 1
      continue
    cells = [f"{edges[i]:,.0f}–{edges[i + 1]:,.0f}"]
    for label in labels:
      curve = result["labels"][label]
      cells.append(f"{fmt(curve['mean'][i])} ({fmt(curve['spread'][i])})")
    for label in labels[1:]:
      d = result["diff"][label]
      ok = d["within_noise"][i]
      cells.append(fmt(d["delta"][i]) + ("" if ok is None else
                                          " (within noise)" if ok else " (**outside**)"))
    lines.append("| " + " | ".join(cells) + " |")
  if empty:
    lines.append(f"\n{empty} of {len(edges) - 1} windows, in which no run ended an episode, are "
                 "not shown (a run's envs may end their episodes together).")
  for label in labels[1:]:
    flags = [f for f in result["diff"][label]["within_noise"] if f is not None]
    single = [lb for lb in (first, label) if len(result["labels"][lb]["agents"]) < 2]
    caveat = (f" One seed for {' and '.join(single)}: no spread to measure noise by, so "
              "every difference is flagged." if single else "")
    lines.append(f"\n{label} against {first}: {sum(flags)} of {len(flags)} windows within "
                 "seed noise (|difference of means| ≤ the larger spread over seeds)." + caveat)
  return "\n".join(lines) + "\n"


def plot(result: dict, path: str) -> None:
  """Each label's mean return per window (thick) and its agents' (thin), PNG."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  edges = np.array(result["edges"])
  mid = 0.5 * (edges[1:] + edges[:-1])
  fig, ax = plt.subplots(figsize=(6, 3.5))
  def line(values, **style):  # joined over windows without an episode (NaN)
    values = np.asarray(values, float)
    seen = np.isfinite(values)
    ax.plot(mid[seen], values[seen], **style)
  for i, (label, curve) in enumerate(result["labels"].items()):
    color = f"C{i}"
    for agent in curve["agents"]:
      line(agent, color=color, lw=0.7, alpha=0.5)
    seeds = len(curve["agents"])
    line(curve["mean"], color=color, lw=2, marker="o", ms=3,
         label=f"{label} ({seeds} seed{'s' if seeds != 1 else ''})")
  ax.set_xlabel("training step (transitions per agent)")
  ax.set_ylabel("episode return")
  ax.legend()
  fig.tight_layout()
  fig.savefig(path, dpi=100)
  plt.close(fig)


def parse_runs(specs: list[str]) -> dict[str, list[str]]:
  """``LABEL=PATH`` arguments → label → paths, in order of first appearance."""
  runs: dict[str, list[str]] = {}
  for spec in specs:
    label, sep, path = spec.partition("=")
    if not sep or not label or not path:
      raise ValueError(f"{spec!r}: give runs as LABEL=RUN_DIR (e.g. old=runs/cartpole-16)")
    runs.setdefault(label, []).append(path)
  return runs


def main(argv=None) -> None:
  """Command-line entry (module docstring)."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.train.curves",
                              description=__doc__.splitlines()[0])
  p.add_argument("runs", nargs="+", metavar="LABEL=RUN",
                 help="a train run folder (or log.csv) under a label; the first label is "
                      "the reference; repeat a label for seeds trained apart")
  p.add_argument("--bins", type=int, default=10, help="windows (default: %(default)s)")
  p.add_argument("--out", default=None, help="folder for curves.png/.json/.md (default: "
                 "only print the table)")
  a = p.parse_args(argv)
  if a.bins < 1:
    p.error(f"--bins must be ≥ 1, got {a.bins}")
  try:
    paths = parse_runs(a.runs)
    logs = {label: [read_log(path) for path in group] for label, group in paths.items()}
    result = compare(logs, a.bins)
  except ValueError as e:
    p.error(str(e))
  table = markdown(result)
  print(table, end="")
  if a.out:
    os.makedirs(a.out, exist_ok=True)
    result["runs"] = paths
    with open(os.path.join(a.out, "curves.json"), "w") as f:
      json.dump(result, f, indent=1)
    with open(os.path.join(a.out, "curves.md"), "w") as f:
      f.write(f"`python -m dmcr_jax.train.curves {shlex.join(sys.argv[1:] if argv is None else argv)}`"
              "\n\n" + table)
    plot(result, os.path.join(a.out, "curves.png"))


if __name__ == "__main__":
  main()
