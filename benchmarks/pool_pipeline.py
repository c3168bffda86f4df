"""The pool protocol's step by part: where a pipelined pool block's time goes.

For each number of groups G (`--groups 1,2,4`), a pool block of `--envs` envs of
held-out looks steps as G pool envs sharing one `RenderPool`, round robin as the
protocol does (`protocol_pool.run_pipelined`; G = 1 is the plain loop), with the
protocol's jitted policy call (`protocol_pool._pool_act`) on a random-init SAC agent
of the paper's sizes, the physics on the host CPU and the protocol's render and
physics workers (`protocol_pool.pass_workers`; `--workers`, `--physics-workers` set
them). Each host call is timed, so a row splits the wall time of one agent step of
the whole block (ms) into:

- wait frames: `step_wait`, waiting for a group's frames and stacking them;
- submit: `step_submit`, waiting for the group's physics, fetching what the frames
  read and handing them to the workers;
- policy: the policy call, its actions back on the host (it synchronises);
- dispatch: `step_async`, checking the actions and dispatching the physics.

Beside them: the pool's exact frames/s for the block in one render call of fixed
states (`benchmarks.render.bench_pool`) and the ratio of each row's frames/s to it.

    python -m dmcr_jax.benchmarks.pool_pipeline --task walker-walk --envs 240 --groups 1,2,4
    python -m dmcr_jax.benchmarks.pool_pipeline --groups 2 --workers 16 --physics-workers 0
"""

from __future__ import annotations

import argparse
import time

import dmcr_jax  # noqa: F401  (first: picks a headless MUJOCO_GL before dm_control reads it)
from dmcr_jax.benchmarks import rows as R

PARTS = ("wait_frames", "submit", "policy", "dispatch")
"""The host calls a row's ms per step are split into (module docstring)."""


STEP_CALLS = {"step_wait": "wait_frames", "step_submit": "submit",
              "step_async": "dispatch"}
"""The pool env's step calls timed here, and the part each adds its seconds to."""


class TimedEnv:
  """A pool env whose calls named in `calls` add their seconds to `parts[calls[name]]`;
  every other attribute is the env's."""

  def __init__(self, env, parts: dict, calls: dict = STEP_CALLS):
    self.env, self.parts, self.calls = env, parts, calls

  def __getattr__(self, name):
    call = getattr(self.env, name)
    if name not in self.calls:
      return call

    def timed(*args, **kwargs):
      t0 = time.perf_counter()
      out = call(*args, **kwargs)
      self.parts[self.calls[name]] += time.perf_counter() - t0
      return out
    return timed


