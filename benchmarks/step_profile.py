"""Where the time of one agent step goes: env parts, acting, buffer insert, updates.

One agent step of the training loop (`dmcr_jax.train.loop`) at N envs is: the env step of
all N envs — physics (the jitted batched step, frame skip included), the
device→host transfer of what rendering needs, rendering (the render workers also
build the frame stacks), the copy of the stacked observations out of shared
memory (`env.timings`) — then the host→device put of the observations, the
policy's actions for the N observations (`sac.act`), the replay-buffer insert of
N transitions (`replay.add`, buffer donated) and the gradient updates owed: the
loop does `utd` updates per transition, so N·utd updates of one agent per agent
step. This benchmark measures each part apart, for walker-walk (default) at
frame skip 2 with every visual factor varying:

- env parts: `dmcr_jax.make` stepped `--steps` times with random actions after
  warm-up; ms per step from `env.timings`, the rest of the step as "env_other";
- stacking: the workers' stack shift (`out[..., :-3] = prev[..., 3:]` plus the new
  frame) timed once more in this process on (N, H, W, 3·stack) arrays, for
  reference only — inside the env it is part of "render", spread over the workers;
- obs_to_device, act, buffer_add: jitted as the loop runs them (one agent),
  median of `--reps` calls ended by `block_until_ready`, compile apart;
- update: `--pairs` × `sac.update_pair` in one jitted `lax.scan` (two updates
  each, two batches sampled from a full buffer of the same N and capacity:
  `dmcr_jax.train.step.update_pair`, the training step's own; unrolled on CPU);
  per-update ms = call time / (2·pairs); its share of an agent step =
  N·utd·per-update ms.

    python -m dmcr_jax.benchmarks.step_profile --sizes 1024 --out benchmarks/results/step_profile_h100.jsonl

One JSON line per N (device, settings, compile_s, parts_ms, shares, per-update
ms, agent-steps/s of the env alone, with acting and insert ("collect"), and with
the updates ("train")) appended to `--out`, and a Markdown table beside it.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import sys
import time

import numpy as np

import dmcr_jax  # first: picks a headless MUJOCO_GL before dm_control reads it
from dmcr_jax.benchmarks import rows as R

ENV_PARTS = ("physics", "transfer", "render", "copy", "env_other")
"""The env step's parts, as `env.timings` names them, plus the unaccounted rest."""

LEARNER_PARTS = ("obs_to_device", "act", "buffer_add", "update")
"""The training loop's parts of an agent step outside the env."""


def breakdown(parts_ms: dict, num_envs: int) -> dict:
  """Totals, shares and throughputs from the ms per agent step of each part.

  Args:
    parts_ms: ms per agent step of every part (`ENV_PARTS` + `LEARNER_PARTS`;
      missing parts count 0).
    num_envs: N, the transitions one agent step collects.

  Returns:
    total_ms, shares (part → fraction of the total), and agent-steps/s (one per
    env and step, like `dmcr_jax.benchmarks.env`) of the env alone, of collecting (env,
    obs_to_device, act, buffer_add) and of training (all parts).
  """
  env_ms = sum(parts_ms.get(p, 0.0) for p in ENV_PARTS)
  collect_ms = env_ms + sum(parts_ms.get(p, 0.0) for p in LEARNER_PARTS if p != "update")
  total_ms = collect_ms + parts_ms.get("update", 0.0)
  rate = lambda ms: num_envs / (ms / 1e3) if ms > 0 else None
  return dict(total_ms=total_ms,
              shares={k: (v / total_ms if total_ms > 0 else None) for k, v in parts_ms.items()},
              env_agent_steps_per_s=rate(env_ms), collect_agent_steps_per_s=rate(collect_ms),
              train_agent_steps_per_s=rate(total_ms))


def _median_time(fn, reps: int) -> float:
  """Median seconds of `reps` calls of `fn()`, its result blocked on."""
  return statistics.median(R.time_calls(fn, repeats=reps, warmup=0))


