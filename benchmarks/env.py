"""Pixel env throughput: `dmcr_jax.make` agent-steps/s against the original pipeline.

For walker-walk (default) at frame skip 2 with every visual factor varying (env i
shows visual seed i + 1), it measures in one run:
- the original DMCR pipeline: one dm_control env, `frame_skip` × `env.step` and one
  `physics.render` (84×84, camera 0) per agent step, the model rebuilt at every
  reset as the original did (`suite.load`); its agent-steps/s include one rebuild
  per episode;
- `dmcr_jax.make` at each (N, render quality): agent-steps/s of `env.step` with
  random actions over at least `--seconds` after warm-up, and the time per step
  split into physics (the jitted batched step), device→host transfer, rendering
  (the render workers also stack the frames) and the copy of the stacked
  observations out of shared memory (`env.timings`);
- with `--renderers pool,jax`, also `dmcr_jax.make(..., renderer="jax")` at each N
  (physics, ray casting and stacking in one jitted call, observations copied to
  the host as for the pool, or left on the device with `--obs-on-device`, as a
  JAX learner takes them): agent-steps/s of `env.step`, and the parts timed on
  their own on the same states: the jitted physics step alone, the jitted render
  alone, and the device→host copy of the observations (`env.timings`). The two
  parts run fused in `env.step`, so their sum only approximates its time.

    python -m dmcr_jax.benchmarks.env --sizes 1,16,256,1024 --qualities exact,fast,fastest \
        --out benchmarks/results/env_h100.jsonl
    python -m dmcr_jax.benchmarks.env --sizes 1024 --renderers pool,jax --ls-iterations 4 \
        --no-copy --out benchmarks/results/env_h100.jsonl

One JSON line per row and a Markdown table beside the JSONL file.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

import dmcr_jax  # first: picks a headless MUJOCO_GL before dm_control reads it
from dmcr_jax.benchmarks import rows as R
from dmcr_jax.env_checks import check_renderer_name


def original_pipeline(task: str, frame_skip: int, size: int, steps: int,
                      rebuilds: int = 3) -> dict:
  """Agent-steps/s of one dm_control env rendering every step, rebuilt per reset."""
  from dm_control import suite
  domain, name = task.split("-", 1)
  t0 = time.perf_counter()
  for _ in range(rebuilds):
    env = suite.load(domain, name, task_kwargs={"random": 0})
    env.reset()
  rebuild_s = (time.perf_counter() - t0) / rebuilds
  spec = env.action_spec()
  rng = np.random.default_rng(0)
  env.physics.render(size, size, camera_id=0)  # GL context warm-up
  t0 = time.perf_counter()
  for _ in range(steps):
    a = rng.uniform(spec.minimum, spec.maximum)
    for _ in range(frame_skip):
      ts = env.step(a)
    env.physics.render(size, size, camera_id=0)
    if ts.last():
      env.reset()
  step_s = (time.perf_counter() - t0) / steps
  episode = 1000 // frame_skip
  return dict(step_ms=step_s * 1e3, rebuild_ms=rebuild_s * 1e3,
              agent_steps_per_s=1.0 / (step_s + rebuild_s / episode),
              agent_steps_per_s_no_rebuild=1.0 / step_s)


def uniform_actions(env, rng: np.random.Generator) -> np.ndarray:
  """float32 (N, A) actions drawn uniformly inside the env's action bounds."""
  return rng.uniform(env.single_action_space.low, env.single_action_space.high,
                     env.action_space.shape).astype(np.float32)


def timed_steps(env, seconds: float, warmup: int, rng: np.random.Generator
                ) -> tuple[int, float]:
  """Resets `env`, steps it `warmup` times (compiling), clears its timings, then
  steps it with random actions for at least `seconds` (and 3 steps).

  Returns:
    (timed steps, their wall time in seconds).
  """
  env.reset(seed=0)
  for _ in range(warmup):
    env.step(env.action_space.sample())
  env.reset_timings()
  steps, t0 = 0, time.perf_counter()
  while steps < 3 or time.perf_counter() - t0 < seconds:
    env.step(uniform_actions(env, rng))
    steps += 1
  return steps, time.perf_counter() - t0


def bench_env(task: str, n: int, quality: str, workers: int | None, frame_skip: int,
              size: int, seconds: float, warmup: int = 3, copy_obs: bool = True,
              ls_iterations: int | None = None) -> dict:
  """Agent-steps/s and the time split of `dmcr_jax.make(task, n)`."""
  t0 = time.perf_counter()
  env = dmcr_jax.make(task, num_envs=n, visual_seeds=np.arange(1, n + 1), vary="all",
                      frame_skip=frame_skip, image_size=size, quality=quality,
                      workers=workers, copy_obs=copy_obs, ls_iterations=ls_iterations)
  with env:
    start_s = time.perf_counter() - t0
    steps, wall = timed_steps(env, seconds, warmup, np.random.default_rng(0))
    warm_s = time.perf_counter() - t0 - wall
    split = {f"{k}_ms": v / steps * 1e3 for k, v in env.timings.items()}
    other = wall / steps * 1e3 - sum(split.values())
    return dict(num_envs=n, quality=quality, workers=env._pool.num_workers, steps=steps,
                copy_obs=copy_obs, ls_iterations=ls_iterations or "default",
                start_s=start_s, warmup_s=warm_s, step_ms=wall / steps * 1e3,
                agent_steps_per_s=n * steps / wall, other_ms=other, **split)


