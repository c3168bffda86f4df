"""Several runs' evaluations during training drawn together, per range of training looks.

Held-out return against training steps per range of training looks (and
augmentation): where one sees whether and when agents of many looks overtake those
of one.

    python -m dmcr_jax.benchmarks.eval_curves runs/few_shot_long/cartpole-balance-* --out runs/few_shot_long

Each run folder holds the `eval_curve.csv` of `dmcr-train --eval-every`
(`dmcr_jax.train.eval_curve`). The agents of all the runs of one task are grouped
by (augmentation, training looks); a group's seeds (from one run or several) give
per evaluated step the mean and the min–max of each condition's held-out return
and of the train return (at the agent's own looks), over the steps every seed of
the group was evaluated at. The runs of a task must share their reduced protocol
(`PROTOCOL`) and conditions, else they are refused naming the difference.
Per task: ``<out>/eval_curves_<task>.png`` (one panel for the train return and one
per condition, one line per group, the min–max as a band), ``.md`` (each panel's
values as a table) and ``.json`` (the groups' series). `dmcr-sweep` writes them
beside its table for every task with evaluated runs of more than one group.
"""

from __future__ import annotations

import argparse
import csv
import json
import os

import numpy as np

from dmcr_jax.train import config, eval_curve

PROTOCOL = ("eval_looks", "eval_dynamics", "eval_train_episodes", "eval_renderer")
"""The `TrainConfig` fields of the reduced protocol that runs drawn together share."""
TRAIN = "train"
"""The panel of the train return (at each agent's own training looks)."""


def read_run(run_dir: str) -> tuple[config.TrainConfig, list[dict]]:
  """A run's config and eval_curve.csv rows.

  Raises:
    ValueError: the folder is not a run, or was trained without --eval-every.
  """
  try:
    cfg = config.load_config(run_dir)
  except FileNotFoundError as e:
    raise ValueError(str(e)) from None
  path = os.path.join(run_dir, eval_curve.CSV)
  if not os.path.exists(path):
    raise ValueError(f"{run_dir}: no {eval_curve.CSV}; it was trained without --eval-every "
                     "(train with e.g. --eval-every 10000 to evaluate during training)")
  with open(path, newline="") as f:
    return cfg, list(csv.DictReader(f))


def group_series(runs: list[tuple[str, config.TrainConfig, list[dict]]]) -> list[dict]:
  """The groups of the module doc from the runs of one task.

  Args:
    runs: (folder, config, eval_curve rows) per run.

  Returns:
    One dict per (augmentation, training looks), ordered by augmentation then by
    number of looks: "aug", "looks" (its label, e.g. "levels:100"), "num_looks",
    "seeds", "steps" (ascending) and "series" {panel: {"mean", "min", "max"}: one
    value per step}, the panels being `TRAIN` and the conditions.

  Raises:
    ValueError: the runs differ in their protocol or conditions, or a seed of a
      group comes twice.
  """
  first_dir, first, _ = runs[0]
  conditions = None
  members: dict[tuple[str, str], dict] = {}
  for run_dir, cfg, rows in runs:
    for field in PROTOCOL:
      if getattr(cfg, field) != getattr(first, field):
        raise ValueError(f"{run_dir} evaluated during training with {field}="
                         f"{getattr(cfg, field)!r}, {first_dir} with "
                         f"{getattr(first, field)!r}: curves drawn together need one protocol")
    mine = list(dict.fromkeys(r["condition"] for r in rows))
    if conditions is None:
      conditions = mine
    elif mine != conditions:
      raise ValueError(f"{run_dir} evaluated conditions {', '.join(mine)}, {first_dir} "
                       f"{', '.join(conditions)}: curves drawn together need the same ones")
    for a, ((seed, aug), look) in enumerate(zip(cfg.agents(), cfg.agent_looks())):
      key = (aug, config.look_label(look))
      group = members.setdefault(key, dict(num_looks=config.num_looks(look), seeds={}))
      if seed in group["seeds"]:
        raise ValueError(f"seed {seed} of {aug} on {key[1]} comes twice ({run_dir}); "
                         "give each seed of a group once")
      values = {}
      for r in rows:
        if int(r["agent"]) == a:
          step = int(r["step"])
          values[(step, r["condition"])] = float(r["mean_return"])
          values[(step, TRAIN)] = float(r["train_return"])
      group["seeds"][seed] = values
  panels = [TRAIN] + conditions
  out = []
  order = lambda kv: (kv[0][0], kv[1]["num_looks"])
  for (aug, looks), group in sorted(members.items(), key=order):
    per_seed = list(group["seeds"].values())
    steps = sorted(set.intersection(*({s for s, _ in v} for v in per_seed)))
    series = {}
    for panel in panels:
      table = np.array([[v[(s, panel)] for s in steps] for v in per_seed])
      series[panel] = dict(mean=table.mean(0).tolist(), min=table.min(0).tolist(),
                           max=table.max(0).tolist())
    out.append(dict(aug=aug, looks=looks, num_looks=group["num_looks"],
                    seeds=sorted(group["seeds"]), steps=steps, series=series))
  return out


