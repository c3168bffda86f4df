"""The paper's generalisation table with our rows beside its rows, from `evaluate` results.

    python -m dmcr_jax.benchmarks.paper_table EVAL_JSON [EVAL_JSON ...] \\
        --out benchmarks/results/paper_table_h200.md

Each EVAL_JSON is an `evaluate` output (``eval.json``). The agents of all of them
are grouped by task, paper method (`paper_results.method_name`) and renderer, so
seeds trained and evaluated apart make one row (their files must share the
protocol and not repeat a seed); a row is the mean over its agents (seeds) of the
train return, each condition of the paper's table and E_G of "all" (computed from
those means, as the paper does). Writes ``--out`` (Markdown) and the same rows as
JSON beside it:

- our row beside the paper's for every task and method (tasks in the order of the
  paper's training-length table), with the difference of "all";
- what each file's agents ran: seeds, training steps and action repeat (against the
  paper's), the protocol (held-out looks × initial states, train episodes,
  render quality), training wall time and devices (from the run's summary.json,
  when the agents came with it), evaluation wall time and device, and its file;
- the ray caster against the pool, condition by condition, where a task and
  method were evaluated with both (over the seeds evaluated with both);
- which rows the paper-table issue asks for are still missing;
- where the agents were also evaluated under moving looks (`dmcr-evaluate
  --moving-intensities`), those conditions' means per row and intensity, beside
  its static "none" (`moving_markdown`).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from dmcr_jax.env_checks import ACTION_REPEAT, default_frame_skip
from dmcr_jax.protocol_report import split_conditions
from dmcr_jax.train import paper_results

TRAINING_STEPS = {"walker-walk": 250_000, "cheetah-run": 250_000, "hopper-stand": 250_000,
                  "finger-spin": 100_000, "ball_in_cup-catch": 75_000,
                  "cartpole-balance": 50_000}
"""The paper's training steps (transitions) per task (its appendix table of training
lengths, in its order; the same table's action repeats are `dmcr_jax.env.ACTION_REPEAT`)."""

WANTED = tuple((task, "SAC+AUG") for task in TRAINING_STEPS) + (
    ("walker-walk", "SAC+CJ+AUG"), ("cheetah-run", "SAC+CJ+AUG"))
"""The (task, method) rows the table is to hold, evaluated with the pool."""


def seed_means(by_seed: dict) -> dict:
  """seeds, and the means over them of the train return and of each condition all
  of them have (the paper's columns, then any moving ones), with E_G of "all"
  computed from those means (as the paper does)."""
  seeds = sorted(by_seed)
  per_seed = [by_seed[s] for s in seeds]
  train = float(np.mean([p["train"] for p in per_seed]))
  conditions = {c: float(np.mean([p["conditions"][c] for p in per_seed]))
                for c in per_seed[0]["conditions"]
                if all(c in p["conditions"] for p in per_seed)}
  all_ = conditions.get("all")
  return dict(seeds=seeds, train=train, conditions=conditions,
              e_g_all=None if all_ is None or train == 0 else (train - all_) / train)


def rows_of(result: dict, source: str) -> list[dict]:
  """One run per (method, renderer) group of an `evaluate` result's agents: their
  means and what they ran (`merge` pools the runs of one row across files)."""
  groups: dict[str, list[dict]] = {}
  for agent in result["agents"]:
    algo = agent.get("algo", "sac_aug")  # (results before evaluate recorded it: SAC+AUG)
    method = (agent.get("method") or paper_results.method_name(algo, agent["aug"])
              or f"{algo}:{agent['aug']}")
    groups.setdefault(method, []).append(agent)
  config = result.get("config", {})
  training = result.get("training") or {}
  rows = []
  for method, agents in groups.items():
    columns = ([c for c in paper_results.COLUMNS if c in agents[0]["conditions"]]
               + [c for c, _, _ in split_conditions(agents[0]["conditions"])[1]])
    by_seed = {a["seed"]: dict(train=a["train"]["mean"],
                               conditions={c: a["conditions"][c]["mean"] for c in columns})
               for a in agents}
    rows.append(dict(
        task=result["task"], method=method, renderer=config.get("renderer", "pool"),
        by_seed=by_seed, **seed_means(by_seed),
        steps=result.get("checkpoint_step"),
        action_repeat=result.get("action_repeat") or default_frame_skip(result["task"]),
        protocol=dict(visual_seeds=config.get("visual_seeds"),
                      dynamics_seeds=config.get("dynamics_seeds"),
                      train_episodes=config.get("train_episodes"),
                      quality=config.get("quality")),
        train_wall_s=training.get("wall_s"), train_devices=training.get("devices", []),
        eval_wall_s=result.get("wall_s"), eval_device=result.get("device"),
        source=source))
  return rows


def _sort_key(row: dict):
  """The paper's task order, then its method order, then the renderer."""
  order = {task: i for i, task in enumerate(TRAINING_STEPS)}
  methods = {m: i for i, m in enumerate(paper_results.METHODS)}
  return (order.get(row["task"], len(order)), row["task"],
          methods.get(row["method"], len(methods)), row["renderer"])