def profile_env(task: str, n: int, quality: str, workers: int | None, frame_skip: int,
                frame_stack: int, size: int, steps: int, warmup: int = 3,
                copy_obs: bool = True, physics_device: str | None = None
                ) -> tuple[dict, dict]:
  """The env's parts of an agent step, and one step's data for the learner parts.

  Returns:
    (measurements: parts_ms, step_ms, start_s, compile_s, workers;
     sample: obs, first, action, reward of the last step as NumPy arrays).
  """
  t0 = time.perf_counter()
  env = dmcr_jax.make(task, num_envs=n, visual_seeds=np.arange(1, n + 1), vary="all",
                      frame_skip=frame_skip, frame_stack=frame_stack, image_size=size,
                      quality=quality, workers=workers, copy_obs=copy_obs,
                      physics_device=physics_device)
  with env:
    start_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    low, high = env.single_action_space.low, env.single_action_space.high
    draw = lambda: rng.uniform(low, high, env.action_space.shape).astype(np.float32)
    t0 = time.perf_counter()
    obs, info = env.reset(seed=0)
    for _ in range(warmup):  # compiles the step
      obs, _, _, _, info = env.step(draw())
    compile_s = time.perf_counter() - t0
    env.reset_timings()
    t0 = time.perf_counter()
    for _ in range(steps):
      action = draw()
      first = info["episode_step"] == 0
      prev = obs
      obs, reward, _, _, info = env.step(action)
    wall_ms = (time.perf_counter() - t0) / steps * 1e3
    parts = {k: v / steps * 1e3 for k, v in env.timings.items()}
    parts["env_other"] = max(0.0, wall_ms - sum(parts.values()))
    used_workers = env._pool.num_workers
    sample = dict(obs=np.array(prev), first=np.asarray(first), action=action,
                  reward=np.asarray(reward, np.float32))
  return dict(parts_ms=parts, step_ms=wall_ms, start_s=start_s, compile_s=compile_s,
              workers=used_workers), sample


def stack_shift_ms(n: int, size: int, frame_stack: int, reps: int) -> float:
  """ms of the render workers' stack shift for N envs, done in one process."""
  prev = np.zeros((n, size, size, 3 * frame_stack), np.uint8)
  out = np.empty_like(prev)
  frames = np.ones((n, size, size, 3), np.uint8)

  def shift():
    out[..., :-3] = prev[..., 3:]
    out[..., -3:] = frames
  shift()
  return _median_time(shift, reps) * 1e3


def profile_learner(sample: dict, capacity: int, batch: int, dtype: str, pairs: int,
                    reps: int, seed: int = 0) -> dict:
  """The loop's parts outside the env for one agent, from one step's data.

  Args:
    sample: obs uint8 (N, H, W, 3k), first bool (N,), action (N, A), reward (N,).
    capacity: replay rows over all N envs (each env's ring holds capacity // N).
    batch: SAC batch size.
    dtype: the networks' compute dtype ("float32", "bfloat16").
    pairs: update pairs per timed call.
    reps: timed calls per part.
    seed: seeds the agent and the random buffer contents.

  Returns:
    ms of obs_to_device, act, buffer_add and one update; compile seconds.
  """
  import jax
  import jax.numpy as jnp
  from dmcr_jax.train import replay, sac

  obs, first, action, reward = (sample[k] for k in ("obs", "first", "action", "reward"))
  n, h, w, c = obs.shape
  stack = c // 3
  config = sac.SACConfig(batch_size=batch, compute_dtype=dtype)
  agent = sac.init_agent(jax.random.key(seed), (h, w, c), action.shape[1], config)
  compile_s = {}

  put = lambda: jax.block_until_ready(jax.device_put(obs))
  put()
  obs_dev = put()
  h2d_ms = _median_time(put, reps) * 1e3

  act = jax.jit(sac.act)
  key = jax.random.key(seed + 1)
  t0 = time.perf_counter()
  jax.block_until_ready(act(agent, obs_dev, key))
  compile_s["act"] = time.perf_counter() - t0
  act_ms = _median_time(lambda: jax.block_until_ready(act(agent, obs_dev, key)), reps) * 1e3

  buffer = filled_buffer(capacity, n, (h, w, 3), action.shape[1], stack, seed)
  add = jax.jit(replay.add, donate_argnums=0)
  args = (obs_dev[..., -3:], jnp.asarray(first), jnp.asarray(action), jnp.asarray(reward))
  t0 = time.perf_counter()
  buffer = jax.block_until_ready(add(buffer, *args))
  compile_s["buffer_add"] = time.perf_counter() - t0
  holder = [buffer]

  def one_add():
    holder[0] = jax.block_until_ready(add(holder[0], *args))
  add_ms = _median_time(one_add, reps) * 1e3
  buffer = holder[0]

  on_cpu = jax.default_backend() == "cpu"
  update = jax.jit(functools.partial(_updates, pairs=pairs, config=config, unroll=on_cpu),
                   donate_argnums=0)
  keys = jax.random.split(jax.random.key(seed + 2), reps + 1)
  t0 = time.perf_counter()
  agents = [jax.block_until_ready(update(agent, buffer, keys[0]))]
  compile_s["update"] = time.perf_counter() - t0
  calls = iter(keys[1:])

  def one_call():
    agents[0] = jax.block_until_ready(update(agents[0], buffer, next(calls)))
  per_update_ms = _median_time(one_call, reps) * 1e3 / (2 * pairs)
  return dict(obs_to_device_ms=h2d_ms, act_ms=act_ms, buffer_add_ms=add_ms,
              per_update_ms=per_update_ms, compile_s=compile_s)


