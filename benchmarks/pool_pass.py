"""The pool protocol's pass by part: where a whole pass's time goes, beside its frames.

A `dmcr_jax.protocol` pool pass (walker-walk by default, a random-init SAC agent of
the paper's sizes with `dmcr-evaluate`'s greedy policy, the protocol's own render
and physics workers) runs twice on one opening of its envs and workers, as inside
``with proto:``; its wall time is split into (seconds):

- open: `protocol_pool.pool_envs`, starting the render workers, the pool envs and
  their physics workers (once);
- looks: setting every env's look (`set_looks`, `set_visuals`);
- reset: the resets (on the first pass also the physics workers' compilation);
- loop: `protocol_pool.run_pipelined`, itself split into waiting for frames,
  submitting (waiting for the physics, handing the frames to the workers),
  dispatching the physics, and the rest (the policy calls, the host's own work).

Each pass's frames/s (one frame per agent step: the loop's, and the pass's with
its looks and resets) is set beside the pool's exact frames/s of the block in one
render call of fixed states (`benchmarks.render.bench_pool`) in the same run.

    python -m dmcr_jax.benchmarks.pool_pass --task walker-walk --visual-seeds 10 --train-episodes 30
"""

from __future__ import annotations

import argparse
import collections
import time

import dmcr_jax  # noqa: F401  (first: picks a headless MUJOCO_GL before dm_control reads it)
from dmcr_jax.benchmarks import rows as R

TIMED = {"set_looks": "looks", "set_visuals": "looks", "reset": "reset"}
"""The pool env calls timed beside `pool_pipeline.STEP_CALLS`, and their parts."""
PARTS = ("looks", "reset", "loop", "wait_frames", "submit", "dispatch")
"""A pass's parts (module docstring), in seconds."""


def bench_pass(task: str, visual_seeds: int, train_episodes: int, image_size: int) -> dict:
  """Two pool passes on one opening: the open seconds and each pass's parts."""
  import jax
  from dmcr_jax import protocol, protocol_pool
  from dmcr_jax.benchmarks.evaluate import sac_agents
  from dmcr_jax.benchmarks.pool_pipeline import STEP_CALLS, TimedEnv
  from dmcr_jax.train.evaluate import greedy_policy
  proto = protocol.prepare(task, greedy_policy, renderer="pool", quality="exact",
                           visual_seeds=visual_seeds, train_episodes=train_episodes,
                           image_size=image_size)
  key = jax.random.key(0)
  parts = collections.defaultdict(float)
  loop = protocol_pool.run_pipelined

  def timed_loop(*args):
    t0 = time.perf_counter()
    out = loop(*args)
    parts["loop"] += time.perf_counter() - t0
    return out

  passes = []
  t0 = time.perf_counter()
  with protocol_pool.pool_envs(proto) as penvs:
    open_s = time.perf_counter() - t0
    calls = {**STEP_CALLS, **TIMED}
    timed = protocol_pool.PoolEnvs(
        {k: TimedEnv(e, parts, calls) for k, e in penvs.envs.items()}, penvs.low, penvs.high)
    protocol_pool.run_pipelined = timed_loop
    try:
      for seed in (0, 1):
        parts.clear()
        params = jax.tree.map(lambda x: x[0], sac_agents(task, 1, image_size, 3, seed=seed))
        run_block = protocol_pool.block_runner(proto, timed, params, key)
        t0 = time.perf_counter()
        for idx in proto.block_slices():
          run_block(proto._block_inputs(idx))
        passes.append(dict(wall_s=time.perf_counter() - t0,
                           **{f"{k}_s": parts[k] for k in PARTS}))
    finally:
      protocol_pool.run_pipelined = loop
  workers, physics_workers = protocol_pool.workers_for(proto)
  return dict(task=task, visual_seeds=visual_seeds, train_episodes=train_episodes,
              image_size=image_size, block_envs=proto.block_envs, blocks=proto.num_blocks,
              groups=len(protocol_pool.pool_groups(1, proto.block)), workers=workers,
              physics_workers=physics_workers, episode_length=proto.episode_length,
              frames=proto.num_blocks * proto.block_envs * proto.episode_length,
              open_s=open_s, passes=passes)


def markdown(rows: list[dict]) -> str:
  """The pass rows as one table (seconds per part, frames/s, ratios)."""
  out = [r for r in rows if not r.get("is_baseline")]
  return R.table(out, [
      ("device", "device"), ("task", "task"), ("variant", "variant"),
      ("envs × blocks", lambda r: f"{r['block_envs']:,} × {r['blocks']}"),
      ("open s", lambda r: f"{r['open_s']:.1f}" if r["pass"] == 1 else "–"),
      *[(f"{k.replace('_', ' ')} s", (lambda k: lambda r: f"{r[f'{k}_s']:.1f}")(k))
        for k in ("wall",) + PARTS],
      ("loop frames/s", lambda r: f"{r['loop_frames_per_s']:,.0f}"),
      ("pass frames/s", lambda r: f"{r['throughput']:,.0f}"),
      ("exact frames/s", lambda r: f"{r['baseline_throughput']:,.0f}"),
      ("loop ratio", lambda r: f"{r['loop_ratio']:.2f}"),
      ("pass ratio", lambda r: f"{r['ratio']:.2f}")])


def main(argv=None) -> None:
  """`python -m dmcr_jax.benchmarks.pool_pass [options]`."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.benchmarks.pool_pass",
                              description=__doc__.splitlines()[0])
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--visual-seeds", type=int, default=10)
  p.add_argument("--train-episodes", type=int, default=30)
  p.add_argument("--image-size", type=int, default=84)
  p.add_argument("--out", default=None, help="JSONL file the rows are appended to")
  a = p.parse_args(argv)
  from dmcr_jax.checks import positive_int
  for name in ("visual_seeds", "train_episodes", "image_size"):
    positive_int(f"--{name.replace('_', '-')}", getattr(a, name))
  import jax
  from dmcr_jax.benchmarks.render import bench_pool
  device = jax.devices()[0]
  own = dict(device=device.device_kind, platform=device.platform)
  fields = bench_pass(a.task, a.visual_seeds, a.train_episodes, a.image_size)
  frames = bench_pool(a.task, fields["block_envs"], fields["workers"], "exact",
                      a.image_size, repeats=3)
  base = R.row(dict(own, task=a.task, workers=fields["workers"]),
               "the pool's exact frames, one call", n=fields["block_envs"],
               throughput=frames["frames_per_s"], unit="frames/s", run_s=frames["run_s"],
               is_baseline=True)
  R.emit(base, a.out)
  rows = [base]
  passes = fields.pop("passes")
  for i, parts in enumerate(passes, 1):
    r = R.row(dict(own, **fields, **parts, **{"pass": i}),
              f"pass {i}{' (compiles)' if i == 1 else ''}", n=fields["block_envs"],
              throughput=fields["frames"] / parts["wall_s"], unit="frames/s",
              run_s=parts["wall_s"], baseline=base["variant"],
              baseline_throughput=base["throughput"])
    r["loop_frames_per_s"] = fields["frames"] / parts["loop_s"]
    r["loop_ratio"] = r["loop_frames_per_s"] / base["throughput"]
    r["ratio"] = r["throughput"] / base["throughput"]
    R.emit(r, a.out)
    rows.append(r)
  R.print_and_write(rows, a.out, markdown)


if __name__ == "__main__":
  main()
