"""Hopper: stand, hop (dm_control `hopper`).

A JAX port of `dm_control.suite.hopper.Hopper` on dm_control's own `hopper.xml`
(0.005 s physics steps, 0.02 s control steps = 4 substeps, 20 s = 1,000 control
steps). Reset draws every limited joint uniformly in its range and the
unlimited `rooty` hinge uniformly in [-π, π] (dm_control's joint randomizer).
Observation: `position` = qpos without rootx, `velocity` = qvel, `touch` =
log1p of the `touch_toe`, `touch_heel` sensors (acceleration stage: they
describe the start of the last substep, as in dm_control's legacy stepping).
Reward: torso-above-foot height inside (0.6, 2), times small control (stand) or
a linear forward-speed term on `torso_subtreelinvel` (hop, 2 m/s).
No deviation from dm_control; the only model edit is the `energy` flag.
"""

from __future__ import annotations

import collections

import jax.numpy as jnp

from dmcr_jax.models import names, randomizers
from dmcr_jax.models.base import task_variants
from dmcr_jax.models.rewards import tolerance

_CONTROL_TIMESTEP = .02
_DEFAULT_TIME_LIMIT = 20
_STAND_HEIGHT = 0.6
_HOP_SPEED = 2


def _height(m, d):
  """Height of the torso's centre of mass above the foot's."""
  return d.xipos[names.body_id(m, "torso"), 2] - d.xipos[names.body_id(m, "foot"), 2]


def _speed(m, d):
  return names.sensor(m, d, "torso_subtreelinvel")[0]


def _touch(m, d):
  return jnp.log1p(jnp.concatenate(
      [names.sensor(m, d, "touch_toe"), names.sensor(m, d, "touch_heel")]))


def _observation(m, d, info):
  del info
  return collections.OrderedDict(
      position=d.qpos[1:], velocity=d.qvel, touch=_touch(m, d))


def _reward(m, d, info, hopping: bool):
  del info
  standing = tolerance(_height(m, d), (_STAND_HEIGHT, 2))
  if hopping:
    hopping_reward = tolerance(_speed(m, d), bounds=(_HOP_SPEED, float("inf")),
                               margin=_HOP_SPEED / 2, value_at_margin=0.5,
                               sigmoid="linear")
    return standing * hopping_reward
  small_control = tolerance(d.ctrl, margin=1, value_at_margin=0,
                            sigmoid="quadratic").mean()
  small_control = (small_control + 4) / 5
  return standing * small_control


TASKS = task_variants(
    {"stand": {"reward": dict(hopping=False)},
     "hop": {"reward": dict(hopping=True)}},
    domain="hopper", initialize=randomizers.initialize_randomized_joints,
    observation=_observation, reward=_reward,
    control_timestep=_CONTROL_TIMESTEP, time_limit=_DEFAULT_TIME_LIMIT)
