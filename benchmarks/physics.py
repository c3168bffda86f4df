"""Physics throughput of every DMCR task: MJX steps/s against a bare MJX loop.

For each task and batch size N, one jitted `lax.scan` runs `K` control steps of a
vmapped `Task.step` with random actions (the task wrapper: action clipping, the
post-step sync, observation and reward), and, in the same run, a bare vmapped
`mjx.step` loop over the same model (the baseline). Physics steps/s counts MJX
substeps: N × K × n_sub_steps / run time. Compile time is measured apart (lower +
compile), run time is the median of `--repeats` calls after `block_until_ready`.

    python -m benchmarks.physics --tasks walker-walk --sizes 1,64,1024,8192
    python -m benchmarks.physics --tasks all --out benchmarks/results/physics_h100.jsonl

Each row is one JSON line (device kind, task, N, steps, compile_s, run_s,
physics_steps_per_s, and the baseline's numbers); a Markdown table is written
next to the JSONL file.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
from mujoco import mjx

from dmcr_jax import models


def _compile(fn, *args):
  t0 = time.perf_counter()
  compiled = jax.jit(fn).lower(*args).compile()
  return compiled, time.perf_counter() - t0


def _time(compiled, *args, repeats: int) -> float:
  jax.block_until_ready(compiled(*args))  # warm-up
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    times.append(time.perf_counter() - t0)
  return statistics.median(times)


def task_rollout(task: models.Task, n: int, k: int):
  """`(state, key) -> state` after k random-action control steps of n envs."""
  step = jax.vmap(task.step)

  def fn(state, key):
    def body(s, kk):
      a = jax.random.uniform(kk, (n, task.action_size), minval=task.action_low,
                             maxval=task.action_high)
      return step(s, a), None
    s, _ = jax.lax.scan(body, state, jax.random.split(key, k))
    return s
  return fn


def bare_rollout(task: models.Task, n: int, k: int):
  """The baseline: k × n_sub_steps bare `mjx.step`s of n envs, random ctrl."""
  m = task.mjx_model
  sub = task.n_sub_steps

  def fn(data, key):
    def body(d, kk):
      ctrl = jax.random.uniform(kk, (n, task.action_size), minval=task.action_low,
                                maxval=task.action_high)
      d = d.replace(ctrl=ctrl)
      d = jax.vmap(lambda x: jax.lax.fori_loop(0, sub, lambda _, y: mjx.step(m, y), x))(d)
      return d, None
    d, _ = jax.lax.scan(body, data, jax.random.split(key, k))
    return d
  return fn


def bench_task(name: str, sizes: list[int], k: int, repeats: int, baseline: bool,
               parallel_compiles: int = 1) -> list[dict]:
  """Benchmarks one task at every batch size; returns one row per size.

  The reset is compiled once at the largest size and sliced for smaller ones.
  With `parallel_compiles > 1` the XLA compilations of all sizes run in threads
  at once (their compile times then include that contention; rows say so).
  """
  task = models.load(name)
  full = jax.jit(jax.vmap(task.reset))(jax.random.split(jax.random.key(0), max(sizes)))
  key = jax.random.key(1)
  jobs = []
  for n in sizes:
    state = jax.tree.map(lambda x: x[:n], full)
    jobs.append((n, "task", task_rollout(task, n, k), state))
    if baseline:
      jobs.append((n, "bare", bare_rollout(task, n, k), state.data))
  with ThreadPoolExecutor(max(1, parallel_compiles)) as pool:
    compiled = list(pool.map(lambda j: _compile(j[2], j[3], key), jobs))
  rows = {}
  for (n, kind, _, arg), (fn, compile_s) in zip(jobs, compiled):
    run_s = _time(fn, arg, key, repeats=repeats)
    substeps = n * k * task.n_sub_steps
    row = rows.setdefault(n, dict(
        bench="physics", device=jax.devices()[0].device_kind,
        platform=jax.default_backend(), host=platform.node(), cpus=os.cpu_count(),
        task=name, num_envs=n, control_steps=k, n_sub_steps=task.n_sub_steps,
        concurrent_compiles=max(1, parallel_compiles)))
    if kind == "task":
      row.update(compile_s=round(compile_s, 3), run_s=run_s,
                 physics_steps_per_s=substeps / run_s, agent_steps_per_s=n * k / run_s)
    else:
      row.update(bare_compile_s=round(compile_s, 3), bare_run_s=run_s,
                 bare_physics_steps_per_s=substeps / run_s)
  for row in rows.values():
    if "bare_run_s" in row:
      row["wrapper_speed_ratio"] = row["bare_run_s"] / row["run_s"]
  return [rows[n] for n in sizes]


def markdown(rows: list[dict]) -> str:
  lines = ["| device | task | envs | physics steps/s | bare MJX steps/s | task/bare | compile s |",
           "|---|---|---:|---:|---:|---:|---:|"]
  for r in rows:
    bare = r.get("bare_physics_steps_per_s")
    lines.append(
        f"| {r['device']} | {r['task']} | {r['num_envs']:,} | {r['physics_steps_per_s']:,.0f} | "
        + (f"{bare:,.0f} | {r['wrapper_speed_ratio']:.2f}" if bare else "– | –")
        + f" | {r['compile_s']:.1f} |")
  return "\n".join(lines) + "\n"


def main(argv=None) -> None:
  argv = sys.argv[1:] if argv is None else argv
  p = argparse.ArgumentParser(description="MJX physics throughput per DMCR task.")
  p.add_argument("--tasks", default="walker-walk",
                 help="comma-separated task names or 'all' (default: %(default)s)")
  p.add_argument("--sizes", default="1,64,1024,8192", help="batch sizes")
  p.add_argument("--steps", type=int, default=20, help="control steps per timed call")
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--no-baseline", action="store_true", help="skip the bare MJX loop")
  p.add_argument("--parallel-compiles", type=int, default=1,
                 help="XLA compilations to run at once per task (default: %(default)s)")
  p.add_argument("--out", default=None, help="JSONL output path (a .md is written beside)")
  args = p.parse_args(argv)
  names = models.ALL_TASKS if args.tasks == "all" else tuple(args.tasks.split(","))
  for name in names:
    models.split_name(name)
  sizes = [int(s) for s in args.sizes.split(",")]
  rows = []
  for name in names:
    for row in bench_task(name, sizes, args.steps, args.repeats, not args.no_baseline,
                          args.parallel_compiles):
      rows.append(row)
      print(json.dumps(row), flush=True)
      if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "a") as f:
          f.write(json.dumps(row) + "\n")
  table = markdown(rows)
  print(table)
  if args.out:
    with open(os.path.splitext(args.out)[0] + ".md", "w") as f:
      f.write(f"`python -m benchmarks.physics {' '.join(argv)}`\n\n")
      f.write(table)


if __name__ == "__main__":
  main()
