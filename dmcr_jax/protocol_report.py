"""Reports of the zero-shot protocol: the Markdown table, the bar chart, augmentation
groups and few-shot curves, from a summary (`dmcr_jax.protocol.Results.summary`, which
`dmcr-evaluate` extends with each agent's seed, augmentation and method).

A summary is a dict: "task", "conditions", "config" (the protocol's options),
"train_look", "wall_s", "agents" (per agent: "agent", "label" or the run's "seed",
"aug", "algo", "method", and "train" / "conditions" cells with "mean", "std",
"episodes", "e_g"), "mean" (`mean_row`) and "augs" (`aug_groups`); a run's summary
also has "run_dir" and "checkpoint_step". Where a row names one of the paper's
methods, the paper's Table 4 row (`dmcr_jax.train.paper_results`) stands beside it.
Several runs' summaries of one task and protocol merge into one (`merge_summaries`),
whose few-shot curve spans all their ranges, augmentations and seeds.
"""

from __future__ import annotations

import json
import os

import numpy as np

from dmcr_jax._files import json_safe  # noqa: F401 (re-exported)
from dmcr_jax.train import paper_results
from dmcr_jax.visuals.levels import TRAIN_SEEDS


def generalization_error(train: float, test: float) -> float:
  """E_G = (train − test) / train (paper Sec. 3); NaN when train is 0."""
  return float("nan") if train == 0 else (train - test) / train


def mean_row(results: list[dict], conditions) -> dict:
  """The agents' mean train return, condition means and E_G of those means."""
  train = float(np.mean([r["train"]["mean"] for r in results]))
  means = {c: float(np.mean([r["conditions"][c]["mean"] for r in results]))
           for c in conditions}
  return dict(train=train, conditions=means,
              e_g={c: generalization_error(train, m) for c, m in means.items()})


def _label(row: dict) -> str:
  """An agent's name in the table: its augmentation (SAC+AUG) or algorithm (+ aug) for
  a `dmcr-train` agent, else its "label"."""
  if "aug" not in row:
    return row.get("label") or f"agent {row['agent']}"
  algo, aug = row.get("algo", "sac_aug"), row["aug"]
  if algo == "sac_aug":
    return aug
  return algo if aug == "none" else f"{algo}, {aug}"


def _several_ranges(summary: dict) -> bool:
  """Whether the summary's agents trained on more than one training-look range."""
  return len({r.get("train_look") for r in summary["agents"]}) > 1


def aug_groups(summary: dict) -> list[dict]:
  """The agents grouped by augmentation (by algorithm and augmentation), in run order;
  in a run with several training-look ranges, by augmentation and range (a mean
  over agents trained on different looks would mix what the few-shot curve
  separates).

  Args:
    summary: `evaluate`'s results (its "agents", "conditions" and "task").

  Returns:
    One dict per group: label (`_label`), aug, method (the paper's name or None),
    agents (indices), seeds, `_mean_row`'s train / conditions / e_g over its
    agents, and paper: the paper's Table 4 row for the task and method as
    {"returns": {condition: return}, "e_g": {condition: E_G}} (its "None"
    column taken as the train return), or None.
  """
  conditions = summary["conditions"]
  ranges = _several_ranges(summary)
  groups: dict[str, list[dict]] = {}
  for r in summary["agents"]:
    groups.setdefault(_label(r) + (f", {r['train_look']}" if ranges else ""), []).append(r)
  out = []
  for label, rows in groups.items():
    method = rows[0].get("method")
    table = paper_results.table4(summary["task"], method) if method else None
    paper = None if table is None else dict(
        returns=table, e_g={c: generalization_error(table["none"], table[c])
                            for c in conditions if c in table})
    out.append(dict(label=label, aug=rows[0].get("aug"), method=method,
                    agents=[r["agent"] for r in rows], seeds=[r.get("seed") for r in rows],
                    **mean_row(rows, conditions), paper=paper))
  return out