def collect(paths: list[str]) -> list[dict]:
  """The runs (`rows_of`) of every `evaluate` JSON in `paths`, in the paper's task
  order; `merge` makes the table's rows of them.

  Raises:
    ValueError: a path that is not an `evaluate` result.
  """
  rows = []
  for path in paths:
    rows.extend(rows_of(read(path), path))
  return sorted(rows, key=_sort_key)


def read(path: str) -> dict:
  """The `evaluate` result (eval.json) at `path`.

  Raises:
    ValueError: a path that cannot be read or is not an `evaluate` result.
  """
  try:
    with open(path) as f:
      result = json.load(f)
  except (OSError, json.JSONDecodeError) as e:
    raise ValueError(f"{path}: cannot read an evaluate result ({e})") from None
  if not isinstance(result, dict) or not {"task", "agents"} <= set(result):
    raise ValueError(f"{path}: not an evaluate result (eval.json): no task and agents")
  return result


def merge(runs: list[dict]) -> list[dict]:
  """The table's rows: one per (task, method, renderer), pooling its runs' seeds.

  A row's train return and conditions are means over all its seeds, E_G of "all"
  is computed from those means, and `sources` lists its files.

  Raises:
    ValueError: runs of one row with different protocols, or a seed in two of them.
  """
  rows: dict[tuple, dict] = {}
  for run in runs:
    key = (run["task"], run["method"], run["renderer"])
    row = rows.get(key)
    if row is None:
      rows[key] = dict(task=run["task"], method=run["method"], renderer=run["renderer"],
                       protocol=run["protocol"], by_seed=dict(run["by_seed"]),
                       sources=[run["source"]])
      continue
    name = f"{run['task']} {run['method']} ({run['renderer']})"
    if run["protocol"] != row["protocol"]:
      raise ValueError(f"{name}: {run['source']} was evaluated with another protocol than "
                       f"{', '.join(row['sources'])} ({run['protocol']} against "
                       f"{row['protocol']}); one row needs one protocol")
    both = sorted(set(run["by_seed"]) & set(row["by_seed"]))
    if both:
      raise ValueError(f"{name}: seed {', '.join(map(str, both))} is in {run['source']} and "
                       f"in {', '.join(row['sources'])}; pass one evaluation per seed")
    row["by_seed"].update(run["by_seed"])
    row["sources"].append(run["source"])
  return sorted((dict(row, **seed_means(row["by_seed"])) for row in rows.values()),
                key=_sort_key)


def missing(rows: list[dict]) -> list[tuple[str, str]]:
  """The `WANTED` rows with no pool evaluation among `rows`."""
  have = {(r["task"], r["method"]) for r in rows if r["renderer"] == "pool"}
  return [w for w in WANTED if w not in have]


def _num(v, digits=1) -> str:
  return "–" if v is None else f"{v:,.{digits}f}"