def markdown(task: str, groups: list[dict]) -> str:
  """Each panel's values: one table per panel, a row per step, a column per group."""
  names = [f"{g['aug']}, {g['looks']} ({len(g['seeds'])} seed{'s' * (len(g['seeds']) > 1)})"
           for g in groups]
  lines = [f"Held-out return during training ({task}): mean over a group's seeds, min–max "
           "in brackets where it has several; train = the return at the agent's own looks.", ""]
  steps = sorted({s for g in groups for s in g["steps"]})
  for panel in groups[0]["series"]:
    lines += [f"### {panel}", "", "| step | " + " | ".join(names) + " |",
              "|---:|" + "---:|" * len(groups)]
    for step in steps:
      cells = []
      for g in groups:
        if step not in g["steps"]:
          cells.append("–")
          continue
        s, i = g["series"][panel], g["steps"].index(step)
        band = f" ({s['min'][i]:.1f}–{s['max'][i]:.1f})" if len(g["seeds"]) > 1 else ""
        cells.append(f"{s['mean'][i]:.1f}{band}")
      lines.append(f"| {step:,} | " + " | ".join(cells) + " |")
    lines.append("")
  return "\n".join(lines)


def plot(task: str, groups: list[dict], png_path: str) -> None:
  """One panel per series (train, then each condition), one line per group."""
  import matplotlib.pyplot as plt
  panels = list(groups[0]["series"])
  fig, axes = eval_curve.step_panels(len(panels), cols=4)
  augs = list(dict.fromkeys(g["aug"] for g in groups))
  colours = plt.get_cmap("viridis")(np.linspace(0, 0.9, max(len(groups), 1)))
  for ax, panel in zip(axes, panels):
    for g, colour in zip(groups, colours):
      s = g["series"][panel]
      style = ["-", "--", ":", "-."][augs.index(g["aug"]) % 4]
      ax.plot(g["steps"], s["mean"], style, marker="o", ms=2.5, color=colour,
              label=f"{g['looks']}, {g['aug']}")
      if len(g["seeds"]) > 1:
        ax.fill_between(g["steps"], s["min"], s["max"], color=colour, alpha=0.15, lw=0)
    ax.set_title(f"{task}: {panel}" + (" (own looks)" if panel == TRAIN else ""), fontsize=9)
  eval_curve.save_panels(fig, axes, png_path)


def curves(run_dirs: list[str], out_dir: str) -> dict[str, list[dict]]:
  """Draws the module doc's files for each task of `run_dirs` whose runs hold more
  than one group; {task: its groups (`group_series`)} of the tasks drawn.

  Raises:
    ValueError: as `read_run` and `group_series`.
  """
  by_task: dict[str, list] = {}
  for run_dir in run_dirs:
    cfg, rows = read_run(run_dir)
    by_task.setdefault(cfg.task, []).append((run_dir, cfg, rows))
  drawn = {}
  for task, runs in by_task.items():
    groups = group_series(runs)
    if len(groups) < 2 or not any(g["steps"] for g in groups):
      continue
    os.makedirs(out_dir, exist_ok=True)
    name = os.path.join(out_dir, f"eval_curves_{task}")
    with open(name + ".json", "w") as f:
      json.dump(dict(task=task, runs=[r for r, _, _ in runs], groups=groups), f, indent=1)
    with open(name + ".md", "w") as f:
      f.write(markdown(task, groups))
    plot(task, groups, name + ".png")
    drawn[task] = groups
  return drawn


def main(argv=None) -> None:
  """Command-line entry (module docstring)."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.benchmarks.eval_curves",
                              description=__doc__.splitlines()[0])
  p.add_argument("runs", nargs="+", metavar="RUN_DIR",
                 help="run folders trained with --eval-every")
  p.add_argument("--out", required=True, help="the folder of eval_curves_<task>.{md,json,png}")
  a = p.parse_args(argv)
  try:
    drawn = curves(a.runs, a.out)
  except ValueError as e:
    p.error(str(e))
  if not drawn:
    p.error("no task among these runs has agents of more than one training-look range or "
            "augmentation with evaluations; the picture compares at least two")
  for task in drawn:
    print(f"wrote {os.path.join(a.out, f'eval_curves_{task}')}.md, .json and .png")


if __name__ == "__main__":
  main()
