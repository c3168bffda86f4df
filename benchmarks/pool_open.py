"""The pool protocol's start: seconds from opening its envs to the first block reset.

`protocol_pool.pool_envs` opens a pass's render pool and its pool envs (each with its
physics workers, which compile their physics as they start); the first block then
sets its looks and resets (the first frames, the physics workers' first call). This
benchmark times both, for the protocol as it is (each `WorkerPool` returns once its
workers are launched, `wait_start=False`: the render and physics workers start
together and the first calls wait for them) and, in the same run, with every pool's
constructor waiting for its workers in turn (`wait_start=True`, `WorkerPool`'s default).
Each variant opens fresh workers; the physics workers compile into a cache of their
own pool (set no `JAX_COMPILATION_CACHE_DIR`), so every opening compiles.

    python -m dmcr_jax.benchmarks.pool_open --task walker-walk --visual-seeds 10 --train-episodes 30
"""

from __future__ import annotations

import argparse
import time

import dmcr_jax  # noqa: F401  (first: picks a headless MUJOCO_GL before dm_control reads it)
from dmcr_jax.benchmarks import rows as R

VARIANTS = {"together": "workers start together (first call waits)",
            "in turn": "each constructor waits for its workers"}
"""`--order` names and their rows' variants."""


def time_open(task: str, visual_seeds: int, train_episodes: int, image_size: int,
              wait_in_constructor: bool) -> dict:
  """Opens a pool pass's envs and resets its first block: (open_s, first_reset_s,
  block_envs, workers, physics_workers), seconds from the opening."""
  from dmcr_jax import protocol, protocol_pool
  from dmcr_jax.train.evaluate import greedy_policy
  from dmcr_jax.visuals import pool as worker_pool
  proto = protocol.prepare(task, greedy_policy, renderer="pool", quality="exact",
                           visual_seeds=visual_seeds, train_episodes=train_episodes,
                           image_size=image_size)
  init = worker_pool.WorkerPool.__init__

  def waiting(self, *args, **kwargs):
    init(self, *args, **dict(kwargs, wait_start=True))

  if wait_in_constructor:
    worker_pool.WorkerPool.__init__ = waiting
  try:
    t0 = time.perf_counter()
    with protocol_pool.pool_envs(proto) as penvs:
      open_s = time.perf_counter() - t0
      inputs = proto._block_inputs(next(iter(proto.block_slices())))
      _, groups, _, _ = protocol_pool.reset_block(proto, penvs, inputs)
      first_reset_s = time.perf_counter() - t0
  finally:
    worker_pool.WorkerPool.__init__ = init
  workers, physics_workers = protocol_pool.workers_for(proto)
  return dict(open_s=open_s, first_reset_s=first_reset_s, block_envs=proto.block_envs,
              groups=len(groups), workers=workers, physics_workers=physics_workers)


def markdown(rows: list[dict]) -> str:
  """The rows as one table (seconds from the opening)."""
  return R.table(rows, [
      ("device", "device"), ("task", "task"), ("variant", "variant"),
      ("envs", lambda r: f"{r['block_envs']:,}"), ("groups", "groups"),
      ("render workers", "workers"), ("physics workers per group", "physics_workers"),
      ("open s", lambda r: f"{r['open_s']:.1f}"),
      ("open to first reset s", lambda r: f"{r['first_reset_s']:.1f}")])


def main(argv=None) -> None:
  """`python -m dmcr_jax.benchmarks.pool_open [options]`."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.benchmarks.pool_open",
                              description=__doc__.splitlines()[0])
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--visual-seeds", type=int, default=10)
  p.add_argument("--train-episodes", type=int, default=30)
  p.add_argument("--image-size", type=int, default=84)
  p.add_argument("--order", default="together,in turn,together",
                 help=f"the variants in the order they run, comma-separated: {', '.join(VARIANTS)}")
  p.add_argument("--out", default=None, help="JSONL file the rows are appended to")
  a = p.parse_args(argv)
  from dmcr_jax.checks import positive_int
  for name in ("visual_seeds", "train_episodes", "image_size"):
    positive_int(f"--{name.replace('_', '-')}", getattr(a, name))
  order = [v.strip() for v in a.order.split(",")]
  if bad := [v for v in order if v not in VARIANTS]:
    p.error(f"--order: unknown {bad}; choose from {', '.join(VARIANTS)}")
  import jax
  device = jax.devices()[0]
  own = dict(device=device.device_kind, platform=device.platform, task=a.task)
  rows = []
  for v in order:
    fields = time_open(a.task, a.visual_seeds, a.train_episodes, a.image_size,
                       wait_in_constructor=v == "in turn")
    r = R.row(dict(own, **fields), VARIANTS[v], n=fields["block_envs"], throughput=None,
              unit="s", run_s=fields["first_reset_s"])
    R.emit(r, a.out)
    rows.append(r)
  R.print_and_write(rows, a.out, markdown)


if __name__ == "__main__":
  main()
