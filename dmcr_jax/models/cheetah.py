"""Cheetah: run (dm_control `cheetah`).

A JAX port of `dm_control.suite.cheetah.Cheetah` on dm_control's own
`cheetah.xml` (one 0.01 s physics step per control step, 10 s = 1,000 steps).
Reset draws every limited joint uniformly in its range, lets the model settle
for 200 physics steps and sets time to 0. dm_control's first settling step is
its legacy `mj_step2`, which integrates the accelerations of the *previous*
forward pass (the reset pose, qpos0) from the randomised pose; this port
reproduces that by running `mjx.forward` at qpos0 and `mjx.euler` after writing
the randomised qpos, then 199 ordinary `mjx.step`s. Observation: `position` =
qpos without rootx, `velocity` = qvel. Reward: linear in the `torso_subtreelinvel`
x velocity, 1 from 10 m/s. No deviation from dm_control; the only model edit is
the `energy` flag.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from dmcr_jax._mjx import mjx  # mujoco.mjx, quietly

from dmcr_jax.models import names
from dmcr_jax.models.base import TaskSpec, physics_steps
from dmcr_jax.models.rewards import tolerance

_DEFAULT_TIME_LIMIT = 10
_RUN_SPEED = 10
_SETTLE_STEPS = 200


def _speed(m, d):
  return names.sensor(m, d, "torso_subtreelinvel")[0]


def _initialize(key, m, d):
  # dm_control indexes qpos by joint: every joint has one dof.
  assert m.nq == m.njnt
  limited = np.asarray(m.jnt_limited).astype(bool)
  lower, upper = jnp.asarray(m.jnt_range)[limited].T
  qpos = d.qpos.at[limited].set(
      jax.random.uniform(key, lower.shape, minval=lower, maxval=upper))
  # First settling step: dm_control's mj_step2 on the reset pose's forward pass.
  d = mjx.forward(m, d)
  d = mjx.euler(m, d.replace(qpos=qpos))
  d = physics_steps(m, d, _SETTLE_STEPS - 1)
  return d.replace(time=jnp.zeros_like(d.time)), {}


def _observation(m, d, info):
  del m, info
  return {"position": d.qpos[1:], "velocity": d.qvel}


def _reward(m, d, info):
  del info
  return tolerance(_speed(m, d), bounds=(_RUN_SPEED, float("inf")),
                   margin=_RUN_SPEED, value_at_margin=0, sigmoid="linear")


TASKS = {
    "run": TaskSpec(domain="cheetah", task="run", initialize=_initialize,
                    observation=_observation, reward=_reward,
                    control_timestep=None, time_limit=_DEFAULT_TIME_LIMIT),
}
