"""The device driver: with the JAX renderer, a chunk of training is one XLA call.

`dmcr_jax.train.loop.train` runs a plan with this stepper when its renderer is
the ray caster and the physics steps on the learner's device
(`dmcr_jax.train.config.Plan.device_driver`). The env is
`dmcr_jax.make(..., renderer="jax")`, whose pure functional core
(`dmcr_jax.jax_env.PixelEnv`) steps the physics, ray-casts the frames and stacks
them on the device. A chunk of `TrainConfig.chunk_steps` vector steps of all K·N
envs is one jitted `lax.scan` of `dmcr_jax.train.step`'s training step (act,
learn, env step, store) — the functions the host driver calls, with the same RNG
stream: given the same frames, both drivers train the same agents, up to float32
rounding (`tests/test_train.py`). The update count owed and whether the buffers
can be sampled are kept in the scan's carry (`dmcr_jax.train.step.owed_updates`,
`can_sample`); the number of update pairs of a step is dynamic (a loop of that
many pairs).

`device_steps` yields one report per chunk (the host driver's form), so the
log, checkpoints and the stop flag are handled between chunks by `train`. The
run's last chunk is shortened to end at `steps` (one more compilation when
`steps` is not a multiple of `chunk_steps × num_envs`). The whole run lives on
one device (the agent axis is not sharded over several).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from dmcr_jax import jax_env
from dmcr_jax.train import step as train_step


@struct.dataclass
class Carry:
  """What one chunk hands the next (a frozen pytree; donated between chunks).

  Attributes:
    learner: the `dmcr_jax.train.step.Learner` of the K agents.
    env: the `jax_env.PixelState` of the K·N envs (agent k acts in envs k·N …).
    owed: float32 updates owed and not yet run.
    ready: bool, every buffer could be sampled at some step.
    updates_from: int32, transitions per agent before which no update is owed
      (`dmcr_jax.train.loop.updates_from`; traced, so fresh and resumed runs share one
      compilation).
  """
  learner: train_step.Learner
  env: jax_env.PixelState
  owed: jax.Array
  ready: jax.Array
  updates_from: jax.Array


def vector_step(penv: jax_env.PixelEnv, c: Carry, spec: train_step.StepSpec):
  """One training step of every agent's N envs (`dmcr_jax.train.step`'s module doc)."""
  learner, action, env_action = train_step.act(c.learner, c.env.obs, spec)
  owed, ready, pairs = train_step.plan_updates(
      c.owed, c.ready, c.learner.step, lambda: train_step.can_sample(learner.buffers), spec,
      jnp, c.updates_from)
  learner = train_step.learn(learner, pairs, spec)
  first = c.env.physics.episode_step == 0
  env, reward, truncated = penv.step(c.env, env_action)
  learner = train_step.store(learner, c.env.obs, first, action, reward, spec)
  out = dict(step=learner.step, truncated=truncated,
             episode_return=env.physics.episode_return, metrics=learner.metrics)
  return Carry(learner=learner, env=env, owed=owed, ready=ready,
               updates_from=c.updates_from), out


def _chunk(penv: jax_env.PixelEnv, carry: Carry, spec: train_step.StepSpec, length: int):
  """`length` vector steps as one `lax.scan`; (carry, per-step outputs)."""
  return jax.lax.scan(lambda c, _: vector_step(penv, c, spec), carry, None, length=length)


_chunk_jit = jax.jit(_chunk, static_argnames=("spec", "length"))
_chunk_donated = jax.jit(_chunk, static_argnames=("spec", "length"), donate_argnums=(1,))


def device_steps(plan, env, learner: train_step.Learner, spec: train_step.StepSpec,
                 start: int, first_update: int):
  """The device driver: yields (step before, step after, finished episodes, learner)
  after every chunk until `steps` (episodes: (step, agent, return, the update
  metrics at its step) each), as `dmcr_jax.train.loop.host_steps` does per step.

  Args:
    plan: the run's `dmcr_jax.train.config.Plan`.
    env: its `dmcr_jax.make(..., renderer="jax", obs_on_device=True)` env.
    learner: the `Learner` at step `start`.
    spec: the `StepSpec`.
    start: the first step (a resumed run's checkpoint).
    first_update: transitions per agent before which no update is owed.
  """
  cfg, n = plan.cfg, plan.cfg.num_envs
  env.reset(seed=int(cfg.seeds[0]) + start)
  carry = Carry(learner=learner, env=env.pixel_state, owed=jnp.zeros((), jnp.float32),
                ready=jnp.zeros((), bool),
                updates_from=jnp.asarray(first_update, jnp.int32))
  # Committed to one device, as restored checkpoints are: fresh and resumed runs
  # then share one compilation (committed and uncommitted inputs do not).
  carry = jax.device_put(carry, jax.devices()[0])
  chunk_fn = _chunk_jit if jax.default_backend() == "cpu" else _chunk_donated
  step = start
  while step < cfg.steps:
    length = min(cfg.chunk_steps, math.ceil((cfg.steps - step) / n))
    carry, out = chunk_fn(env.functional, carry, spec=spec, length=length)
    out = jax.device_get(out)
    before, step = step, int(out["step"][-1])
    episodes = [(int(out["step"][s]), int(i // n), float(out["episode_return"][s, i]),
                 {name: v[s] for name, v in out["metrics"].items()})
                for s, i in zip(*np.nonzero(out["truncated"]))]
    yield before, step, episodes, carry.learner
