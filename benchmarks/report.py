"""The suite's report from rows in the one row format (`dmcr_jax.benchmarks.rows`): the
headline, a table per benchmark, the jobs' status (`summary.md`) and a plot of
throughput against N (`throughput.png`). Rows carry "benchmark" (one of
`rows.BENCHMARKS`) besides the row format's fields.
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

from dmcr_jax.benchmarks import rows as R
from dmcr_jax.benchmarks.rows import BENCHMARKS

HEADLINE = {
    "physics": ("physics steps/s", lambda r: r["variant"]),
    "render": ("frames/s", lambda r: r.get("quality")),
    "env": ("agent-steps/s with pixels", lambda r: r["variant"]),
    "jax_render": ("JAX renderer", lambda r: r["variant"]),
    "learner": ("updates/s", lambda r: (r.get("agents"), r.get("dtype"))),
    "train": ("end-to-end training", lambda r: r["variant"]),
    "step_profile": ("one agent step, all parts", lambda r: r["variant"]),
}
"""Per benchmark in the headline: its label and how its rows are grouped; each group
shows its row at the largest N (the fastest there)."""


def ratio(r: dict) -> float | None:
  """The row's throughput over its baseline's, if both are known."""
  if r.get("throughput") and r.get("baseline_throughput"):
    return r["throughput"] / r["baseline_throughput"]
  return None


def headline(rows: list[dict]) -> list[dict]:
  """Per benchmark and group (`HEADLINE`), the row at the largest N, the fastest
  there; baselines are left out (they show as the rows' baseline columns)."""
  picked = []
  for bench, (_, key) in HEADLINE.items():
    groups: dict = {}
    for r in rows:
      if r["benchmark"] == bench and not r.get("is_baseline") and r.get("throughput"):
        groups.setdefault(key(r), []).append(r)
    picked += [max(g, key=lambda r: (r.get("n") or 0, r["throughput"]))
               for g in groups.values()]
  return picked


def headline_markdown(rows: list[dict]) -> str:
  """The headline table, or a line saying there is nothing yet."""
  picked = headline(rows)
  if not picked:
    return "No headline rows (no benchmark produced results).\n"
  return R.table(picked, [
      ("what", lambda r: HEADLINE[r["benchmark"]][0]),
      ("setting", lambda r: r["variant"] + ("" if r.get("n") is None else f", N = {r['n']:,}")),
      ("device", "device"),
      ("result", lambda r: r.get("headline") or f"{R.num(r['throughput'])} {r['unit']}"),
      ("baseline (same run)", lambda r: r.get("baseline") and
       f"{r['baseline']}: {R.num(r['baseline_throughput'])}"),
      ("× baseline", lambda r: R.fmt(ratio(r), ".1f"))])


def benchmark_markdown(rows: list[dict]) -> str:
  """One table of a benchmark's rows and, where rows carry "parts_ms", their time splits."""
  rows = sorted(rows, key=lambda r: (bool(r.get("is_baseline")), r["variant"], r.get("n") or 0))
  text = R.table(rows, [
      ("variant", lambda r: r["variant"] + (" (baseline)" if r.get("is_baseline") else "")),
      ("device", "device"), ("N", lambda r: R.num(r.get("n"))),
      ("compile s", lambda r: R.secs(r.get("compile_s"))),
      ("run s / call", lambda r: R.secs(r.get("run_s"))),
      ("throughput", lambda r: R.num(r.get("throughput"))), ("unit", "unit"),
      ("baseline", lambda r: R.num(r.get("baseline_throughput"))),
      ("× baseline", lambda r: R.fmt(ratio(r), ".2f"))])
  split = [r for r in rows if r.get("parts_ms")]
  if split:
    parts = list(dict.fromkeys(p for r in split for p in r["parts_ms"]))
    text += "\nTime per agent step (ms):\n\n" + R.table(split, [
        ("variant", "variant"), ("N", lambda r: R.num(r.get("n")))] + [
        (p, lambda r, p=p: R.secs(r["parts_ms"].get(p))) for p in parts])
  return text


def jobs_markdown(results: Iterable[dict]) -> str:
  """The status of every job; those not ok with their last line of output."""
  def last(r):
    line = next((t for t in reversed(r.get("tail") or []) if t.strip()), "")
    if r["status"] == "ok" or not line:
      return ""
    return "`" + line.strip().replace("|", "\\|").replace("`", "'")[:160] + "`"
  return R.table(list(results), [
      ("job", "name"), ("status", "status"), ("exit", "returncode"), ("rows", "rows"),
      ("wall s", lambda r: f"{r['wall_s']:,.1f}"), ("last output", last)])


def summary_markdown(rows: list[dict], results: Sequence[dict], meta: dict) -> str:
  """The whole `summary.md`: what ran, the headline, the jobs, a table per benchmark.

  Args:
    rows: the suite's rows.
    results: `JobResult`s as dicts, in run order.
    meta: "commands" (the suite invocations: command, mode, time_utc, wall_s, cpus, host).
  """
  devices = sorted({str(r.get("device")) for r in rows}) or ["(no rows)"]
  out = [f"# Benchmark suite ({', '.join(devices)})", ""]
  out += [f"- `{c['command']}` — {c['mode']} mode, {c['time_utc']}, {c['wall_s']:,.0f} s, "
          f"{c.get('cpus')} cores ({c.get('host')})" for c in meta.get("commands", [])]
  failed = [r for r in results if r["status"] != "ok"]
  out += ["", f"{len(results)} job(s), {len(failed)} not ok. Throughputs are medians of timed "
          "calls after compilation; compile (or start-up) time is reported apart; ratios "
          "are to the baseline measured in the same run; N: envs, frames or images per "
          "call. Rows: `benchmarks.jsonl`; plot: `throughput.png`; child output: `logs/`.",
          "", "## Headline", "", headline_markdown(rows), "## Jobs", "", jobs_markdown(results)]
  for bench in BENCHMARKS:
    mine = [r for r in rows if r["benchmark"] == bench]
    if mine:
      out += [f"## {bench}", "", benchmark_markdown(mine)]
  return "\n".join(out)


def plot_throughput(rows: list[dict], path: str) -> bool:
  """Throughput against N, log-log, one panel per benchmark (PNG): a line per variant,
  a dashed one per baseline measured in the same run.

  Returns:
    False (and no file) when no row has an N and a throughput.
  """
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  usable = [r for r in rows if r.get("n") and r.get("throughput") and not r.get("is_baseline")
            and r["benchmark"] != "train"]
  benches = [b for b in BENCHMARKS if any(r["benchmark"] == b for r in usable)]
  if not benches:
    return False
  cols = min(3, len(benches))
  fig, axes = plt.subplots(math.ceil(len(benches) / cols), cols,
                           figsize=(5.2 * cols, 4.0 * math.ceil(len(benches) / cols)),
                           squeeze=False)
  for ax, bench in zip(axes.flat, benches):
    mine = [r for r in usable if r["benchmark"] == bench]
    lines = {}
    for r in mine:
      lines.setdefault(r["variant"], set()).add((r["n"], r["throughput"]))
      if r.get("baseline") and r.get("baseline_throughput"):
        lines.setdefault(r["baseline"] + " (baseline)", set()).add(
            (r["n"], r["baseline_throughput"]))
    for name, pts in lines.items():
      dashed = name.endswith(" (baseline)")
      if dashed and len(pts) == 1:  # measured at one N: a line across the panel
        ax.axhline(min(pts)[1], ls="--", lw=1, color="gray", label=name)
      else:
        ax.plot(*zip(*sorted(pts)), "--" if dashed else "-", marker="o", ms=4, label=name)
    ax.set(xscale="log", yscale="log", title=bench, xlabel="N (envs / frames / images per call)",
           ylabel=" / ".join(dict.fromkeys(r["unit"] for r in mine)))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6 if len(lines) > 6 else 7, ncol=2 if len(lines) > 8 else 1)
  for ax in list(axes.flat)[len(benches):]:
    ax.axis("off")
  devices = ", ".join(sorted({str(r.get("device")) for r in usable}))
  fig.suptitle(f"dmcr_jax benchmarks — throughput against N ({devices})")
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)
  return True


