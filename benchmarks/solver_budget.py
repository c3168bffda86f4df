"""How far smaller constraint-solver budgets drift from dm_control.

MJX's speed on a batch is set by the solver budget (`Task.solver_iterations`,
`Task.ls_iterations`): under `vmap` the line search is a fixed-length scan, so
every solver iteration pays for all `ls_iterations` steps, and the solver loop
runs until the slowest env stops. This tool measures what a smaller budget costs
in fidelity: from `--states` mid-episode states of dm_control random rollouts, it
steps dm_control (float64, its own budget) and MJX under each budget with the
same random actions for `--steps` control steps, and reports the largest
|MJX − dm_control| over qpos, qvel, observation and reward (the measure of the
trajectory-parity test), and its median over the start states (less swayed by
one chaotic contact). Pair it with `dmcr_jax.benchmarks.physics --solver-iterations …
--ls-iterations …` for the speed side.

`--precisions` repeats every budget with the physics' matrix products at other
precisions (`base.physics_matmul_precision`; the physics uses "highest", float32;
on an H100, JAX's "default" lets XLA use TensorFloat-32, a 10-bit mantissa).

    python -m dmcr_jax.benchmarks.solver_budget --tasks walker-walk --budgets -/50,default,-/8,4/8,1/4
    python -m dmcr_jax.benchmarks.solver_budget --tasks walker-walk --budgets default \
        --precisions highest,default
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from dmcr_jax._mjx import mjx  # mujoco.mjx, quietly

from dmcr_jax.benchmarks import rows as R
from dmcr_jax import models
from dmcr_jax.models import base
from tests import dmc_reference


def parse_budget(text: str) -> tuple[int | None, int | None]:
  """"default" -> (None, None); "100/8" -> (100, 8); "-/50" -> (None, 50) ("-" keeps the default)."""
  if text == "default":
    return (None, None)
  try:
    it, ls = text.split("/")
    return tuple(None if v == "-" else int(v) for v in (it, ls))
  except ValueError:
    raise ValueError(f"Budget {text!r}: use 'default' or 'ITERATIONS/LS_ITERATIONS' "
                     "('-' keeps a default).") from None


def reference(name: str, states: dmc_reference.Records, actions: np.ndarray) -> list:
  """dm_control's records after each of `actions` (T, N, A), from `states`."""
  task = models.load(name)
  env = dmc_reference.load_env(name, 0)
  per_env = []
  for i in range(len(states.reward)):
    env.reset()
    p = env.physics
    task.apply_model_variables(p.model.ptr, {k: v[i] for k, v in states.info.items()})
    with p.reset_context():
      for field in ("qpos", "qvel", "act", "qacc_warmstart"):
        getattr(p.data, field)[:] = getattr(states, field)[i]
    recs = []
    for a in actions[:, i]:
      ts = env.step(a)
      recs.append((dmc_reference.snapshot(p, task), dmc_reference.flat_obs(ts.observation),
                   ts.reward))
    per_env.append(recs)
  return [dmc_reference.stack([e[t][0] for e in per_env], [e[t][1] for e in per_env],
                              [e[t][2] for e in per_env]) for t in range(len(actions))]


def mjx_rollout(name: str, budget, states: dmc_reference.Records,
                actions: np.ndarray, precision: str = base.PHYSICS_MATMUL_PRECISION
                ) -> list[np.ndarray]:
  """MJX's (qpos, qvel, obs, reward) after each step under one solver budget,
  its products at `precision` (`base.physics_matmul_precision`)."""
  with base.physics_matmul_precision(precision):
    return _mjx_rollout(name, budget, states, actions)


def _mjx_rollout(name: str, budget, states: dmc_reference.Records,
                 actions: np.ndarray) -> list[np.ndarray]:
  task = models.load(name, *budget)
  n = len(states.reward)
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  m = task.mjx_model
  blank = jax.vmap(lambda _: mjx.make_data(m))(jnp.zeros(n))
  data = blank.replace(qpos=f32(states.qpos), qvel=f32(states.qvel), act=f32(states.act),
                       ctrl=f32(states.ctrl), qacc_warmstart=f32(states.qacc_warmstart))
  data = jax.jit(jax.vmap(lambda d: base.sync(m, d)))(data)
  info = {k: f32(v) for k, v in states.info.items()}
  obs, reward = jax.vmap(task.observe)(data, info)
  state = base.State(data=data, obs=obs, reward=reward, done=jnp.zeros((n,), bool),
                     step_count=jnp.zeros((n,), jnp.int32), info=info)
  step = jax.jit(jax.vmap(task.step))
  out = []
  for a in actions:
    state = step(state, f32(a))
    out.append([np.asarray(x, np.float64) for x in (state.data.qpos, state.data.qvel,
                                                    state.obs, state.reward)])
  return out