def _updates(agent, buffer, key, pairs: int, config, unroll: bool):
  """`pairs` × `dmcr_jax.train.step.update_pair` (two batches sampled from `buffer`, one
  `sac.update_pair`) for one agent, scanned; returns the agent."""
  import jax
  from dmcr_jax.train import step

  def body(agent, k):
    return step.update_pair(agent, buffer, k, config)[0], None
  agent, _ = jax.lax.scan(body, agent, jax.random.split(key, pairs), unroll=unroll)
  return agent


def filled_buffer(capacity: int, n: int, frame_shape: tuple, action_size: int, stack: int,
                  seed: int = 0):
  """A full replay buffer of N envs with random frames and an episode every 125 rows."""
  import jax
  import jax.numpy as jnp
  from dmcr_jax.train import replay

  empty = replay.init(capacity, n, frame_shape, action_size, stack)
  t = empty.ring_size
  key = jax.random.key(seed)
  return empty.replace(
      frames=jax.random.bits(key, empty.frames.shape, jnp.uint8),
      action=jax.random.uniform(key, empty.action.shape, minval=-1, maxval=1),
      reward=jax.random.uniform(key, empty.reward.shape),
      first=jnp.broadcast_to(jnp.arange(t) % 125 == 0, empty.first.shape),
      pos=jnp.zeros_like(empty.pos), count=jnp.full_like(empty.count, t))


def profile(task: str, n: int, quality: str, workers: int | None, frame_skip: int,
            frame_stack: int, size: int, steps: int, batch: int, dtype: str, utd: float,
            capacity: int, pairs: int, reps: int, copy_obs: bool = True,
            physics_device: str | None = None) -> dict:
  """One result row: every part of an agent step at N envs (see the module doc)."""
  import jax
  env_part, sample = profile_env(task, n, quality, workers, frame_skip, frame_stack, size,
                                 steps, copy_obs=copy_obs, physics_device=physics_device)
  learner = profile_learner(sample, capacity, batch, dtype, pairs, reps)
  updates = n * utd
  parts = dict(env_part["parts_ms"], obs_to_device=learner["obs_to_device_ms"],
               act=learner["act_ms"], buffer_add=learner["buffer_add_ms"],
               update=learner["per_update_ms"] * updates)
  device = jax.devices()[0]
  row = dict(
      bench="step_profile", device=device.device_kind, platform=device.platform,
      jax=jax.__version__, cpus=os.cpu_count(), task=task, num_envs=n, quality=quality,
      workers=env_part["workers"], frame_skip=frame_skip, frame_stack=frame_stack,
      image_size=size, copy_obs=copy_obs, physics_device=physics_device or device.platform,
      steps=steps, batch=batch, dtype=dtype, utd=utd,
      capacity=capacity, pairs_per_call=pairs,
      compile_s=round(env_part["compile_s"] + sum(learner["compile_s"].values()), 2),
      compile_parts_s={"env": round(env_part["compile_s"], 2),
                       **{k: round(v, 2) for k, v in learner["compile_s"].items()}},
      env_start_s=round(env_part["start_s"], 2), env_step_ms=env_part["step_ms"],
      parts_ms=parts, per_update_ms=learner["per_update_ms"], updates_per_agent_step=updates,
      stack_one_process_ms=stack_shift_ms(n, size, frame_stack, reps),
      **breakdown(parts, n), time_utc=R.utc_now())
  rate = row["train_agent_steps_per_s"]
  return R.row(row, f"{task} {quality}", n=n, throughput=rate,
               unit="agent-steps/s with updates", compile_s=row["compile_s"],
               run_s=row["total_ms"] / 1e3,
               headline=f"{row['total_ms']:,.1f} ms per agent step, i.e. {R.num(rate)} "
                        "agent-steps/s with updates")


PART_NOTES = {
    "physics": "jitted batched step (frame skip, rewards, auto-reset)",
    "transfer": "device→host: qpos, task variables, rewards, flags",
    "render": "render workers: frames and frame stacks",
    "copy": "stacked observations out of shared memory",
    "env_other": "rest of env.step (action checks, info)",
    "obs_to_device": "host→device put of the stacked observations",
    "act": "policy on N observations (sac.act)",
    "buffer_add": "replay.add of N transitions (buffer donated)",
    "update": "N·utd SAC updates (sac.update_pair, sampling included)",
}


