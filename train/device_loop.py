"""The training loop on the device: with the JAX renderer, a chunk of training is one XLA call.

`train --renderer jax` (`TrainConfig.renderer = "jax"`; `loop.train` dispatches
here). The env is `dmcr_jax.make(..., renderer="jax")`, whose pure functional core
(`dmcr_jax.jax_env.PixelEnv`) steps the physics, ray-casts the frames and stacks
them on the device. A chunk of `TrainConfig.chunk_steps` vector steps of all K·N
envs is one jitted `lax.scan` whose body does, per vector step, exactly what the
host loop (`train.loop`) does per `env.step`:

1. act: uniform random actions while the agent's step count is below
   `warmup_steps`, else `sac.act` (policy samples) on the current stacks
   (`loop.actions`);
2. update: the `utd` updates owed for the step's N transitions per agent, as
   `sac.update_pair`s (`loop.update_pair`: two batches sampled from the buffer,
   a critic-only update, then a full one), sampling the buffers as they were
   before this step's transitions (the DrQ, CURL and SAC-AE order: update, then
   env step); they wait, and accumulate, until every buffer holds a valid
   transition; the count of pairs is dynamic (a `fori_loop`);
3. step the env (`PixelEnv.step`: frame skip, auto-reset, frames, stacks);
4. add the transition (newest frame of the acted-on observation, its
   episode-start flag, the action, the reward) to every agent's buffer.

Between chunks the host writes the finished episodes to log.csv (each with the
metrics of the latest updates at its step), moves the progress bar, saves
checkpoints (at the first chunk end at or past each `checkpoint_every`) and
checks the stop flag (SIGINT/SIGTERM); configuration, the log, checkpoints,
resume (agents, step and key; not the buffers) and the summary are `train.loop`'s.
The run's last chunk is shortened to end at `steps` (one more compilation when
`steps` is not a multiple of `chunk_steps × num_envs`).

Limits: the whole run lives on one device (the agent axis is not sharded over
several, unlike the host loop's `shard_map`); update RNG streams differ from the
host loop's (per-pair keys are `fold_in`s), so the two loops train alike but not
bit for bit.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from dmcr_jax import jax_env
from train import loop, replay, sac
from train.loop import TrainConfig


@struct.dataclass
class Carry:
  """What one chunk hands the next (a frozen pytree; donated between chunks).

  Attributes:
    agents: the K agents (leading agent axis).
    buffers: their replay buffers (leading agent axis).
    env: the `jax_env.PixelState` of the K·N envs (agent k acts in envs k·N …).
    key: the run's PRNG key.
    step: int32 training steps (transitions) per agent so far.
    owed: float32 updates owed and not yet run.
    ready: bool, every buffer held a valid transition at some update.
    metrics: name → float32 (K,) means of the latest updates (NaN before any).
  """
  agents: sac.AgentState
  buffers: replay.ReplayBuffer
  env: jax_env.PixelState
  key: jax.Array
  step: jax.Array
  owed: jax.Array
  ready: jax.Array
  metrics: dict


@dataclasses.dataclass(frozen=True)
class _Static:
  """The chunk's static settings (hashable; a resumed run with another `steps`
  reuses the compilation)."""
  agents: int
  num_envs: int
  warmup_steps: int
  utd: float
  sac: sac.SACConfig
  agent_loop: str
  low: tuple
  high: tuple


def _updates(agents, buffers, keys, pairs, config: sac.SACConfig, agent_loop: str,
             names: tuple[str, ...]):
  """`pairs` (traced) × `loop.update_pair` per agent; (agents, mean metrics (K,))."""
  def one_agent(agent, buffer, key):
    def body(i, carry):
      agent, sums = carry
      agent, m = loop.update_pair(agent, buffer, jax.random.fold_in(key, i), config)
      return agent, {name: sums[name] + jnp.mean(m[name]).astype(jnp.float32)
                     for name in names}

    zeros = {name: jnp.zeros((), jnp.float32) for name in names}
    agent, sums = jax.lax.fori_loop(0, pairs, body, (agent, zeros))
    return agent, {name: v / pairs for name, v in sums.items()}
  return loop.over_agents(one_agent, agent_loop, agents)(agents, buffers, keys)


def _vector_step(penv: jax_env.PixelEnv, c: Carry, st: _Static):
  """One vector step of every agent's N envs (module doc, steps 1–4)."""
  k, n = st.agents, st.num_envs
  key, k_act, k_upd = jax.random.split(c.key, 3)
  obs = c.env.obs.reshape((k, n) + c.env.obs.shape[1:])
  act_keys = jax.random.split(k_act, k)
  action = jax.lax.cond(c.step < st.warmup_steps,
                        lambda: loop.actions(c.agents, obs, act_keys, True),
                        lambda: loop.actions(c.agents, obs, act_keys, False))
  before, step = c.step, c.step + n
  # Updates owed for this step's transitions (as the host loop's dispatch_updates).
  learning = step > st.warmup_steps
  owed = jnp.where(learning, c.owed + st.utd * (step - jnp.maximum(
      before, st.warmup_steps)).astype(jnp.float32), c.owed)
  pairs = jnp.floor(owed / 2).astype(jnp.int32)
  ready = jax.lax.cond(c.ready | ~learning, lambda: c.ready, lambda: jnp.all(
      jax.vmap(replay.num_valid)(c.buffers) > 0))
  run = learning & ready & (pairs > 0)
  upd_keys = jax.random.split(jax.random.fold_in(k_upd, 0), k)
  names = tuple(sorted(c.metrics))
  agents, metrics = jax.lax.cond(
      run, lambda: _updates(c.agents, c.buffers, upd_keys, pairs, st.sac, st.agent_loop,
                            names),
      lambda: (c.agents, c.metrics))
  owed = jnp.where(run, owed - 2 * pairs, owed)
  # The env step and the transition.
  low, high = np.asarray(st.low, np.float32), np.asarray(st.high, np.float32)
  env_action = loop.to_env_action(action.reshape(k * n, -1), low, high)
  first = (c.env.physics.episode_step == 0).reshape(k, n)
  env, reward, truncated = penv.step(c.env, env_action)
  buffers = jax.vmap(replay.add)(c.buffers, obs[..., -3:], first, action,
                                 reward.reshape(k, n))
  out = dict(step=step, truncated=truncated, episode_return=env.physics.episode_return,
             metrics=metrics)
  return Carry(agents=agents, buffers=buffers, env=env, key=key, step=step, owed=owed,
               ready=ready, metrics=metrics), out