def bench_groups(task: str, envs: int, groups: int, steps: int, image_size: int,
                 workers: int | None, physics_workers: int | None = None) -> dict:
  """One row's fields: `envs` envs as `groups` pipelined pool envs, `steps` agent
  steps (after 3 untimed ones), ms per agent step of the block by part; `workers`
  render workers shared by the groups, each pool env's physics in `physics_workers`
  CPU processes (None: the protocol's, `protocol_pool.pass_workers`)."""
  import contextlib
  import jax
  import numpy as np
  from dmcr_jax import make
  from dmcr_jax.benchmarks.evaluate import sac_agents
  from dmcr_jax.protocol_pool import _pool_act, host_workers, run_pipelined
  from dmcr_jax.train.evaluate import greedy_policy
  from dmcr_jax.visuals.levels import TEST_SEEDS
  from dmcr_jax.visuals.render_pool import RenderPool
  size = -(-envs // groups)
  workers, physics_workers = host_workers(groups, workers=workers,
                                         physics_workers=physics_workers)
  workers = min(size, workers)
  params = sac_agents(task, 1, image_size, 3)
  params = jax.tree.map(lambda x: x[0], params)
  key = jax.random.key(0)
  seeds = TEST_SEEDS.start + np.arange(size * groups)
  parts = dict.fromkeys(PARTS, 0.0)
  with contextlib.ExitStack() as stack:
    pool = stack.enter_context(RenderPool(task, max_batch=size * groups,
                                          height=image_size, width=image_size,
                                          workers=workers, frame_stack=3))
    rows = [pool.rows(h * size, (h + 1) * size) for h in range(groups)]
    group_envs = [stack.enter_context(make(
        task, renderer="pool", num_envs=size, frame_stack=3, image_size=image_size,
        copy_obs=False, visual_seeds=seeds[h * size:(h + 1) * size], render_pool=rows[h],
        physics_workers=physics_workers, physics_device="cpu")) for h in range(groups)]
    low = np.asarray(group_envs[0].single_action_space.low, np.float32)
    high = np.asarray(group_envs[0].single_action_space.high, np.float32)
    index = jax.numpy.arange(size, dtype=jax.numpy.int32)

    def act(env, obs, _, t):
      t0 = time.perf_counter()
      actions, _ = _pool_act(params, obs, index, np.int32(t), key, low, high,
                             policy=greedy_policy, agents=None)
      actions = np.asarray(actions)
      parts["policy"] += time.perf_counter() - t0
      env.step_async(actions)

    timed = [TimedEnv(e, parts) for e in group_envs]
    obs = [e.reset(seed=h)[0] for h, e in enumerate(group_envs)]
    run_pipelined(timed, obs, [None] * groups, act, 3)   # compiles; untimed
    for k in parts:
      parts[k] = 0.0
    obs = [e.reset(seed=h)[0] for h, e in enumerate(group_envs)]
    t0 = time.perf_counter()
    run_pipelined(timed, obs, [None] * groups, act, steps)
    wall = time.perf_counter() - t0
  ms = {f"{k}_ms": 1e3 * v / steps for k, v in parts.items()}
  return dict(task=task, envs=size * groups, groups=groups, group_envs=size, steps=steps,
              workers=workers, physics_workers=physics_workers, image_size=image_size,
              step_ms=1e3 * wall / steps,
              frames_per_s=size * groups * steps / wall, **ms)


def markdown(rows: list[dict]) -> str:
  """The rows as one Markdown table."""
  def part(k):
    return lambda r: "–" if r.get(f"{k}_ms") is None else f"{r[f'{k}_ms']:.1f}"
  return R.table(rows, [
      ("device", "device"), ("task", "task"), ("variant", "variant"),
      ("envs", lambda r: f"{r['n']:,}"),
      ("ms per step", lambda r: f"{r['step_ms']:.1f}"),
      *[(f"{k.replace('_', ' ')} ms", part(k)) for k in PARTS],
      ("frames/s", lambda r: f"{r['throughput']:,.0f}"),
      ("ratio", lambda r: "–" if r.get("ratio") is None else f"{r['ratio']:.2f}")])


def main(argv=None) -> None:
  """`python -m dmcr_jax.benchmarks.pool_pipeline [options]`."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.benchmarks.pool_pipeline",
                              description=__doc__.splitlines()[0])
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--envs", type=int, default=240, help="envs of the block")
  p.add_argument("--groups", default="1,2,4", help="comma-separated numbers of groups")
  p.add_argument("--steps", type=int, default=30, help="timed agent steps")
  p.add_argument("--image-size", type=int, default=84)
  p.add_argument("--workers", type=int, default=None,
                 help="render workers (default: the protocol's)")
  p.add_argument("--physics-workers", type=int, default=None,
                 help="CPU physics processes per pool env, 0: this process "
                      "(default: the protocol's)")
  p.add_argument("--out", default=None, help="JSONL file the rows are appended to")
  a = p.parse_args(argv)
  from dmcr_jax.checks import positive_int
  groups = [positive_int("--groups", int(g)) for g in a.groups.split(",")]
  if a.workers is not None:
    positive_int("--workers", a.workers)
  if a.physics_workers is not None and a.physics_workers < 0:
    p.error(f"--physics-workers must be 0 or more, got {a.physics_workers}")
  for name in ("envs", "steps", "image_size"):
    positive_int(f"--{name.replace('_', '-')}", getattr(a, name))
  import jax
  from dmcr_jax.benchmarks.render import bench_pool
  from dmcr_jax.protocol_pool import host_workers
  device = jax.devices()[0]
  machine = dict(device=device.device_kind, platform=device.platform)
  workers = min(a.envs, host_workers(1, workers=a.workers)[0])
  frames = bench_pool(a.task, a.envs, workers, "exact", a.image_size, repeats=3)
  base = R.row(dict(machine, task=a.task, step_ms=1e3 * frames["run_s"], workers=workers),
               "the pool's exact frames, one call", n=a.envs,
               throughput=frames["frames_per_s"], unit="frames/s", run_s=frames["run_s"],
               is_baseline=True)
  R.emit(base, a.out)
  rows = [base]
  for g in groups:
    fields = bench_groups(a.task, a.envs, g, a.steps, a.image_size, a.workers,
                          a.physics_workers)
    w = fields["physics_workers"]
    where = (f", {fields['workers']} render workers, physics "
             f"{f'in {w} workers' if w else 'in this process'}")
    r = R.row(dict(machine, **fields), f"pipelined, {g} group{'s' * (g > 1)}{where}",
              n=fields["envs"], throughput=fields["frames_per_s"], unit="frames/s",
              baseline=base["variant"], baseline_throughput=base["throughput"])
    r["ratio"] = r["throughput"] / base["throughput"]
    R.emit(r, a.out)
    rows.append(r)
  R.print_and_write(rows, a.out, markdown)


if __name__ == "__main__":
  main()