def markdown(rows: list[dict]) -> str:
  """A table per row: ms per agent step and share of each part."""
  out = []
  for r in rows:
    out += [f"**{r['task']}, N = {r['num_envs']:,}, {r['quality']} ({r['workers']} workers), "
            f"frame skip {r['frame_skip']}, physics on {r.get('physics_device') or r['platform']}, "
            f"{r['image_size']}×{r['image_size']}×"
            f"{3 * r['frame_stack']}; SAC batch {r['batch']}, {r['dtype']}, utd {r['utd']:g}; "
            f"{r['device']}, {r['time_utc']}**", "",
            R.table([dict(part=p, ms=f"{ms:,.2f}", share=R.fmt(r["shares"].get(p), ".1%"),
                          what=PART_NOTES.get(p, "")) for p, ms in r["parts_ms"].items()]
                     + [dict(part="**total**", ms=f"**{r['total_ms']:,.2f}**", share="100%",
                             what="")],
                     [("part", "part"), ("ms per agent step", "ms"), ("share", "share"),
                      ("what", "what")]).rstrip("\n"), "",
            f"One update: {r['per_update_ms']:,.2f} ms; an agent step owes N·utd = "
            f"{r['updates_per_agent_step']:,.0f} of them. Agent-steps/s: env alone "
            f"{r['env_agent_steps_per_s']:,.0f}, with acting and insert "
            f"{r['collect_agent_steps_per_s']:,.0f}, with the updates "
            f"{r['train_agent_steps_per_s']:,.1f}. The stack shift done in one process "
            f"takes {r['stack_one_process_ms']:,.2f} ms (inside the env it is part of "
            f"render, spread over the workers). Compile: {r['compile_parts_s']} s.", ""]
  return "\n".join(out)


def main(argv=None) -> None:
  """Command-line entry: one row per N, appended to --out, and the Markdown beside."""
  argv = sys.argv[1:] if argv is None else argv
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--sizes", default="1024", help="numbers of envs N, comma-separated")
  p.add_argument("--quality", default="fastest", help="render preset")
  p.add_argument("--workers", type=int, default=None, help="render workers (default: cores)")
  p.add_argument("--frame-skip", type=int, default=2)
  p.add_argument("--frame-stack", type=int, default=3)
  p.add_argument("--image-size", type=int, default=84)
  p.add_argument("--steps", type=int, default=20, help="timed env steps")
  p.add_argument("--batch", type=int, default=256, help="SAC batch size")
  p.add_argument("--dtype", default="float32", help="compute dtype: float32 or bfloat16")
  p.add_argument("--utd", type=float, default=1.0, help="updates per transition")
  p.add_argument("--capacity", type=int, default=100_000, help="replay rows over all envs")
  p.add_argument("--pairs", type=int, default=None,
                 help="update pairs per timed call (default: 1 on CPU, 10 otherwise)")
  p.add_argument("--reps", type=int, default=5, help="timed calls per learner part")
  p.add_argument("--no-copy", action="store_true", help="make(copy_obs=False)")
  p.add_argument("--physics-device", default=None, choices=("cpu",),
                 help="make(physics_device=...): cpu steps the physics on the host CPU "
                      "(default: JAX's default device)")
  p.add_argument("--out", default=None, help="JSONL path (appended to); .md beside")
  a = p.parse_args(argv)
  from dmcr_jax.visuals.tiled import check_quality
  from dmcr_jax.train import sac
  try:
    sizes = [int(s) for s in a.sizes.split(",")]
    dmcr_jax.models.split_name(a.task)
    check_quality(a.quality)
    sac.SACConfig(batch_size=a.batch, compute_dtype=a.dtype)
    for name in ("steps", "capacity", "reps", "image_size", "frame_stack", "frame_skip"):
      if getattr(a, name) < 1:
        raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
    if min(sizes) < 1 or not a.utd > 0:
      raise ValueError("--sizes must be positive ints and --utd > 0")
  except ValueError as e:
    p.error(str(e))
  import jax
  pairs = a.pairs or (1 if jax.default_backend() == "cpu" else 10)
  rows = []
  for n in sizes:
    row = profile(a.task, n, a.quality, a.workers, a.frame_skip, a.frame_stack,
                  a.image_size, a.steps, a.batch, a.dtype, a.utd, a.capacity, pairs, a.reps,
                  copy_obs=not a.no_copy, physics_device=a.physics_device)
    rows.append(row)
    R.emit(row, a.out)
  if a.out:
    rows = R.read(a.out)
    R.write_markdown(a.out, f"Rows of `python -m dmcr_jax.benchmarks.step_profile` (see its "
                     f"docstring) appended to `{os.path.basename(a.out)}`; the last run: "
                     f"`python -m dmcr_jax.benchmarks.step_profile {' '.join(argv)}` "
                     f"({os.cpu_count()} cores).\n\n" + markdown(rows))
  print(markdown(rows))


if __name__ == "__main__":
  main()
