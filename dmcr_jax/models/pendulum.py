"""Pendulum: swingup (dm_control `pendulum`).

A JAX port of `dm_control.suite.pendulum.SwingUp` on dm_control's own
`pendulum.xml` (contacts disabled, one 20 ms physics step per control step,
20 s = 1,000 steps). The episode starts at rest with the hinge angle uniform in
[-π, π). Observation: `orientation` = the pole's xmat (zz, xz), `velocity` = the
hinge velocity (a scalar). Reward: 1 while the pole is within 8° of upright
(`tolerance` of xmat zz with zero margin), else 0. The only model edit is the
`energy` flag (base.load_mj_model), which MJX does not take and which computes
diagnostics only.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.models import names
from dmcr_jax.models.base import TaskSpec
from dmcr_jax.models.rewards import tolerance

_DEFAULT_TIME_LIMIT = 20.0
_ANGLE_BOUND = 8
_COSINE_BOUND = float(np.cos(np.deg2rad(_ANGLE_BOUND)))


def _pole_xmat(m, d):
  return d.xmat[names.body_id(m, "pole")]


def _initialize(key, m, d):
  adr = names.qpos_adr(m, "hinge")
  angle = jax.random.uniform(key, (), minval=-jnp.pi, maxval=jnp.pi)
  return d.replace(qpos=d.qpos.at[adr].set(angle)), {}


def _observation(m, d, info):
  del info
  xmat = _pole_xmat(m, d)
  return {"orientation": jnp.stack([xmat[2, 2], xmat[0, 2]]),
          "velocity": d.qvel[names.qvel_adr(m, "hinge")]}


def _reward(m, d, info):
  del info
  return tolerance(_pole_xmat(m, d)[2, 2], (_COSINE_BOUND, 1.0))


TASKS = {
    "swingup": TaskSpec(
        domain="pendulum", task="swingup", initialize=_initialize,
        observation=_observation, reward=_reward, control_timestep=None,
        time_limit=_DEFAULT_TIME_LIMIT),
}
