"""The few-shot curve across runs: several runs' `evaluate` results (eval.json) of one task
merged into one generalisation curve against the number of training looks, over all
their ranges, augmentations and seeds.

    python -m dmcr_jax.benchmarks.few_shot runs/few_shot/*/eval/eval.json --out runs/few_shot

Per task whose files' agents trained on more than one training-look range, the files
are merged by `dmcr_jax.protocol_report.merge_summaries` (one protocol: the same
`PROTOCOL_OPTIONS` and conditions, else refused naming the differing option; each
seed of an augmentation and range once) and drawn by `write_few_shot` as
``<out>/few_shot_<task>.md``, ``.json`` and ``.png``: per condition the mean over the
seeds, with the min–max over them in the table and as a band in the plot.
`dmcr-sweep` writes the same files beside its ``table.md`` (`curves`).
"""

from __future__ import annotations

import argparse
import os

from dmcr_jax import protocol_report
from dmcr_jax.benchmarks.paper_table import read


def several_ranges(results: list[dict]) -> bool:
  """Whether the agents of `results` (eval.json summaries) trained on more than one
  training-look range."""
  return len({a.get("train_look") for r in results for a in r["agents"]}) > 1


def curves(paths: list[str], out_dir: str) -> dict[str, list[dict]]:
  """Merges and draws the curves of the module doc from the eval.json at `paths`.

  Args:
    paths: `evaluate` results (eval.json), of one or more tasks.
    out_dir: where ``few_shot_<task>.{md,json,png}`` go (made).

  Returns:
    {task: the curve's rows (`protocol_report.few_shot_rows`)} for each task drawn
    (a task whose agents trained on one range has no curve).

  Raises:
    ValueError: a file that is not an evaluate result, or files of one task that
      `merge_summaries` refuses (another protocol, a repeated seed, no "looks").
  """
  by_task: dict[str, list[tuple[str, dict]]] = {}
  for path in paths:
    result = read(path)
    by_task.setdefault(result["task"], []).append((path, result))
  out = {}
  for task, files in by_task.items():
    results = [r for _, r in files]
    if several_ranges(results):
      merged = protocol_report.merge_summaries(results, [p for p, _ in files])
      out[task] = protocol_report.write_few_shot(merged, out_dir, name=f"few_shot_{task}")
  return out


def main(argv=None) -> None:
  """Command-line entry (module docstring)."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.benchmarks.few_shot",
                              description=__doc__.splitlines()[0])
  p.add_argument("results", nargs="+", metavar="EVAL_JSON", help="evaluate's eval.json files")
  p.add_argument("--out", required=True, help="the folder of few_shot_<task>.{md,json,png}")
  a = p.parse_args(argv)
  try:
    drawn = curves(a.results, a.out)
  except ValueError as e:
    p.error(str(e))
  if not drawn:
    p.error("no task among these files has agents of more than one training-look range; "
            "a few-shot curve needs at least two")
  for task in drawn:
    name = os.path.join(a.out, f"few_shot_{task}")
    with open(name + ".md") as f:
      print(f.read())
    print(f"wrote {name}.md, .json and .png")


if __name__ == "__main__":
  main()