def _group_word(summary: dict) -> str:
  """The E_G table's first column: "augmentation" for `dmcr-train` agents, else "policy"."""
  return "augmentation" if any("aug" in r for r in summary["agents"]) else "policy"


def split_conditions(conditions) -> tuple[list[str], list[tuple[str, str, float]]]:
  """The static conditions, and the moving ones as (name, factor, intensity)
  (``moving-<factor>@<intensity>``, `protocol_plan.moving_of`), each in order."""
  from dmcr_jax.protocol_plan import moving_of
  static = [c for c in conditions if moving_of(c) is None]
  return static, [(c,) + moving_of(c) for c in conditions if moving_of(c) is not None]


def _moving_grid(moving):
  """(factors, intensities) of the moving conditions, each in first-seen order."""
  return (list(dict.fromkeys(f for _, f, _ in moving)),
          list(dict.fromkeys(i for _, _, i in moving)))


def _render_words(cfg: dict) -> str:
  if cfg.get("renderer", "pool") == "jax":
    return "rendered by the JAX ray caster"
  return f"render quality {cfg['quality']}"


def markdown(summary: dict) -> str:
  """The results as the paper's Table 4 (returns per condition) plus train and E_G.

  Rows: every agent; the mean over agents (per augmentation when the run trained
  several, if one has several seeds); the paper's row for each method it has. A second table gives E_G per
  condition for those means and the paper's rows, augmentations side by side.
  """
  conditions, moving = split_conditions(summary["conditions"])
  cfg = summary["config"]
  groups = summary.get("augs") or aug_groups(summary)
  head = ["agent", "train"] + conditions + ["E_G (all)" if "all" in conditions else "E_G"]
  source = (f"`{summary['run_dir']}` ({summary['task']}, checkpoint step "
            f"{summary['checkpoint_step']:,})" if "run_dir" in summary else
            f"{summary['task']}")
  lines = [f"Zero-shot evaluation of {source}: train = mean return over "
           f"{cfg['train_episodes']} initial states at the training look "
           f"({summary['train_look']}); each condition = mean over {cfg['visual_seeds']} "
           f"held-out visual seeds × {cfg['dynamics_seeds']} initial states; "
           f"{_render_words(cfg)}; E_G = (train − test) / train. Wall time "
           f"{summary['wall_s']:.0f} s.", "",
           "| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
  last = "all" if "all" in conditions else conditions[-1] if conditions else None
  pct = lambda e: f"{100 * e:.1f} %" if e is not None and np.isfinite(e) else "–"

  def line(label, train, means, e_g):
    cells = [label, f"{train:.1f}"] + [f"{means[c]:.1f}" for c in conditions]
    return "| " + " | ".join(cells + [pct(e_g)]) + " |"

  def paper_line(g):
    row = g["paper"]["returns"]
    cells = [f"paper, {g['method']}", f"{row['none']:.1f}"]
    cells += [f"{row[c]:.1f}" if c in row else "–" for c in conditions]
    return "| " + " | ".join(cells + [pct(g["paper"]["e_g"].get(last))]) + " |"

  ranges = _several_ranges(summary)
  for r in summary["agents"]:
    means = {c: r["conditions"][c]["mean"] for c in conditions}
    label = (f"seed {r['seed']}, " if "seed" in r else "") + _label(r)
    label += f", {r['train_look']}" if ranges else ""
    lines.append(line(label, r["train"]["mean"], means,
                      r["conditions"][last]["e_g"] if last else None))
  if len(groups) == 1 and len(summary["agents"]) > 1 and not ranges:
    m = summary["mean"]
    lines.append(line("**mean**", m["train"], m["conditions"], m["e_g"].get(last)))
  elif 1 < len(groups) < len(summary["agents"]):
    for g in groups:
      lines.append(line(f"**{g['label']}** (mean of {len(g['agents'])})", g["train"],
                        g["conditions"], g["e_g"].get(last)))
  papers = list({g["method"]: g for g in groups if g["paper"] is not None}.values())
  lines += [paper_line(g) for g in papers]
  if papers:
    lines += ["", "Paper rows are its Table 4 (five runs; its \"None\" column, shown "
                  "under both train and none)."]
  whose = ("policy" if _group_word(summary) == "policy"
           else "augmentation's agents per training-look range" if ranges
           else "augmentation's agents" if len(groups) > 1 else "agent set")
  lines += ["", "E_G per condition (mean return of each " + whose
            + ("; paper: from its Table 4 with \"None\" as train" if papers else "") + "):",
            "",
            "| " + " | ".join([_group_word(summary), "train"] + conditions) + " |",
            "|---|" + "---:|" * (len(conditions) + 1)]
  for g in groups:
    cells = [g["label"], f"{g['train']:.1f}"] + [pct(g["e_g"][c]) for c in conditions]
    lines.append("| " + " | ".join(cells) + " |")
  for g in papers:
    row = g["paper"]
    cells = [f"paper, {g['method']}", f"{row['returns']['none']:.1f}"]
    cells += [pct(row["e_g"].get(c)) for c in conditions]
    lines.append("| " + " | ".join(cells) + " |")
  if moving:
    lines += [""] + moving_markdown(summary, groups)
  return "\n".join(lines) + "\n"


def moving_markdown(summary: dict, groups: list[dict] | None = None) -> list[str]:
  """The moving conditions' tables (lines): mean return per agent and intensity with
  a column per moving factor ("all": every factor moving), then E_G per group and
  intensity; each row says its intensity, each column its factor."""
  _, moving = split_conditions(summary["conditions"])
  groups = groups or summary.get("augs") or aug_groups(summary)
  factors, levels = _moving_grid(moving)
  name = {(f, i): c for c, f, i in moving}
  cell = lambda values, f, i, fmt: fmt(values[name[(f, i)]]) if (f, i) in name else "–"
  pct = lambda e: f"{100 * e:.1f} %" if e is not None and np.isfinite(e) else "–"
  ranges = _several_ranges(summary)
  lines = ["Moving distractions: dm_control's look with one factor moving within each "
           "episode (`all`: every factor), the held-out visual seed picking its motion, "
           "at each intensity (the fraction of each factor's range, as the Distracting "
           "Control Suite's difficulty; `moving-<factor>@<intensity>`); mean return:", "",
           "| " + " | ".join(["agent", "intensity", "train"] + factors) + " |",
           "|---|---:|---:|" + "---:|" * len(factors)]
  for r in summary["agents"]:
    label = (f"seed {r['seed']}, " if "seed" in r else "") + _label(r)
    label += f", {r['train_look']}" if ranges else ""
    means = {c: r["conditions"][c]["mean"] for c, _, _ in moving}
    for i in levels:
      lines.append("| " + " | ".join([label, f"{i:g}", f"{r['train']['mean']:.1f}"]
                                     + [cell(means, f, i, lambda v: f"{v:.1f}")
                                        for f in factors]) + " |")
  lines += ["", "E_G per moving condition (mean return of each group of agents):", "",
            "| " + " | ".join([_group_word(summary), "intensity"] + factors) + " |",
            "|---|---:|" + "---:|" * len(factors)]
  for g in groups:
    for i in levels:
      lines.append("| " + " | ".join([g["label"], f"{i:g}"]
                                     + [cell(g["e_g"], f, i, pct) for f in factors]) + " |")
  return lines


def plot(summary: dict, png_path: str) -> None:
  """Grouped bars, one colour per augmentation (or policy): mean return at the training look
  and per condition (dots: agents; ×: the paper's row), and E_G per condition."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  conditions, moving = split_conditions(summary["conditions"])
  groups = summary.get("augs") or aug_groups(summary)
  columns = ["train"] + list(conditions)
  x = np.arange(len(columns))
  width = 0.8 / len(groups)
  colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
  rows = 2 if moving else 1
  fig, axes = plt.subplots(rows, 2, figsize=(2.0 + 1.5 * max(len(columns), 4), 3.8 * rows),
                           gridspec_kw=dict(width_ratios=(len(columns),
                                                          max(len(conditions), 1))),
                           squeeze=False)
  (ax, ax_e) = axes[0]
  drawn_papers = set()
  for k, g in enumerate(groups):
    color, dx = colors[k % len(colors)], (k - (len(groups) - 1) / 2) * width
    means = [g["train"]] + [g["conditions"][c] for c in conditions]
    ax.bar(x + dx, means, width, color=color, alpha=0.8,
           label=f"{g['label']} ({len(g['agents'])})")
    for a in g["agents"]:
      r = next(r for r in summary["agents"] if r["agent"] == a)
      ax.plot(x + dx, [r["train"]["mean"]] + [r["conditions"][c]["mean"] for c in conditions],
              "k.", ms=4, alpha=0.6, ls="none")
    ax_e.bar(np.arange(len(conditions)) + dx, [g["e_g"][c] for c in conditions], width,
             color=color, alpha=0.8)
    if g["paper"] is not None and g["method"] not in drawn_papers:
      drawn_papers.add(g["method"])
      row = g["paper"]["returns"]
      ax.plot(np.array([i for i, c in enumerate(columns) if c in row or c == "train"]) + dx,
              [row["none"] if c == "train" else row[c] for c in columns
               if c in row or c == "train"],
              "X", color=color, mec="k", ms=8, mew=0.8, ls="none",
              label=f"paper {g['method']}")
      ax_e.plot([i + dx for i, c in enumerate(conditions) if c in row],
                [g["paper"]["e_g"][c] for c in conditions if c in row],
                "X", color=color, mec="k", ms=8, mew=0.8, ls="none")
  ax.set_xticks(x, columns, rotation=30)
  ax.set_ylabel("mean episode return")
  ax.set_title(f"{summary['task']}: zero-shot returns per visual condition", fontsize=10)
  ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0, -0.22), ncol=2,
            frameon=False)
  ax_e.set_xticks(np.arange(len(conditions)), conditions, rotation=30)
  ax_e.axhline(0, color="k", lw=0.8)
  ax_e.set_ylabel("E_G = (train − test) / train")
  ax_e.set_title("generalisation error (×: paper)", fontsize=10)
  if moving:
    _plot_moving(summary, groups, moving, axes[1], colors)
  fig.tight_layout()
  fig.savefig(png_path, dpi=100, bbox_inches="tight")
  plt.close(fig)


def _plot_moving(summary: dict, groups: list[dict], moving, axes, colors) -> None:
  """Mean return and E_G against intensity, a line per (group, moving factor);
  "none" (where run) drawn at intensity 0, where every moving condition starts."""
  factors, _ = _moving_grid(moving)
  styles = ["-", "--", ":", "-."]
  ax, ax_e = axes
  for k, g in enumerate(groups):
    for j, f in enumerate(factors):
      pts = sorted((i, c) for c, ff, i in moving if ff == f)
      xs, cs = [i for i, _ in pts], [c for _, c in pts]
      ys, es = [g["conditions"][c] for c in cs], [g["e_g"][c] for c in cs]
      if "none" in g["conditions"] and 0.0 not in xs:
        xs, ys, es = [0.0] + xs, [g["conditions"]["none"]] + ys, [g["e_g"]["none"]] + es
      style = dict(color=colors[j % len(colors)], ls=styles[k % len(styles)], marker="o",
                   ms=3, lw=2 if f == "all" else 1)
      ax.plot(xs, ys, label=f if len(groups) == 1 else f"{f}, {g['label']}", **style)
      ax_e.plot(xs, es, **style)
  ax.set_xlabel("intensity")
  ax_e.set_xlabel("intensity")
  ax.set_ylabel("mean episode return")
  ax_e.set_ylabel("E_G = (train − test) / train")
  ax_e.axhline(0, color="k", lw=0.8)
  ax.set_title(f"{summary['task']}: moving distractions (0: none)", fontsize=10)
  ax_e.set_title("E_G, moving", fontsize=10)
  ax.legend(fontsize=7, ncol=2)


def few_shot_rows(summary: dict) -> list[dict]:
  """The generalisation curve of a few-shot run: one row per (augmentation, training
  looks), the means over that group's agents (seeds) and their spread.

  Returns:
    Rows sorted by augmentation then number of looks, each with "aug", "method",
    "looks" (number of training looks), "train_look", "seeds", "train" (mean
    return at the training looks), "conditions" {condition: mean test return},
    "e_g" {condition: E_G of those means}, "train_min" / "train_max" and
    "conditions_min" / "conditions_max" {condition: return} (the least and
    greatest agent mean over the seeds; the mean itself for one seed) and
    "all_std" (std of "all" over the seeds; 0 for one seed).
  """
  groups: dict[tuple, list[dict]] = {}
  for r in summary["agents"]:
    groups.setdefault((r["aug"], r["looks"], r["train_look"]), []).append(r)
  rows = []
  for (aug, looks, label), agents in sorted(groups.items(), key=lambda kv: kv[0][:2]):
    mean = mean_row(agents, summary["conditions"])
    train = [r["train"]["mean"] for r in agents]
    per = {c: [r["conditions"][c]["mean"] for r in agents] for c in summary["conditions"]}
    row = dict(aug=aug, method=agents[0].get("method"), looks=looks, train_look=label,
               seeds=[r["seed"] for r in agents], train=mean["train"],
               conditions=mean["conditions"], e_g=mean["e_g"],
               train_min=float(min(train)), train_max=float(max(train)),
               conditions_min={c: float(min(v)) for c, v in per.items()},
               conditions_max={c: float(max(v)) for c, v in per.items()})
    if "all" in summary["conditions"]:
      row["all_std"] = float(np.std(per["all"]))
    rows.append(row)
  return rows


def zero_shot_references(rows: list[dict]) -> dict[str, float]:
  """{method or augmentation: test return under "all"} of the zero-shot rows
  (trained on dm_control's look alone: levels:1 or seed 0)."""
  return {(r["method"] or r["aug"]): r["conditions"]["all"] for r in rows
          if r["train_look"] in ("levels:1", "seed 0") and "all" in r["conditions"]}


def _few_shot_source(summary: dict) -> str:
  """What a few-shot table is of: the run, or the merged runs (`merge_summaries`),
  with the task and checkpoint step(s)."""
  step = summary["checkpoint_step"]
  steps = (f"checkpoint step {step:,}" if isinstance(step, int) else
           "checkpoint steps " + ", ".join(f"{s:,}" for s in step))
  where = (f"`{summary['run_dir']}`" if "runs" not in summary else
           f"{len(summary['runs'])} runs")
  return f"{where} ({summary['task']}, {steps})"


def _spread(mean: float, lo: float, hi: float, seeds: int) -> str:
  """A cell: "mean" for one seed, "mean (min–max)" for several."""
  return f"{mean:.1f}" if seeds == 1 else f"{mean:.1f} ({lo:.1f}–{hi:.1f})"


def few_shot_markdown(summary: dict, rows: list[dict]) -> str:
  """The curve as a Markdown table: per augmentation and number of training looks,
  the train return, each condition's test return (as "mean (min–max)" over the
  seeds where a row has several) and E_G (all) of the means; a merged summary
  (`merge_summaries`) lists its runs below."""
  conditions = summary["conditions"]
  cfg = summary["config"]
  last = "all" if "all" in conditions else conditions[-1]
  head = ["augmentation", "training looks", "seeds", "train"] + conditions + [f"E_G ({last})"]
  spread = any(len(r["seeds"]) > 1 for r in rows)
  lines = [f"Few-shot generalisation of {_few_shot_source(summary)}: one agent per "
           f"training-look range and seed, all tested on the same {cfg['visual_seeds']} "
           f"held-out visual seeds × {cfg['dynamics_seeds']} initial states; train = mean "
           f"return over {cfg['train_episodes']} episodes at looks from the agent's own "
           f"range; {_render_words(cfg)}; means over seeds"
           + (" (min–max over the seeds in brackets)" if spread else "")
           + "; E_G = (train − test) / train of the means.", "",
           "| " + " | ".join(head) + " |", "|---|---|---:|" + "---:|" * (len(head) - 3)]
  for r in rows:
    e_g, n = r["e_g"][last], len(r["seeds"])
    looks = "all" if r["looks"] == len(TRAIN_SEEDS) else f"{r['looks']:,}"
    cells = [r["method"] or r["aug"], f"{looks} ({r['train_look']})", str(n),
             _spread(r["train"], r["train_min"], r["train_max"], n)]
    cells += [_spread(r["conditions"][c], r["conditions_min"][c], r["conditions_max"][c], n)
              for c in conditions]
    cells.append(f"{100 * e_g:.1f} %" if np.isfinite(e_g) else "–")
    lines.append("| " + " | ".join(cells) + " |")
  if "runs" in summary:
    lines += ["", "Runs: " + ", ".join(f"`{r}`" for r in summary["runs"]) + "."]
  return "\n".join(lines) + "\n"


def _band_style(colour: str, aug: int) -> dict:
  """`fill_between` options of a min–max band: a light fill for the first
  augmentation, a hatch of its own for each further one (bands of several
  augmentations overlap)."""
  if aug == 0:
    return dict(color=colour, alpha=0.13, lw=0)
  return dict(facecolor="none", edgecolor=colour, alpha=0.35, lw=0,
              hatch=["//", "\\\\", "..", "xx"][(aug - 1) % 4])


def few_shot_figure(summary: dict, rows: list[dict]):
  """The matplotlib figure of `plot_few_shot` (left axes: returns; right: E_G). Each
  min–max band is a filled area whose gid is "band CONDITION, NAME" ("train" for
  the train return; NAME the method or augmentation)."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  conditions = summary["conditions"]
  last = "all" if "all" in conditions else conditions[-1]
  augs = list(dict.fromkeys(r["aug"] for r in rows))
  styles = ["-", "--", ":", "-."]
  colours = {c: ("black" if c == "all" else f"C{i}") for i, c in enumerate(conditions)}
  fig, (ax, ax_e) = plt.subplots(1, 2, figsize=(10, 4), gridspec_kw=dict(width_ratios=(3, 2)))
  for j, aug in enumerate(augs):
    mine = [r for r in rows if r["aug"] == aug]
    x = [r["looks"] for r in mine]
    name = mine[0]["method"] or aug
    band = any(len(r["seeds"]) > 1 for r in mine)
    ax.plot(x, [r["train"] for r in mine], styles[j % 4], color="grey", marker="s", ms=3,
            lw=1.5, label="train (own looks)" if len(augs) == 1 else f"train, {name}")
    if band:
      ax.fill_between(x, [r["train_min"] for r in mine], [r["train_max"] for r in mine],
                      gid=f"band train, {name}", **_band_style("grey", j))
    for c in conditions:
      ax.plot(x, [r["conditions"][c] for r in mine], styles[j % 4], color=colours[c],
              marker="o", ms=3, lw=2.5 if c == last else 1,
              label=f"{c}" if len(augs) == 1 else f"{c}, {name}")
      if band and c == last:
        ax.fill_between(x, [r["conditions_min"][c] for r in mine],
                        [r["conditions_max"][c] for r in mine], gid=f"band {c}, {name}",
                        **_band_style(colours[c], j))
    ax_e.plot(x, [r["e_g"][last] for r in mine], styles[j % 4], color="black", marker="o",
              ms=3, label=name)
  for k, (name, value) in enumerate(zero_shot_references(rows).items()):
    ax.axhline(value, color=f"C{k + len(conditions)}", ls=(0, (5, 3)), lw=1.2,
               label=f"zero-shot {name} ({last})")
  ticks = sorted({r["looks"] for r in rows})
  for a in (ax, ax_e):
    a.set_xscale("log")
    a.set_xticks(ticks, [f"{t:,}" if t < 2**30 else "2^30 (all)" for t in ticks],
                 fontsize=7, rotation=30)
    a.minorticks_off()
    a.set_xlabel("training looks (visual seeds)")
  seeds = max(len(r["seeds"]) for r in rows)
  ax.set_ylabel("return (test: held-out looks; train: own looks)")
  ax_e.set_ylabel(f"E_G ({last})")
  ax.set_title(f"{summary['task']}: test return against training looks"
               + (f" (mean; band: min–max over {seeds} seeds)" if seeds > 1 else ""),
               fontsize=9)
  ax_e.set_title("generalisation error (train − test) / train", fontsize=9)
  ax.legend(fontsize=6, loc="best", ncol=2)
  ax_e.legend(fontsize=7)
  fig.tight_layout()
  return fig


def plot_few_shot(summary: dict, rows: list[dict], png_path: str) -> None:
  """Test return per condition ("all" bold), the train return (grey) and E_G against
  the number of training looks (log x), one line style per augmentation; where a
  row has several seeds, a min–max band around "all" and the train return;
  dashed: the zero-shot "all" returns (`zero_shot_references`)."""
  import matplotlib.pyplot as plt
  fig = few_shot_figure(summary, rows)
  fig.savefig(png_path, dpi=100)
  plt.close(fig)


def write_few_shot(summary: dict, out_dir: str, name: str = "few_shot") -> list[dict]:
  """Writes the generalisation curve of a few-shot evaluation (one run's summary, or
  several runs' merged by `merge_summaries`): `<name>.json` (rows and zero-shot
  references), `<name>.md` and `<name>.png` in `out_dir` (made); returns the rows."""
  rows = few_shot_rows(summary)
  data = dict(task=summary["task"], checkpoint_step=summary["checkpoint_step"],
              conditions=summary["conditions"], rows=rows,
              zero_shot=zero_shot_references(rows))
  data.update({k: summary[k] for k in ("run_dir", "runs") if k in summary})
  os.makedirs(out_dir, exist_ok=True)
  with open(os.path.join(out_dir, f"{name}.json"), "w") as f:
    json.dump(json_safe(data), f, indent=1, allow_nan=False)
  with open(os.path.join(out_dir, f"{name}.md"), "w") as f:
    f.write(few_shot_markdown(summary, rows))
  plot_few_shot(summary, rows, os.path.join(out_dir, f"{name}.png"))
  return rows


PROTOCOL_OPTIONS = ("visual_seeds", "dynamics_seeds", "train_episodes", "seed", "renderer",
                    "quality")
"""The evaluation options (`EvalConfig` fields) that runs merged into one curve must
share, with their conditions; the others (workers, devices, block size) change how
the protocol runs, not what it measures."""


def _protocol_value(summary: dict, option: str):
  """A summary's value of a protocol option (`PROTOCOL_OPTIONS`, or "conditions":
  the conditions it ran)."""
  return summary["conditions"] if option == "conditions" else summary["config"].get(option)


def merge_summaries(summaries: list[dict], sources: list[str] | None = None) -> dict:
  """Several runs' evaluations of one task (their eval.json summaries) as one
  summary holding every agent, for `write_few_shot` (one curve over all their
  ranges, augmentations and seeds) and `markdown`.

  Args:
    summaries: `evaluate` summaries (eval.json), whose agents say how many looks
      they trained on ("looks").
    sources: each summary's name in messages and in "runs" (default: its
      "run_dir").

  Returns:
    A summary with "runs" (the sources), "checkpoint_step" (an int, or the sorted
    distinct steps), the first summary's "config", the shared "conditions", the
    agents renumbered in order (each with its "run_dir"), "train_look" (the
    ranges, comma-separated), "wall_s" (the sum), "mean" and "augs".

  Raises:
    ValueError: no summary; summaries of other tasks or of another protocol
      (naming the option, `PROTOCOL_OPTIONS` or the conditions); an agent without
      "looks"; the same seed of one augmentation and range in two summaries.
  """
  if not summaries:
    raise ValueError("merge_summaries needs at least one evaluate summary (eval.json)")
  sources = list(sources or [s.get("run_dir", f"summary {i}") for i, s in enumerate(summaries)])
  first, where = summaries[0], sources[0]
  for s, src in zip(summaries[1:], sources[1:]):
    if s["task"] != first["task"]:
      raise ValueError(f"{src} evaluated {s['task']} and {where} {first['task']}; a "
                       "few-shot curve is of one task")
    for option in PROTOCOL_OPTIONS + ("conditions",):
      mine, theirs = _protocol_value(s, option), _protocol_value(first, option)
      if mine != theirs:
        raise ValueError(f"{src} was evaluated with {option} = {mine!r} and {where} with "
                         f"{theirs!r}; one curve needs one protocol (the same "
                         f"{', '.join(PROTOCOL_OPTIONS)} and conditions)")
  agents, seen = [], {}
  for s, src in zip(summaries, sources):
    for r in s["agents"]:
      if "looks" not in r:
        raise ValueError(f"{src}: agent {r.get('agent')} does not say how many looks it "
                         "trained on ('looks'); evaluate the run again with dmcr-evaluate")
      key = (r.get("algo", "sac_aug"), r.get("aug"), r["train_look"], r.get("seed"))
      if key in seen:
        raise ValueError(f"seed {key[3]} of {r.get('method') or _label(r)} at {key[2]} is in {seen[key]} and in "
                         f"{src}; pass one evaluation per seed")
      seen[key] = src
      agents.append(dict(r, agent=len(agents), run_dir=src))
  steps = sorted({s["checkpoint_step"] for s in summaries})
  merged = dict(task=first["task"], runs=sources,
                checkpoint_step=steps[0] if len(steps) == 1 else steps,
                config=first["config"], conditions=list(first["conditions"]),
                train_look=",".join(dict.fromkeys(r["train_look"] for r in agents)),
                wall_s=float(sum(s.get("wall_s", 0.0) for s in summaries)), agents=agents,
                mean=mean_row(agents, first["conditions"]))
  merged["augs"] = aug_groups(merged)
  return merged


def write(summary: dict, out_dir: str, few_shot: bool | None = None) -> None:
  """Writes eval.json (an undefined E_G as null), eval.md and eval.png into `out_dir`
  (made), and the few-shot curve's files (`write_few_shot`, which reads each row's
  "looks") when `few_shot`; None: when the agents trained on several training-look
  ranges and every row says how many looks."""
  os.makedirs(out_dir, exist_ok=True)
  with open(os.path.join(out_dir, "eval.json"), "w") as f:
    json.dump(json_safe(summary), f, indent=1, allow_nan=False)
  with open(os.path.join(out_dir, "eval.md"), "w") as f:
    f.write(markdown(summary))
  plot(summary, os.path.join(out_dir, "eval.png"))
  if few_shot is None:
    few_shot = _several_ranges(summary) and all("looks" in r for r in summary["agents"])
  if few_shot:
    write_few_shot(summary, out_dir)