def max_diff(a: list, b: list) -> float:
  """Largest |a − b| over steps and quantities of two rollouts."""
  return max(float(np.abs(x - y).max()) for sa, sb in zip(a, b) for x, y in zip(sa, sb))


def median_diff(a: list, b: list) -> float:
  """Median over start states of each state's largest |a − b| (steps, quantities)."""
  per_state = np.zeros(len(a[0][0]))
  for sa, sb in zip(a, b):
    for x, y in zip(sa, sb):
      d = np.abs(x - y)
      per_state = np.maximum(per_state, d.reshape(len(per_state), -1).max(axis=1))
  return float(np.median(per_state))


def main(argv=None) -> None:
  argv = sys.argv[1:] if argv is None else argv
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--tasks", default="walker-walk", help="comma-separated task names")
  p.add_argument("--budgets", default="-/50,default,-/8,4/8,1/4",
                 help="'default' or ITERATIONS/LS_ITERATIONS ('-' keeps a default), "
                      "comma-separated; the first is the reference of the last column")
  p.add_argument("--precisions", default=base.PHYSICS_MATMUL_PRECISION,
                 help="precisions of the physics' matrix products, comma-separated, from "
                      f"{', '.join(base.MATMUL_PRECISIONS)} (default: %(default)s, the "
                      "physics' own); each budget runs under each")
  p.add_argument("--states", type=int, default=32, help="start states (mid-episode)")
  p.add_argument("--steps", type=int, default=20, help="control steps from each state")
  p.add_argument("--out", default=None, help="JSONL path to append to (a .md beside)")
  args = p.parse_args(argv)
  budgets = [parse_budget(b) for b in args.budgets.split(",")]
  precisions = args.precisions.split(",")
  for prec in precisions:
    if prec not in base.MATMUL_PRECISIONS:
      p.error(f"--precisions: {prec!r} is not one of {', '.join(base.MATMUL_PRECISIONS)}")
  rows = []
  for name in args.tasks.split(","):
    task = models.load(name)
    states = dmc_reference.random_rollout_states(name, n_states=args.states)
    rng = np.random.RandomState(1)
    actions = rng.uniform(task.action_low, task.action_high,
                          (args.steps, args.states, task.action_size))
    ref = [[r.qpos, r.qvel, r.obs, r.reward] for r in reference(name, states, actions)]
    first = None
    for budget, prec in itertools.product(budgets, precisions):
      t = models.load(name, *budget)
      traj = mjx_rollout(name, budget, states, actions, prec)
      first = traj if first is None else first
      row = dict(bench="solver_budget", device=jax.devices()[0].device_kind,
                 host=platform.node(), task=name, states=args.states, steps=args.steps,
                 solver_iterations=t.solver_iterations, ls_iterations=t.ls_iterations,
                 default=budget == (None, None), matmul_precision=prec,
                 max_abs_drift=max_diff(traj, ref),
                 median_abs_drift=median_diff(traj, ref),
                 max_abs_diff_vs_first_budget=max_diff(traj, first),
                 time_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
      rows.append(row)
      print(json.dumps(row), flush=True)
      if args.out:
        with open(args.out, "a") as f:
          f.write(json.dumps(row) + "\n")
  if args.out:
    with open(args.out) as f:
      rows = [json.loads(line) for line in f]
  text = markdown(rows)
  print(text)
  if args.out:
    R.write_markdown(args.out, (
        f"Rows of `python -m dmcr_jax.benchmarks.solver_budget` runs appended to "
        f"`{os.path.basename(args.out)}`; the last: "
        f"`python -m dmcr_jax.benchmarks.solver_budget {' '.join(argv)}`.\n\n"
        "Mid-episode states × control steps (in each row), float32 MJX against "
        "float64 dm_control (largest, and the median over start states of each state's "
        "largest), and against MJX under the first budget (and matmul precision) run "
        "for the task. "
        "From contact-rich mid-episode states the absolute drift includes chaotic "
        "divergence and sparse rewards flipping (ball_in_cup: 0 or 1); compare "
        "budgets within a task.\n\n") + text)


def markdown(rows: list[dict]) -> str:
  """The rows as one Markdown table."""
  return R.table(rows, [
      ("device", lambda r: r.get("device", "?")), ("task", "task"),
      ("solver it/ls", lambda r: f"{r['solver_iterations']}/{r['ls_iterations']}"
                                 + (" (default)" if r["default"] else "")),
      ("matmul precision", lambda r: r.get("matmul_precision", "default")),
      ("states × steps", lambda r: f"{r['states']} × {r['steps']}"),
      ("max abs drift vs dm_control", lambda r: f"{r['max_abs_drift']:.2e}"),
      ("median over states", lambda r: R.fmt(r.get("median_abs_drift"), ".2e")),
      ("max abs diff vs the task's first run",
       lambda r: f"{r['max_abs_diff_vs_first_budget']:.2e}")])


if __name__ == "__main__":
  main()