def bench_jax_env(task: str, n: int, frame_skip: int, size: int, seconds: float,
                  warmup: int = 3, ls_iterations: int | None = None,
                  obs_on_device: bool = False) -> dict:
  """Agent-steps/s of `dmcr_jax.make(task, n, renderer="jax")` and its parts timed
  alone (module docstring)."""
  import jax
  import jax.numpy as jnp
  t0 = time.perf_counter()
  env = dmcr_jax.make(task, num_envs=n, visual_seeds=np.arange(1, n + 1), vary="all",
                      frame_skip=frame_skip, image_size=size, renderer="jax",
                      ls_iterations=ls_iterations, obs_on_device=obs_on_device)
  with env:
    rng = np.random.default_rng(0)
    steps, wall = timed_steps(env, seconds, warmup, rng)
    warm_s = time.perf_counter() - t0 - wall
    random_actions = lambda: uniform_actions(env, rng)
    transfer_ms = env.timings["transfer"] / steps * 1e3

    # The parts alone, on the env's current states (each compiled, then timed).
    ps = env.pixel_state
    carried = [jax.tree.map(jnp.copy, ps.physics)]  # `_step` donates its state

    def physics():
      carried[0] = env._step(carried[0], random_actions(), env._seed_arg)[0]
      return carried[0]
    render_fn = jax.jit(lambda penv, es, look: penv.render(es, look))
    render = lambda: render_fn(env.functional, ps.physics, ps.look)
    parts = {}
    for name, fn in (("physics", physics), ("render", render)):
      jax.block_until_ready(fn())
      reps = max(3, int(min(seconds, 2.0) / max(wall / steps, 1e-3)))
      t1 = time.perf_counter()
      for _ in range(reps):
        out = fn()
      jax.block_until_ready(out)
      parts[f"{name}_ms"] = (time.perf_counter() - t1) / reps * 1e3
    return dict(num_envs=n, renderer="jax", quality="ray caster", workers=0,
                steps=steps, copy_obs=True, obs_on_device=obs_on_device, ls_iterations=ls_iterations or "default",
                warmup_s=warm_s, step_ms=wall / steps * 1e3,
                agent_steps_per_s=n * steps / wall, transfer_ms=transfer_ms,
                fused_step_ms=env.timings["step"] / steps * 1e3, **parts)


def obs_kept(row: dict) -> str:
  """The table's copy_obs column: yes / no (pool), or where the JAX env's obs go."""
  if row.get("renderer") == "jax":
    return "on device" if row.get("obs_on_device") else "to host"
  return "yes" if row.get("copy_obs", True) else "no"


def variant(row: dict) -> str:
  """The row's line in the suite's plot: quality and the settings that differ."""
  name = row["quality"]
  if row.get("renderer") == "jax" and row.get("obs_on_device"):
    name += ", obs on device"
  if row.get("copy_obs") is False:
    name += ", no copy"
  if row.get("ls_iterations") not in (None, "default"):
    name += f", line search {row['ls_iterations']}"
  return name


def _stacked(r: dict) -> str:
  return ("jitted step" if r.get("renderer") == "jax" else
          "workers" if "copy_ms" in r else "main process")


def markdown(rows: list[dict]) -> str:
  """One table of the "env" rows; each is compared with the original pipeline
  measured in its own run ("original" rows: the latest one is described above)."""
  original = [r for r in rows if r.get("kind") == "original"][-1]
  rows = [r for r in rows if r.get("kind") == "env"]
  copy = lambda r: ("-" if r.get("renderer") == "jax" else
                    f"{r['copy_ms'] if 'copy_ms' in r else r['stack_ms']:.1f}")
  return (f"Original pipeline (one dm_control env, step ×{original['frame_skip']} + "
          f"`physics.render`, model rebuilt per reset), latest run: "
          f"{original['agent_steps_per_s']:,.0f} agent-steps/s "
          f"({original['step_ms']:.1f} ms a step, {original['rebuild_ms']:.0f} ms a rebuild; "
          f"{original['agent_steps_per_s_no_rebuild']:,.0f} without rebuilds).\n\n"
          + R.table(rows, [
              ("device", "device"), ("renderer", lambda r: r.get("renderer", "pool")),
              ("quality", "quality"), ("envs", lambda r: f"{r['num_envs']:,}"),
              ("workers", "workers"), ("stacked by", _stacked), ("copy_obs", obs_kept),
              ("line search", lambda r: r.get("ls_iterations", "default")),
              ("agent-steps/s", lambda r: f"{r['agent_steps_per_s']:,.0f}"),
              ("original", lambda r: f"{r['original_agent_steps_per_s']:,.0f}"),
              ("× original", lambda r: f"{r['speedup']:.1f}"),
              ("physics ms", lambda r: f"{r['physics_ms']:.1f}"),
              ("transfer ms", lambda r: f"{r['transfer_ms']:.1f}"),
              ("render ms", lambda r: f"{r['render_ms']:.1f}"), ("copy / stack ms", copy),
              ("UTC (month-day)", lambda r: f"{r['time_utc'][5:10]} {r['time_utc'][11:16]}")]))


