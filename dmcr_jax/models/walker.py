"""Walker: stand, walk, run (dm_control `walker`).

A JAX port of `dm_control.suite.walker.PlanarWalker` on dm_control's own
`walker.xml` (0.0025 s physics steps, 0.025 s control steps = 10 substeps,
25 s = 1,000 control steps). Reset draws every limited joint uniformly in its
range and the unlimited `rooty` hinge uniformly in [-π, π] (dm_control's joint
randomizer); the root slides stay at 0. Observation: `orientations` = the xx, xz
entries of `xmat` for every body but the world, `height` = torso z, `velocity` =
qvel. Reward: standing (torso height) and uprightness, times a linear speed
term on the `torso_subtreelinvel` sensor for walk (1 m/s) and run (8 m/s).
No deviation from dm_control; the only model edit is the `energy` flag.
"""

from __future__ import annotations

import collections

from dmcr_jax.models import names, randomizers
from dmcr_jax.models.base import task_variants
from dmcr_jax.models.rewards import tolerance

_DEFAULT_TIME_LIMIT = 25
_CONTROL_TIMESTEP = .025
_STAND_HEIGHT = 1.2
_WALK_SPEED = 1
_RUN_SPEED = 8


def _torso_upright(m, d):
  return d.xmat[names.body_id(m, "torso"), 2, 2]


def _torso_height(m, d):
  return d.xpos[names.body_id(m, "torso"), 2]


def _horizontal_velocity(m, d):
  return names.sensor(m, d, "torso_subtreelinvel")[0]


def _observation(m, d, info):
  del info
  return collections.OrderedDict(
      orientations=d.xmat[1:, 0, [0, 2]].ravel(),
      height=_torso_height(m, d),
      velocity=d.qvel)


def _reward(m, d, info, move_speed: float):
  del info
  standing = tolerance(_torso_height(m, d), bounds=(_STAND_HEIGHT, float("inf")),
                       margin=_STAND_HEIGHT / 2)
  upright = (1 + _torso_upright(m, d)) / 2
  stand_reward = (3 * standing + upright) / 4
  if move_speed == 0:
    return stand_reward
  move_reward = tolerance(_horizontal_velocity(m, d),
                          bounds=(move_speed, float("inf")),
                          margin=move_speed / 2, value_at_margin=0.5,
                          sigmoid="linear")
  return stand_reward * (5 * move_reward + 1) / 6


TASKS = task_variants(
    {"stand": {"reward": dict(move_speed=0)},
     "walk": {"reward": dict(move_speed=_WALK_SPEED)},
     "run": {"reward": dict(move_speed=_RUN_SPEED)}},
    domain="walker", initialize=randomizers.initialize_randomized_joints,
    observation=_observation, reward=_reward,
    control_timestep=_CONTROL_TIMESTEP, time_limit=_DEFAULT_TIME_LIMIT)
