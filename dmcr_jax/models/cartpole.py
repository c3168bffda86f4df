"""Cartpole: balance, balance_sparse, swingup, swingup_sparse (dm_control `cartpole`).

A JAX port of `dm_control.suite.cartpole.Balance` on dm_control's own one-pole
`cartpole.xml` (RK4 integrator, one physics step per control step, 10 s = 1,000
steps). Observation: `position` = (cart x, pole xmat zz, pole xmat xz),
`velocity` = qvel. Rewards as dm_control: smooth (upright · centred · small
control · small velocity) or sparse (cart and pole inside their bounds).
The only model edit is the `energy` flag, which MJX does not take and which
computes diagnostics only.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp

from dmcr_jax.models.base import task_variants
from dmcr_jax.models.rewards import tolerance

_CART_RANGE = (-.25, .25)
_ANGLE_COSINE_RANGE = (.995, 1)
_TIME_LIMIT = 10.0


def _initialize(key, m, d, swing_up: bool):
  nv = m.nv
  k1, k2, k3 = jax.random.split(key, 3)
  qpos = d.qpos
  if swing_up:
    qpos = qpos.at[0].set(.01 * jax.random.normal(k1))
    qpos = qpos.at[1].set(jnp.pi + .01 * jax.random.normal(k2))
  else:
    qpos = qpos.at[0].set(jax.random.uniform(k1, minval=-.1, maxval=.1))
    qpos = qpos.at[1:].set(jax.random.uniform(k2, (nv - 1,), minval=-.034, maxval=.034))
  qvel = .01 * jax.random.normal(k3, (nv,))
  return d.replace(qpos=qpos, qvel=qvel), {}


def _pole_angle_cosine(d):
  return d.xmat[2:, 2, 2]


def _observation(m, d, info):
  del m, info
  position = jnp.concatenate([d.qpos[:1], d.xmat[2:, [2, 0], [2, 2]].ravel()])
  return {"position": position, "velocity": d.qvel}


def _reward(m, d, info, sparse: bool):
  del m, info
  cart_position = d.qpos[0]
  if sparse:
    cart_in_bounds = tolerance(cart_position, _CART_RANGE)
    angle_in_bounds = tolerance(_pole_angle_cosine(d), _ANGLE_COSINE_RANGE).prod()
    return cart_in_bounds * angle_in_bounds
  upright = (_pole_angle_cosine(d) + 1) / 2
  centered = (1 + tolerance(cart_position, margin=2)) / 2
  small_control = tolerance(d.ctrl, margin=1, value_at_margin=0,
                            sigmoid="quadratic")[0]
  small_control = (4 + small_control) / 5
  small_velocity = (1 + tolerance(d.qvel[1:], margin=5).min()) / 2
  return upright.mean() * small_control * small_velocity * centered


TASKS = task_variants(
    {"balance": {"initialize": dict(swing_up=False), "reward": dict(sparse=False)},
     "balance_sparse": {"initialize": dict(swing_up=False), "reward": dict(sparse=True)},
     "swingup": {"initialize": dict(swing_up=True), "reward": dict(sparse=False)},
     "swingup_sparse": {"initialize": dict(swing_up=True), "reward": dict(sparse=True)}},
    domain="cartpole", initialize=_initialize, observation=_observation, reward=_reward,
    control_timestep=None, time_limit=_TIME_LIMIT)
