"""Render throughput: `RenderPool` frames/s against a naive `mujoco.Renderer` loop.

For walker (default) with every visual factor varying (one visual seed per env)
and random states, it measures, in one run:
- the baseline: one `mujoco.Renderer` in this process, one `render()` per frame,
  the look applied per frame (`render_model.FrameRenderer`);
- the pool at each (batch, workers, quality): frames/s of `RenderPool.render`
  (the median of `--repeats` calls after a warm-up call), and its start-up time
  (creating the pool until every worker is ready: seconds, column "start s").
  With the exact preset, 16 frames spread over the batch are compared with the
  single-frame reference renderer (`reference_equal`: how many are bit-identical).

    python -m dmcr_jax.benchmarks.render --batches 64,256,1024,4096 --workers 1,4,8,16 \
        --qualities exact,fast,fastest --out benchmarks/results/render_h100.jsonl

One JSON line per row (device, GL backend, cpus, sizes, frames/s, speed-up over
the baseline) and a Markdown table beside the JSONL file.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np

from dmcr_jax.benchmarks import rows as R


def _inputs(rm, n: int, seed: int = 0):
  rng = np.random.default_rng(seed)
  looks = rm.sample(np.arange(1, n + 1), vary="all")
  qpos = rm.model.qpos0 + 0.2 * rng.standard_normal((n, rm.model.nq))
  return qpos, looks


def baseline(task: str, frames: int, size: int) -> float:
  """Frames/s of one `mujoco.Renderer` rendering frame by frame."""
  from dmcr_jax.visuals import render_model as rmod
  rm = rmod.build_render_model(task)
  qpos, looks = _inputs(rm, frames)
  looks = rmod.prepare(rm, looks)
  fr = rmod.FrameRenderer(rm, size, size)
  fr.render(looks, qpos[0])
  t0 = time.perf_counter()
  for i in range(frames):
    fr.render(looks, qpos[i], index=i)
  dt = time.perf_counter() - t0
  fr.close()
  return frames / dt


def bench_pool(task: str, batch: int, workers: int, quality: str, size: int,
               repeats: int) -> dict:
  """One row of the pool benchmark: `RenderPool`'s start time and frames/s rendering
  `batch` frames of `task` per call at `quality` (`repeats` timed calls after a warm-up),
  with up to 16 of the exact preset's frames checked against the reference renderer."""
  from dmcr_jax.visuals import render_model as rmod
  from dmcr_jax.visuals.render_pool import RenderPool
  t0 = time.perf_counter()
  with RenderPool(task, max_batch=batch, height=size, width=size, workers=workers,
                  quality=quality) as pool:
    start_s = time.perf_counter() - t0
    qpos, looks = _inputs(pool.rm, batch)
    looks = rmod.prepare(pool.rm, looks)
    pixels = pool.render(qpos, looks)  # warm-up, and the frames checked below
    times = R.time_calls(lambda: pool.render(qpos, looks, copy_out=False), repeats=repeats,
                         warmup=0)
    gl = pool.gl
    checked = None
    if quality == "exact":  # the reference renderer draws dm_control's settings
      idx = np.unique(np.linspace(0, batch - 1, min(batch, 16)).astype(int))
      with rmod.FrameRenderer(pool.rm, size, size) as ref:
        checked = int(sum(np.array_equal(pixels[i], ref.render(looks, qpos[i], index=i))
                          for i in idx))
      checked = f"{checked}/{len(idx)}"
  run_s = statistics.median(times)
  return dict(batch=batch, workers=workers, quality=quality, gl=gl, start_s=start_s,
              run_s=run_s, frames_per_s=batch / run_s, reference_equal=checked)


def markdown(rows: list[dict]) -> str:
  """The pool rows as one Markdown table."""
  return R.table(rows, [
      ("device", "device"), ("gl", "gl"), ("quality", "quality"),
      ("batch", lambda r: f"{r['batch']:,}"), ("workers", "workers"),
      ("frames/s", lambda r: f"{r['frames_per_s']:,.0f}"),
      ("× naive", lambda r: f"{r['speedup']:.1f}"),
      ("= reference", lambda r: r.get("reference_equal") or "–"),
      ("start s", lambda r: f"{r['start_s']:.2f}")])


def main(argv=None) -> None:
  argv = sys.argv[1:] if argv is None else argv
  p = argparse.ArgumentParser(description="RenderPool frames/s against a naive loop.")
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--size", type=int, default=84)
  p.add_argument("--batches", default="64,256,1024")
  p.add_argument("--workers", default="1,2")
  p.add_argument("--qualities", default="exact")
  p.add_argument("--repeats", type=int, default=3)
  p.add_argument("--baseline-frames", type=int, default=300)
  p.add_argument("--out", default=None)
  args = p.parse_args(argv)
  base_fps = baseline(args.task, args.baseline_frames, args.size)
  common = dict(bench="render", device=R.gpu_name() or "cpu", cpus=os.cpu_count(),
                host=platform.node(), task=args.task, size=args.size,
                baseline_fps=base_fps, vary="all", time_utc=R.utc_now())
  naive = "naive mujoco.Renderer loop"
  rows = []
  for quality in args.qualities.split(","):
    for workers in [int(w) for w in args.workers.split(",")]:
      for batch in [int(b) for b in args.batches.split(",")]:
        row = dict(common, **bench_pool(args.task, batch, workers, quality, args.size,
                                        args.repeats))
        row["speedup"] = row["frames_per_s"] / base_fps
        row = R.row(row, f"{quality}, {workers} workers", n=batch,
                    throughput=row["frames_per_s"], unit="frames/s",
                    compile_s=row["start_s"], run_s=row["run_s"], baseline=naive,
                    baseline_throughput=base_fps)
        rows.append(row)
        R.emit(row, args.out)
  table = markdown(rows)
  print(f"naive mujoco.Renderer loop: {base_fps:,.0f} frames/s\n{table}")
  if args.out:
    R.write_markdown(args.out, f"`python -m dmcr_jax.benchmarks.render {' '.join(argv)}`\n\n"
                     f"Naive loop (one mujoco.Renderer, one process): {base_fps:,.0f} "
                     f"frames/s\n\n{table}")


if __name__ == "__main__":
  main()