def _chunk(penv: jax_env.PixelEnv, carry: Carry, st: _Static, length: int):
  """`length` vector steps as one `lax.scan`; (carry, per-step outputs)."""
  return jax.lax.scan(lambda c, _: _vector_step(penv, c, st), carry, None, length=length)


_chunk_jit = jax.jit(_chunk, static_argnames=("st", "length"))
_chunk_donated = jax.jit(_chunk, static_argnames=("st", "length"), donate_argnums=(1,))


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True) -> dict:
  """`loop.train` for `cfg.renderer == "jax"` (same arguments, outputs and errors)."""
  import dmcr_jax
  manager = loop.open_run(cfg, resume)
  specs = cfg.agents()
  k, n = len(specs), cfg.num_envs
  env = dmcr_jax.make(cfg.task, num_envs=k * n,
                      visual_seeds=loop.parse_visual_seeds(cfg.visual_seeds), vary=cfg.vary,
                      frame_skip=cfg.action_repeat, frame_stack=cfg.frame_stack,
                      image_size=cfg.image_size, seed=int(cfg.seeds[0]), renderer="jax",
                      obs_on_device=True)
  on_cpu = jax.default_backend() == "cpu"
  obs_shape = env.single_observation_space.shape
  action_size = env.task.action_size
  agents, buffers, key, start = loop.initial_state(cfg, manager, resume, obs_shape,
                                                   action_size)
  env.reset(seed=int(cfg.seeds[0]) + start)
  names = jax.eval_shape(
      lambda a, b, kk: loop.update_pair(a, b, kk, cfg.sac)[1],
      jax.tree.map(lambda x: x[0], agents), jax.tree.map(lambda x: x[0], buffers),
      jax.random.key(0)).keys()
  carry = Carry(agents=agents, buffers=buffers, env=env.pixel_state, key=key,
                step=jnp.asarray(start, jnp.int32), owed=jnp.zeros((), jnp.float32),
                ready=jnp.zeros((), bool),
                metrics={name: jnp.full((k,), jnp.nan, jnp.float32) for name in names})
  # Committed to one device, as restored checkpoints are: fresh and resumed runs
  # then share one compilation (committed and uncommitted inputs do not).
  carry = jax.device_put(carry, jax.devices()[0])
  st = _Static(agents=k, num_envs=n, warmup_steps=int(cfg.warmup_steps), utd=float(cfg.utd),
               sac=cfg.sac, agent_loop=cfg.agent_loop or ("vmap" if on_cpu else "map"),
               low=tuple(float(x) for x in env.single_action_space.low),
               high=tuple(float(x) for x in env.single_action_space.high))
  chunk_fn = _chunk_jit if on_cpu else _chunk_donated
  log = loop.RunLog(cfg, start, resume, progress)
  step = start
  try:
    while step < cfg.steps and not log.stopped:
      length = min(cfg.chunk_steps, math.ceil((cfg.steps - step) / n))
      carry, out = chunk_fn(env.functional, carry, st=st, length=length)
      out = jax.device_get(out)
      before, step = step, int(out["step"][-1])
      wall = log.wall()
      for s, i in zip(*np.nonzero(out["truncated"])):
        metrics = {name: v[s] for name, v in out["metrics"].items()}
        log.episode(int(out["step"][s]), int(i // n), float(out["episode_return"][s, i]),
                    wall, metrics)
      if loop.crossed(cfg.log_every, before, step) or step >= cfg.steps:
        log.progress(step)
      if loop.crossed(cfg.checkpoint_every, before, step):
        loop._save(manager, step, carry.agents, carry.key)
    if manager.latest_step() != step:
      loop._save(manager, step, carry.agents, carry.key)
  finally:
    log.close()
    env.close()
  return loop.finish(cfg, step, log)