def main(argv=None) -> None:
  argv = sys.argv[1:] if argv is None else argv
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--sizes", default="1,16,256,1024", help="numbers of envs")
  p.add_argument("--qualities", default="fastest", help="render presets, comma-separated")
  p.add_argument("--workers", type=int, default=None, help="render workers (default: cores)")
  p.add_argument("--frame-skip", type=int, default=2)
  p.add_argument("--image-size", type=int, default=84)
  p.add_argument("--seconds", type=float, default=5.0, help="timed seconds per row")
  p.add_argument("--original-steps", type=int, default=200)
  p.add_argument("--renderers", default="pool",
                 help="comma-separated: pool (the render pool, --qualities apply) and/or "
                      "jax (the ray caster)")
  p.add_argument("--obs-on-device", action="store_true",
                 help="renderer jax: make(obs_on_device=True), observations stay on the "
                      "device (no device→host copy)")
  p.add_argument("--no-copy", action="store_true",
                 help="make(copy_obs=False): observations are views of shared memory")
  p.add_argument("--ls-iterations", default="default",
                 help="comma-separated MJX line-search caps to run ('default': the "
                      "env's own)")
  p.add_argument("--out", default=None, help="JSONL path (appended to); .md beside")
  args = p.parse_args(argv)
  renderers = args.renderers.split(",")
  try:
    for name in renderers:
      check_renderer_name(name)
  except ValueError as e:
    p.error(str(e))
  import jax
  device = (R.gpu_name() or "none") if jax.default_backend() == "gpu" else "cpu"
  common = dict(bench="env", device=device, platform=jax.default_backend(),
                cpus=os.cpu_count(), host=platform.node(), task=args.task,
                frame_skip=args.frame_skip, image_size=args.image_size, vary="all",
                time_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
  original = original_pipeline(args.task, args.frame_skip, args.image_size,
                               args.original_steps)
  baseline = "original DMCR pipeline"
  rows = [R.row(dict(common, kind="original", **original), baseline, n=1,
                throughput=original["agent_steps_per_s"], unit="agent-steps/s",
                run_s=original["step_ms"] / 1e3, is_baseline=True)]
  R.emit(rows[0], args.out)
  budgets = [None if b == "default" else int(b) for b in args.ls_iterations.split(",")]
  runs = [(q, int(s), b) for q in (args.qualities.split(",") if "pool" in renderers else [])
          for s in args.sizes.split(",") for b in budgets]
  if "jax" in renderers:
    runs += [("jax", int(s), b) for s in args.sizes.split(",") for b in budgets]
  for quality, n, ls in runs:
    if quality == "jax":
      result = bench_jax_env(args.task, n, args.frame_skip, args.image_size,
                             args.seconds, ls_iterations=ls,
                             obs_on_device=args.obs_on_device)
    else:
      result = bench_env(args.task, n, quality, args.workers, args.frame_skip,
                         args.image_size, args.seconds, copy_obs=not args.no_copy,
                         ls_iterations=ls)
    row = dict(common, kind="env", **result)
    row["original_agent_steps_per_s"] = original["agent_steps_per_s"]
    row["speedup"] = row["agent_steps_per_s"] / original["agent_steps_per_s"]
    row["parts_ms"] = {k[:-3]: row[k] for k in ("physics_ms", "transfer_ms", "render_ms",
                                                "copy_ms", "stack_ms", "other_ms") if k in row}
    row = R.row(row, variant(row), n=n, throughput=row["agent_steps_per_s"],
                unit="agent-steps/s", compile_s=row["warmup_s"] - row.get("start_s", 0.0),
                run_s=row["step_ms"] / 1e3, baseline=baseline,
                baseline_throughput=original["agent_steps_per_s"])
    rows.append(row)
    R.emit(row, args.out)
  print(markdown(rows))
  if args.out:
    R.write_markdown(args.out, f"Rows of `python -m dmcr_jax.benchmarks.env` runs appended to "
                     f"`{os.path.basename(args.out)}` (each row holds its device, settings "
                     f"and UTC time); the last: `python -m dmcr_jax.benchmarks.env {' '.join(argv)}` "
                     f"on {device} with {os.cpu_count()} cores. The original pipeline "
                     "rebuilds the model with `suite.load` (no texture edits).\n\n"
                     + markdown(R.read(args.out)))


if __name__ == "__main__":
  main()
