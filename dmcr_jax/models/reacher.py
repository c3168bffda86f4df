"""Reacher: easy, hard (dm_control `reacher`).

A JAX port of `dm_control.suite.reacher.Reacher` on dm_control's own
`reacher.xml` (contacts disabled, one 0.02 s physics step per control step,
20 s = 1,000 steps). Each episode randomises both joints as dm_control's
randomizer does (shoulder uniform in [-π, π], wrist uniform in its range) and
places the target at angle U(0, 2π), radius U(.05, .20) around the origin; the
target's `geom_pos` and `geom_size` (.05 easy, .015 hard) are model variables
kept in `info`. The target geom hangs on the world body, so its world position
is its `geom_pos`. Observation: `position` = qpos, `to_target` = target − finger
(x, y), `velocity` = qvel. Reward: 1 when the finger–target distance is at most
the sum of their radii, else 0. No model edits beyond the shared `energy` flag.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp

from dmcr_jax.models import names, randomizers
from dmcr_jax.models.base import task_variants

_TIME_LIMIT = 20.0
_BIG_TARGET = .05
_SMALL_TARGET = .015

_TARGET_POS = "geom_pos:target"
_TARGET_SIZE = "geom_size:target"


def _initialize(key, m, d, target_size: float):
  k_joints, k_angle, k_radius = jax.random.split(key, 3)
  qpos = randomizers.randomize_limited_and_rotational_joints(k_joints, m, d.qpos)
  angle = jax.random.uniform(k_angle, minval=0., maxval=2 * jnp.pi)
  radius = jax.random.uniform(k_radius, minval=.05, maxval=.20)
  target = names.geom_id(m, "target")
  pos = jnp.asarray(m.geom_pos)[target].at[0].set(radius * jnp.sin(angle))
  pos = pos.at[1].set(radius * jnp.cos(angle))
  size = jnp.asarray(m.geom_size)[target].at[0].set(target_size)
  info = {_TARGET_POS: pos.astype(jnp.float32), _TARGET_SIZE: size.astype(jnp.float32)}
  return d.replace(qpos=qpos), info


def _finger_to_target(m, d, info):
  # The target geom is attached to the world body: world position = geom_pos.
  return info[_TARGET_POS][:2] - d.geom_xpos[names.geom_id(m, "finger"), :2]


def _observation(m, d, info):
  return {"position": d.qpos, "to_target": _finger_to_target(m, d, info),
          "velocity": d.qvel}


def _reward(m, d, info):
  radii = info[_TARGET_SIZE][0] + m.geom_size[names.geom_id(m, "finger"), 0]
  dist = jnp.linalg.norm(_finger_to_target(m, d, info))
  # `tolerance` needs static bounds; with margin 0 it is this indicator.
  return jnp.where((dist >= 0) & (dist <= radii), 1.0, 0.0)


TASKS = task_variants(
    {"easy": {"initialize": dict(target_size=_BIG_TARGET)},
     "hard": {"initialize": dict(target_size=_SMALL_TARGET)}},
    domain="reacher", initialize=_initialize, observation=_observation, reward=_reward,
    control_timestep=None, time_limit=_TIME_LIMIT,
    model_variables=(("geom_pos", "target"), ("geom_size", "target")))
