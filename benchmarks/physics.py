"""Physics throughput of every DMCR task: MJX steps/s against a bare MJX loop.

For each task and batch size N, one jitted `lax.scan` runs `K` control steps of a
vmapped `Task.step` with random actions (the task wrapper: action clipping, the
post-step sync, observation and reward), and, in the same run, a bare vmapped
`mjx.step` loop over the same model (the baseline). Physics steps/s counts MJX
substeps: N × K × n_sub_steps / run time. Compile time is measured apart (lower +
compile), run time is the median of `--repeats` calls after `block_until_ready`.

    python -m dmcr_jax.benchmarks.physics --tasks walker-walk --sizes 1,64,1024,8192
    python -m dmcr_jax.benchmarks.physics --tasks all --out benchmarks/results/physics_h100.jsonl

    python -m dmcr_jax.benchmarks.physics --tasks walker-walk --sizes 8192 \
        --solver-iterations 1 --ls-iterations 4   # mjx.benchmark's solver budget
    python -m dmcr_jax.benchmarks.physics --tasks walker-walk --sizes 8192 \
        --matmul-precision default   # JAX's precision: TensorFloat-32 products on an H100
    JAX_PLATFORMS=cpu python -m dmcr_jax.benchmarks.physics --tasks walker-walk --sizes 16,32 \
        --xla-defaults   # XLA:CPU's YNNPACK fusions on, as a plain `jax.jit` compiles them

Each row is one JSON line (device kind, task, N, steps, solver budget, compile_s,
run_s, physics_steps_per_s, and the baseline's numbers); a Markdown table is
written next to the JSONL file. Runs append to `--out` and skip what is there, so
a sweep cut off by a time limit resumes where it stopped.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import jax
from dmcr_jax._mjx import mjx  # mujoco.mjx, quietly

from dmcr_jax.benchmarks import rows as R
from dmcr_jax import models
from dmcr_jax.models import base


def _compile(fn, *args, options=None):
  t0 = time.perf_counter()
  compiled = jax.jit(fn, compiler_options=options or None).lower(*args).compile()
  return compiled, time.perf_counter() - t0


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
      # At the task physics' precision (`base.full_precision`): only the wrapper differs.
      d = jax.vmap(base.full_precision(
          lambda x: jax.lax.fori_loop(0, sub, lambda _, y: mjx.step(m, y), x)))(d)
      return d, None
    d, _ = jax.lax.scan(body, data, jax.random.split(key, k))
    return d
  return fn


def _row(task: models.Task, n: int, k: int, parallel_compiles: int, options: dict) -> dict:
  return dict(
      bench="physics", device=jax.devices()[0].device_kind,
      platform=jax.default_backend(), host=platform.node(), cpus=os.cpu_count(),
      task=task.name, num_envs=n, control_steps=k, n_sub_steps=task.n_sub_steps,
      solver_iterations=task.solver_iterations, ls_iterations=task.ls_iterations,
      matmul_precision=base.PHYSICS_MATMUL_PRECISION,
      concurrent_compiles=max(1, parallel_compiles),
      xla_flags=os.environ.get("XLA_FLAGS", ""), compiler_options=options,
      time_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))


def bench_tasks(names: list[str], sizes: list[int], k: int, repeats: int, baseline: bool,
                parallel_compiles: int = 1, solver: tuple = (None, None),
                options: dict | None = None):
  """Benchmarks several tasks at every batch size; yields one row per (task, size).

  `options` are the rollouts' XLA compile options (None: the physics' own,
  `base.physics_compiler_options()`; {}: XLA's defaults).

  Each task's reset is compiled once at the largest size and sliced for smaller
  ones. All XLA compilations (resets, then rollouts) run in `parallel_compiles`
  threads at once (compile times then include that contention; rows say so);
  the timed runs happen afterwards, one at a time.
  """
  tasks = [models.load(name, *solver) for name in names]
  options = base.physics_compiler_options() if options is None else options
  key = jax.random.key(1)
  with ThreadPoolExecutor(max(1, parallel_compiles)) as pool:
    resets = list(pool.map(
        lambda t: _compile(jax.vmap(t.reset), jax.random.split(jax.random.key(0), max(sizes))),
        tasks))
    jobs = []
    for task, (reset, _) in zip(tasks, resets):
      full = reset(jax.random.split(jax.random.key(0), max(sizes)))
      for n in sizes:
        state = jax.tree.map(lambda x: x[:n], full)
        jobs.append((task, n, "task", task_rollout(task, n, k), state))
        if baseline:
          jobs.append((task, n, "bare", bare_rollout(task, n, k), state.data))
    compiled = list(pool.map(lambda j: _compile(j[3], j[4], key, options=options), jobs))
  rows = {}
  for (task, n, kind, _, arg), (fn, compile_s) in zip(jobs, compiled):
    run_s = statistics.median(R.time_calls(lambda: fn(arg, key), repeats=repeats))
    substeps = n * k * task.n_sub_steps
    row = rows.setdefault((task.name, n), _row(task, n, k, parallel_compiles, options))
    if kind == "task":
      row.update(compile_s=round(compile_s, 3), run_s=run_s,
                 physics_steps_per_s=substeps / run_s, agent_steps_per_s=n * k / run_s)
    else:
      row.update(bare_compile_s=round(compile_s, 3), bare_run_s=run_s,
                 bare_physics_steps_per_s=substeps / run_s)
    if "run_s" in row and ("bare_run_s" in row or not baseline):
      if baseline:
        row["wrapper_speed_ratio"] = row["bare_run_s"] / row["run_s"]
      bare = row.get("bare_physics_steps_per_s")  # yielded once complete: a cut-off run keeps it
      yield R.row(row, task.name, n=n, throughput=row["physics_steps_per_s"],
                  unit="physics steps/s", compile_s=row["compile_s"], run_s=row["run_s"],
                  baseline=f"{task.name} bare MJX" if bare else None,
                  baseline_throughput=bare)


def _done(path: str | None, solver: tuple, options: dict) -> set:
  """(task, num_envs) pairs already in `path` for this device, solver budget,
  precision and compile options."""
  if not path or not os.path.exists(path):
    return set()
  device = jax.devices()[0].device_kind
  done = set()
  for r in R.read(path):
    task = models.load(r["task"], *solver)
    if (r["device"] == device and r.get("solver_iterations") == task.solver_iterations
        and r.get("ls_iterations") == task.ls_iterations
        and r.get("matmul_precision", "default") == base.PHYSICS_MATMUL_PRECISION
        and r.get("compiler_options", {}) == options):
      done.add((r["task"], r["num_envs"]))
  return done


def markdown(rows: list[dict]) -> str:
  """The rows as one Markdown table."""
  return R.table(rows, [
      ("device", "device"), ("task", "task"),
      ("solver it/ls",
       lambda r: f"{r.get('solver_iterations', '?')}/{r.get('ls_iterations', '?')}"),
      ("matmul precision", lambda r: r.get("matmul_precision", "default")),
      ("XLA:CPU YNNPACK fusions",
       lambda r: "off" if r.get("compiler_options") == base.NO_YNN_FUSIONS else "XLA's default"),
      ("envs", lambda r: f"{r['num_envs']:,}"),
      ("physics steps/s", lambda r: f"{r['physics_steps_per_s']:,.0f}"),
      ("bare MJX steps/s", lambda r: R.fmt(r.get("bare_physics_steps_per_s"), ",.0f")),
      ("task/bare", lambda r: R.fmt(r.get("wrapper_speed_ratio"), ".2f")),
      ("compile s", lambda r: f"{r['compile_s']:.1f}")])


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
                 help="XLA compilations to run at once (default: %(default)s)")
  p.add_argument("--tasks-per-wave", type=int, default=1,
                 help="tasks compiled together before their runs are timed and written")
  p.add_argument("--solver-iterations", type=int, default=None,
                 help="override the solver's iterations (default: dm_control's)")
  p.add_argument("--ls-iterations", type=int, default=None,
                 help="override the line-search iterations (default: dm_control's)")
  p.add_argument("--matmul-precision", default=base.PHYSICS_MATMUL_PRECISION,
                 choices=base.MATMUL_PRECISIONS,
                 help="precision of the physics' matrix products (default: %(default)s, the "
                      "physics' own; 'default' is JAX's: TensorFloat-32 on an H100)")
  p.add_argument("--xla-defaults", action="store_true",
                 help="compile the rollouts with XLA's default options instead of the "
                      "physics' own (`models.base.physics_compiler_options`: XLA:CPU's "
                      "YNNPACK fusions off)")
  p.add_argument("--out", default=None,
                 help="JSONL output path, appended to; (task, size) rows already there for "
                      "this device, solver, matmul precision and compile options are skipped, so a cut-off run resumes "
                      "(a .md of all its rows is written beside)")
  args = p.parse_args(argv)
  with base.physics_matmul_precision(args.matmul_precision):
    _run(args)


def _run(args) -> None:
  names = models.ALL_TASKS if args.tasks == "all" else tuple(args.tasks.split(","))
  for name in names:
    models.split_name(name)
  sizes = [int(s) for s in args.sizes.split(",")]
  solver = (args.solver_iterations, args.ls_iterations)
  options = {} if args.xla_defaults else base.physics_compiler_options()
  done = _done(args.out, solver, options)
  todo = [n for n in names if not all((n, size) in done for size in sizes)]
  rows = []
  if len(todo) < len(names):
    print(f"skipping {len(names) - len(todo)} task(s) already in {args.out}", flush=True)
  for i in range(0, len(todo), max(1, args.tasks_per_wave)):
    wave = todo[i:i + max(1, args.tasks_per_wave)]
    for row in bench_tasks(wave, sizes, args.steps, args.repeats, not args.no_baseline,
                           args.parallel_compiles, solver, options):
      R.emit(row, args.out)
      rows.append(row)
  if args.out:
    rows = R.read(args.out)
    R.write_markdown(args.out, "Rows from `python -m dmcr_jax.benchmarks.physics` runs appended to "
                     f"`{os.path.basename(args.out)}` (each row holds its device and "
                     "settings).\n\n" + markdown(rows))
  print(markdown(rows))


if __name__ == "__main__":
  main()
