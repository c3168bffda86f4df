"""Benchmark of `dmcr_jax.augment`: time per batch of 84×84×9 uint8 observations.

For every name in `dmcr_jax.augment.NAMES` it compiles ``jax.jit(aug)`` for a
batch of observations (and for an (obs, next_obs) pair), reports the compile
time apart, then times calls with fresh keys, each ended by
``block_until_ready``, and keeps the median (and the 10th/90th percentiles).
One JSON line per augmentation goes to ``--out`` (default
``benchmarks/results/augment_<device>.jsonl``, e.g. ``augment_cpu.jsonl``,
``augment_h100.jsonl``) and a Markdown table next to it (same name, ``.md``).

``--aug`` adds your own augmentations beside them: registered names or
``package.module:function`` import paths (`dmcr_jax.augment.load`), e.g.
``--aug examples.augmentations:hue_rotation,examples.augmentations:hue_rotation+drq``.

Usage::

    python -m dmcr_jax.benchmarks.augment [--batch 256] [--out PATH] [--names drq,cj+drq]
                                 [--aug package.module:function]
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import numpy as np

from dmcr_jax.benchmarks import rows as R
from dmcr_jax import augment


def bench_one(name: str, batch: int, size: int, stack: int, min_time: float,
              min_reps: int, max_reps: int, seed: int = 0) -> dict:
  """Compiles and times augmentation `name`; returns one result row.

  Args:
    name: an augmentation name (see `dmcr_jax.augment.NAMES`).
    batch: batch size B.
    size: image side (H = W).
    stack: frames per observation (channels = 3·stack).
    min_time: keep timing until this many seconds have passed …
    min_reps: … and at least this many calls were timed,
    max_reps: but never more than this many.
    seed: seed of the random images and keys.

  Returns:
    A JSON-serialisable dict.
  """
  device = jax.devices()[0]
  rng = np.random.default_rng(seed)
  shape = (batch, size, size, 3 * stack)
  obs = jax.device_put(rng.integers(0, 256, shape, dtype=np.uint8), device)
  next_obs = jax.device_put(rng.integers(0, 256, shape, dtype=np.uint8), device)
  keys = list(jax.random.split(jax.random.key(seed), max_reps + 2))
  aug = augment.get(name)
  row = {"name": name, "device_kind": device.device_kind, "device": device.device_kind,
         "platform": device.platform,
         "jax": jax.__version__, "batch": batch, "shape": list(shape), "dtype": "uint8"}
  for tag, images in (("", obs), ("pair_", (obs, next_obs))):
    fn = jax.jit(aug)
    t0 = time.perf_counter()
    compiled = fn.lower(keys[0], images).compile()
    row[f"{tag}compile_s"] = round(time.perf_counter() - t0, 3)
    fresh = iter(keys)  # a new key per call: two warm-up calls, then the timed ones
    times = np.asarray(R.time_calls(lambda: compiled(next(fresh), images), repeats=min_reps,
                                    seconds=min_time, max_calls=max_reps, warmup=2))
    row[f"{tag}reps"] = int(times.size)
    row[f"{tag}median_ms"] = round(float(np.median(times)) * 1e3, 4)
    row[f"{tag}p10_ms"] = round(float(np.percentile(times, 10)) * 1e3, 4)
    row[f"{tag}p90_ms"] = round(float(np.percentile(times, 90)) * 1e3, 4)
  row["us_per_image"] = round(row["median_ms"] * 1e3 / batch, 3)
  return row


def markdown_table(rows: list[dict]) -> str:
  """The rows as a Markdown table (one line per augmentation)."""
  first = rows[0]
  return (f"Augmentation time per batch of {first['batch']} × "
          f"{'×'.join(map(str, first['shape'][1:]))} uint8 on {first['device_kind']} "
          f"({first['platform']}, jax {first['jax']}); median of timed calls, "
          "block_until_ready; compile time apart.\n\n" + R.table(rows, [
              ("augmentation", lambda r: f"`{r['name']}`"),
              ("median ms (obs)", lambda r: f"{r['median_ms']:.3f}"),
              ("p10–p90 ms", lambda r: f"{r['p10_ms']:.3f}–{r['p90_ms']:.3f}"),
              ("µs / image", lambda r: f"{r['us_per_image']:.2f}"),
              ("median ms (obs, next_obs)", lambda r: f"{r['pair_median_ms']:.3f}"),
              ("compile s", lambda r: f"{r['compile_s']:.2f}")]))


def main(argv=None):
  """Command-line entry: benchmark every augmentation, write .jsonl and .md."""
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--batch", type=int, default=256)
  parser.add_argument("--size", type=int, default=84)
  parser.add_argument("--stack", type=int, default=3)
  parser.add_argument("--names", default=",".join(augment.NAMES),
                      help="comma-separated names (default: all of augment.NAMES)")
  parser.add_argument("--aug", default="",
                      help="comma-separated augmentations of your own to time after "
                           "--names: package.module:function import paths (or "
                           "'+'-compositions with built-ins)")
  parser.add_argument("--min-time", type=float, default=1.0,
                      help="seconds of timed calls per measurement (at least)")
  parser.add_argument("--min-reps", type=int, default=5)
  parser.add_argument("--max-reps", type=int, default=200)
  parser.add_argument("--out", default=None,
                      help="JSONL path (default: "
                           "benchmarks/results/augment_<device>.jsonl)")
  args = parser.parse_args(argv)
  names = [n for n in args.names.split(",") + args.aug.split(",") if n]
  for name in names:  # import and validate every name before timing anything
    try:
      augment.get(name)
    except ValueError as e:
      parser.error(str(e))

  out = args.out or os.path.join("benchmarks", "results",
                                 f"augment_{R.device_slug(jax.devices()[0].device_kind)}.jsonl")
  os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
  open(out, "w").close()  # each run writes its own rows
  rows = []
  stamp = R.utc_now()
  for name in names:
    row = bench_one(name, args.batch, args.size, args.stack, args.min_time,
                    args.min_reps, args.max_reps)
    run_s = row["median_ms"] / 1e3
    row = R.row(dict(row, cpu_count=os.cpu_count(), time_utc=stamp), name, n=args.batch,
                throughput=args.batch / run_s, unit="images/s", compile_s=row["compile_s"],
                run_s=run_s)
    rows.append(row)
    R.emit(row, out)
    print(f"{name:>20s}  {row['median_ms']:9.3f} ms  "
          f"(pair {row['pair_median_ms']:9.3f} ms)  "
          f"compile {row['compile_s']:.2f} s", flush=True)
  md = R.write_markdown(out, markdown_table(rows))
  print(f"wrote {out} and {md}")


if __name__ == "__main__":
  main()
