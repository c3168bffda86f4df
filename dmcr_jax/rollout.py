"""`dmcr-rollout`: roll out DMCR tasks with a random policy, batched on one device.

The smallest end-to-end job: for each task, `num_envs` envs are reset with
different dynamics keys and stepped for `steps` control steps with uniform
random actions, all inside one jitted `lax.scan` over a vmapped `Task.step`.
It prints each task's mean return, compile time and physics steps per second.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax import models
from dmcr_jax.models.base import physics_jit

DEFAULT_TASKS = ("cartpole-balance", "pendulum-swingup", "reacher-easy")


def make_rollout(task: models.Task, num_envs: int, steps: int):
  """Returns a jitted `key -> (returns (N,), final obs (N, O))` random-policy rollout."""

  def rollout(key):
    k_reset, k_act = jax.random.split(key)
    state = jax.vmap(task.reset)(jax.random.split(k_reset, num_envs))

    def body(carry, k):
      s, ret = carry
      a = jax.random.uniform(k, (num_envs, task.action_size), minval=task.action_low,
                             maxval=task.action_high)
      s = jax.vmap(task.step)(s, a)
      return (s, ret + s.reward), None

    (state, returns), _ = jax.lax.scan(
        body, (state, jnp.zeros(num_envs)), jax.random.split(k_act, steps))
    return returns, state.obs

  return physics_jit(rollout)


def run(names, num_envs: int, steps: int, seed: int = 0) -> list[dict]:
  """Rolls out each task; returns one result row per task."""
  rows = []
  for name in names:
    task = models.load(name)
    fn = make_rollout(task, num_envs, steps)
    key = jax.random.key(seed)
    t0 = time.perf_counter()
    compiled = fn.lower(key).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    returns, obs = jax.block_until_ready(compiled(key))
    t_run = time.perf_counter() - t0
    if not np.all(np.isfinite(np.asarray(obs))):
      raise FloatingPointError(f"{name}: non-finite observation")
    rows.append(dict(task=name, num_envs=num_envs, steps=steps,
                     mean_return=float(np.mean(returns)),
                     std_return=float(np.std(returns)),
                     compile_s=t_compile, run_s=t_run,
                     agent_steps_per_s=num_envs * steps / t_run,
                     physics_steps_per_s=num_envs * steps * task.n_sub_steps / t_run))
  return rows


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--tasks", default=",".join(DEFAULT_TASKS),
                 help="comma-separated task names, or 'all' (default: %(default)s)")
  p.add_argument("--num-envs", type=int, default=64)
  p.add_argument("--steps", type=int, default=200, help="control steps per env")
  p.add_argument("--seed", type=int, default=0)
  args = p.parse_args(argv)
  names = models.ALL_TASKS if args.tasks == "all" else tuple(
      t.strip() for t in args.tasks.split(",") if t.strip())
  for n in names:
    models.split_name(n)  # fail fast, listing the valid names
  if args.num_envs < 1 or args.steps < 1:
    p.error("--num-envs and --steps must be positive")
  print(f"device: {jax.devices()[0].device_kind}; {args.num_envs} envs x "
        f"{args.steps} steps, random policy")
  print(f"{'task':<22}{'return':>16}{'compile s':>11}{'agent-steps/s':>15}"
        f"{'physics-steps/s':>17}")
  for r in run(names, args.num_envs, args.steps, args.seed):
    print(f"{r['task']:<22}{r['mean_return']:>9.1f} ± {r['std_return']:<5.1f}"
          f"{r['compile_s']:>11.1f}{r['agent_steps_per_s']:>15,.0f}"
          f"{r['physics_steps_per_s']:>17,.0f}", flush=True)


if __name__ == "__main__":
  main()