def markdown(runs: list[dict]) -> str:
  """The four parts of the module docstring as Markdown, from `collect`'s runs.

  Raises:
    ValueError: as `merge`.
  """
  cols = paper_results.COLUMNS
  rows = merge(runs)
  out = ["| task | method | renderer | seeds | train | " + " | ".join(cols)
         + " | E_G (all) | all − paper |", "|---|---|---|---:|---:|" + "---:|" * len(cols)
         + "---:|---:|"]
  for r in rows:
    paper = paper_results.table4(r["task"], r["method"])
    cells = [_num(r["conditions"].get(c)) for c in cols]
    diff = (None if paper is None or "all" not in r["conditions"]
            else r["conditions"]["all"] - paper["all"])
    e_g = "–" if r["e_g_all"] is None else f"{100 * r['e_g_all']:.1f} %"
    out.append(f"| {r['task']} | {r['method']} | {r['renderer']} | {len(r['seeds'])} | "
               f"{_num(r['train'])} | " + " | ".join(cells) + f" | {e_g} | {_num(diff)} |")
    if paper is not None and r["renderer"] == "pool":
      e_g = (paper["none"] - paper["all"]) / paper["none"]
      out.append(f"| | paper | | 5 | {_num(paper['none'])} | "
                 + " | ".join(_num(paper[c]) for c in cols) + f" | {100 * e_g:.1f} % | |")
  out += ["", "(The paper's train return is its \"none\" column: its agents trained on "
          "dm_control's look; its rows are means of five runs.)", "",
          "| task | method | renderer | seeds | steps (paper) | action repeat (paper) | "
          "protocol | training wall s | trained on | evaluation wall s | evaluated on | file |",
          "|---|---|---|---|---|---|---|---:|---|---:|---|---|"]
  for r in runs:
    steps, repeat = TRAINING_STEPS.get(r["task"]), ACTION_REPEAT.get(r["task"])
    p = r["protocol"]
    protocol = (f"{p['visual_seeds']} × {p['dynamics_seeds']}, train {p['train_episodes']}, "
                f"{p['quality'] if r['renderer'] == 'pool' else 'ray caster'}")
    out.append(f"| {r['task']} | {r['method']} | {r['renderer']} | "
               f"{', '.join(map(str, r['seeds']))} | {_num(r['steps'], 0)} ({_num(steps, 0)}) | "
               f"{r['action_repeat'] or '–'} ({repeat or '–'}) | {protocol} | "
               f"{_num(r['train_wall_s'], 0)} | {', '.join(r['train_devices']) or '–'} | "
               f"{_num(r['eval_wall_s'], 0)} | {r['eval_device'] or '–'} | "
               f"`{r['source']}` |")
  pairs = [(a, b) for a in rows for b in rows if a["renderer"] == "pool"
           and b["renderer"] == "jax" and (a["task"], a["method"]) == (b["task"], b["method"])]
  pairs = [(a, b, sorted(set(a["by_seed"]) & set(b["by_seed"]))) for a, b in pairs]
  pairs = [(a, b, seeds) for a, b, seeds in pairs if seeds]
  if pairs:
    out += ["", "Ray caster minus pool, per condition (mean over the seeds evaluated with both):",
            "", "| task | method | seeds | train | " + " | ".join(cols) + " |",
            "|---|---|---|---:|" + "---:|" * len(cols)]
    for pool, jax_row, seeds in pairs:
      def d(c=None):
        runs = [(pool["by_seed"][s], jax_row["by_seed"][s]) for s in seeds]
        if c is None:
          return float(np.mean([j["train"] - p["train"] for p, j in runs]))
        if any(c not in p["conditions"] or c not in j["conditions"] for p, j in runs):
          return None
        return float(np.mean([j["conditions"][c] - p["conditions"][c] for p, j in runs]))
      out.append(f"| {pool['task']} | {pool['method']} | {', '.join(map(str, seeds))} | "
                 f"{_num(d())} | " + " | ".join(_num(d(c)) for c in cols) + " |")
  gaps = missing(rows)
  out += ["", "Still missing (evaluated with the pool): "
          + (", ".join(f"{m} on {t}" for t, m in gaps) if gaps else "none") + "."]
  out += moving_markdown(rows)
  return "\n".join(out) + "\n"


def moving_markdown(rows: list[dict]) -> list[str]:
  """The moving conditions of `merge`'s rows that ran any, as lines of Markdown (none
  when no row did): a line per row and intensity with its static "none", a column per
  moving factor ("all": every factor moving; "–" where the row did not run it) and
  E_G of "all" at that intensity."""
  moving = [(r, split_conditions(r["conditions"])[1]) for r in rows]
  moving = [(r, m) for r, m in moving if m]
  if not moving:
    return []
  factors = list(dict.fromkeys(f for _, m in moving for _, f, _ in m))
  factors = [f for f in factors if f != "all"] + ["all"] * ("all" in factors)
  out = ["", "Under moving looks (dm_control's look with one factor, or all, moving within "
         "each episode; intensity as the Distracting Control Suite's difficulty; "
         "`moving-<factor>@<intensity>`), mean return beside the static \"none\":", "",
         "| task | method | renderer | seeds | intensity | none | " + " | ".join(factors)
         + " | E_G (all) |", "|---|---|---|---:|---:|---:|" + "---:|" * len(factors) + "---:|"]
  for r, m in moving:
    name = {(f, i): c for c, f, i in m}
    for level in dict.fromkeys(i for _, _, i in m):
      cells = [_num(r["conditions"].get(name.get((f, level)))) for f in factors]
      all_ = r["conditions"].get(name.get(("all", level)))
      e_g = ("–" if all_ is None or r["train"] == 0
             else f"{100 * (r['train'] - all_) / r['train']:.1f} %")
      out.append(f"| {r['task']} | {r['method']} | {r['renderer']} | {len(r['seeds'])} | "
                 f"{level:g} | {_num(r['conditions'].get('none'))} | " + " | ".join(cells)
                 + f" | {e_g} |")
  return out


def main(argv=None) -> None:
  """Command-line entry (module docstring)."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.benchmarks.paper_table",
                              description=__doc__.splitlines()[0])
  p.add_argument("results", nargs="+", metavar="EVAL_JSON", help="evaluate's eval.json files")
  p.add_argument("--out", default=None,
                 help="Markdown path (its .json beside it; default: print only)")
  a = p.parse_args(argv)
  try:
    runs = collect(a.results)
    rows = merge(runs)
  except ValueError as e:
    p.error(str(e))
  table = markdown(runs)
  print(table, end="")
  if a.out:
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out, "w") as f:
      f.write("Our rows beside the DMCR paper's (`python -m dmcr_jax.benchmarks.paper_table "
              + " ".join(a.results) + "`).\n\n" + table)
    with open(os.path.splitext(a.out)[0] + ".json", "w") as f:
      json.dump(dict(rows=rows, runs=runs, missing=missing(rows)), f, indent=1)


if __name__ == "__main__":
  main()
