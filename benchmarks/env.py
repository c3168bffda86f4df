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
  observations out of shared memory (`env.timings`).

    python -m benchmarks.env --sizes 1,16,256,1024 --qualities exact,fast,fastest \
        --out benchmarks/results/env_h100.jsonl

One JSON line per row and a Markdown table beside the JSONL file.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

import dmcr_jax  # first: picks a headless MUJOCO_GL before dm_control reads it
from benchmarks.render import _gpu_name


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
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    for _ in range(warmup):  # compiles the step
      env.step(env.action_space.sample())
    warm_s = time.perf_counter() - t0
    env.reset_timings()
    steps = 0
    t0 = time.perf_counter()
    while steps < 3 or time.perf_counter() - t0 < seconds:
      env.step(rng.uniform(env.single_action_space.low, env.single_action_space.high,
                           env.action_space.shape).astype(np.float32))
      steps += 1
    wall = time.perf_counter() - t0
    split = {f"{k}_ms": v / steps * 1e3 for k, v in env.timings.items()}
    other = wall / steps * 1e3 - sum(split.values())
    return dict(num_envs=n, quality=quality, workers=env._pool.num_workers, steps=steps,
                copy_obs=copy_obs, ls_iterations=ls_iterations or "default",
                start_s=start_s, warmup_s=warm_s, step_ms=wall / steps * 1e3,
                agent_steps_per_s=n * steps / wall, other_ms=other, **split)


def markdown(rows: list[dict]) -> str:
  """One table of the "env" rows; each is compared with the original pipeline
  measured in its own run ("original" rows: the latest one is described above)."""
  original = [r for r in rows if r.get("kind") == "original"][-1]
  rows = [r for r in rows if r.get("kind") == "env"]
  lines = [f"Original pipeline (one dm_control env, step ×{original['frame_skip']} + "
           f"`physics.render`, model rebuilt per reset), latest run: "
           f"{original['agent_steps_per_s']:,.0f} agent-steps/s "
           f"({original['step_ms']:.1f} ms a step, {original['rebuild_ms']:.0f} ms a rebuild; "
           f"{original['agent_steps_per_s_no_rebuild']:,.0f} without rebuilds).", "",
           "| device | quality | envs | workers | stacked by | copy_obs | line search "
           "| agent-steps/s | original "
           "| × original | physics ms | transfer ms | render ms | copy / stack ms | UTC |",
           "|---|---|---:|---:|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
  for r in rows:
    by_workers = "copy_ms" in r
    lines.append(
        f"| {r['device']} | {r['quality']} | {r['num_envs']:,} | {r['workers']} | "
        f"{'workers' if by_workers else 'main process'} | "
        f"{'yes' if r.get('copy_obs', True) else 'no'} | {r.get('ls_iterations', 'default')} | "
        f"{r['agent_steps_per_s']:,.0f} | "
        f"{r['original_agent_steps_per_s']:,.0f} | {r['speedup']:.1f} | "
        f"{r['physics_ms']:.1f} | {r['transfer_ms']:.1f} | {r['render_ms']:.1f} | "
        f"{r['copy_ms'] if by_workers else r['stack_ms']:.1f} | {r['time_utc'][11:16]} |")
  return "\n".join(lines) + "\n"


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
  p.add_argument("--no-copy", action="store_true",
                 help="make(copy_obs=False): observations are views of shared memory")
  p.add_argument("--ls-iterations", default="default",
                 help="comma-separated MJX line-search caps to run ('default': the "
                      "env's own)")
  p.add_argument("--out", default=None, help="JSONL path (appended to); .md beside")
  args = p.parse_args(argv)
  import jax
  device = _gpu_name() if jax.default_backend() == "gpu" else "cpu"
  common = dict(bench="env", device=device, platform=jax.default_backend(),
                cpus=os.cpu_count(), host=platform.node(), task=args.task,
                frame_skip=args.frame_skip, image_size=args.image_size, vary="all",
                time_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
  original = original_pipeline(args.task, args.frame_skip, args.image_size,
                               args.original_steps)
  rows = [dict(common, kind="original", **original)]
  _emit(rows[0], args.out)
  budgets = [None if b == "default" else int(b) for b in args.ls_iterations.split(",")]
  for quality in args.qualities.split(","):
    for n, ls in [(int(s), b) for s in args.sizes.split(",") for b in budgets]:
      row = dict(common, kind="env", **bench_env(
          args.task, n, quality, args.workers, args.frame_skip, args.image_size,
          args.seconds, copy_obs=not args.no_copy, ls_iterations=ls))
      row["original_agent_steps_per_s"] = original["agent_steps_per_s"]
      row["speedup"] = row["agent_steps_per_s"] / original["agent_steps_per_s"]
      rows.append(row)
      _emit(row, args.out)
  print(markdown(rows))
  if args.out:
    with open(args.out) as f:
      rows = [json.loads(line) for line in f]
    with open(os.path.splitext(args.out)[0] + ".md", "w") as f:
      f.write(f"Rows of `python -m benchmarks.env` runs appended to "
              f"`{os.path.basename(args.out)}` (each row holds its device, settings and "
              f"UTC time); the last: `python -m benchmarks.env {' '.join(argv)}` on "
              f"{device} with {os.cpu_count()} cores. The original pipeline rebuilds the "
              "model with `suite.load` (no texture edits).\n\n" + markdown(rows))


def _emit(row: dict, out: str | None) -> None:
  print(json.dumps(row), flush=True)
  if out:
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    with open(out, "a") as f:
      f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
  main()
