"""Humanoid: stand, walk, run (dm_control `humanoid`).

A JAX port of `dm_control.suite.humanoid.Humanoid` (the feature observations,
not `run_pure_state`) on dm_control's own `humanoid.xml` (5 ms physics steps,
5 per 25 ms control step, 25 s = 1,000 steps). The episode starts with every
joint drawn by `randomize_limited_and_rotational_joints` (limited hinges uniform
in range, the root's orientation `normalize(U(0,1)^4)`, its position left at
1.5 m), redrawn with `fold_in(key, attempt)` until nothing touches, as
dm_control loops while `ncon > 0` (shared rejection loop of `ball_in_cup`).
Observation, in dm_control's order: `joint_angles` (qpos without the free
joint), `head_height`, `extremities` (hands and feet relative to the torso, in
the torso frame), `torso_vertical` (the torso xmat's z row), `com_velocity`
(the `torso_subtreelinvel` sensor), `velocity` (qvel). Reward: standing (head
height) · upright (torso zz) · small control · either not moving (stand) or
horizontal centre-of-mass speed at least 1 (walk) or 10 m/s (run). The only
model edit is the `energy` flag.
"""

from __future__ import annotations

import collections

import jax.numpy as jnp
import mujoco
import numpy as np

from dmcr_jax.models import names, randomizers
from dmcr_jax.models.ball_in_cup import rejection_sample
from dmcr_jax.models.base import task_variants
from dmcr_jax.models.rewards import tolerance

_DEFAULT_TIME_LIMIT = 25.0
_CONTROL_TIMESTEP = .025
_STAND_HEIGHT = 1.4
_WALK_SPEED = 1.0
_RUN_SPEED = 10.0


def _initialize(key, m, d):
  draw = lambda k, qpos: randomizers.randomize_limited_and_rotational_joints(
      k, m, qpos)
  return rejection_sample(key, m, d, draw), {}


def _joint_angles(m, d):
  """qpos without the free joints' 7 entries (dm_control's `qpos[7:]`)."""
  free = np.asarray(m.jnt_type) == mujoco.mjtJoint.mjJNT_FREE
  keep = np.ones(m.nq, bool)
  for adr in np.asarray(m.jnt_qposadr)[free]:
    keep[adr:adr + 7] = False
  return d.qpos[np.flatnonzero(keep)]


def _head_height(m, d):
  return d.xpos[names.body_id(m, "head"), 2]


def _torso_xmat(m, d):
  return d.xmat[names.body_id(m, "torso")]


def _extremities(m, d):
  torso = names.body_id(m, "torso")
  limbs = [names.body_id(m, side + limb) for side in ("left_", "right_")
           for limb in ("hand", "foot")]
  torso_to_limb = d.xpos[np.array(limbs)] - d.xpos[torso]
  return (torso_to_limb @ d.xmat[torso]).ravel()


def _com_velocity(m, d):
  return names.sensor(m, d, "torso_subtreelinvel")


def _observation(m, d, info):
  del info
  # An OrderedDict: JAX sorts a plain dict's keys when it flattens one (e.g. in
  # `Task.__init__`'s `eval_shape`), which would lose dm_control's order.
  return collections.OrderedDict([
      ("joint_angles", _joint_angles(m, d)),
      ("head_height", _head_height(m, d)),
      ("extremities", _extremities(m, d)),
      ("torso_vertical", _torso_xmat(m, d)[2]),
      ("com_velocity", _com_velocity(m, d)),
      ("velocity", d.qvel)])


def _reward(m, d, info, move_speed: float):
  del info
  standing = tolerance(_head_height(m, d), bounds=(_STAND_HEIGHT, float("inf")),
                       margin=_STAND_HEIGHT / 4)
  upright = tolerance(_torso_xmat(m, d)[2, 2], bounds=(0.9, float("inf")),
                      sigmoid="linear", margin=1.9, value_at_margin=0)
  stand_reward = standing * upright
  small_control = tolerance(d.ctrl, margin=1, value_at_margin=0,
                            sigmoid="quadratic").mean()
  small_control = (4 + small_control) / 5
  horizontal_velocity = _com_velocity(m, d)[:2]
  if move_speed == 0:
    dont_move = tolerance(horizontal_velocity, margin=2).mean()
    return small_control * stand_reward * dont_move
  move = tolerance(jnp.linalg.norm(horizontal_velocity),
                   bounds=(move_speed, float("inf")), margin=move_speed,
                   value_at_margin=0, sigmoid="linear")
  move = (5 * move + 1) / 6
  return small_control * stand_reward * move


TASKS = task_variants(
    {"stand": {"reward": dict(move_speed=0.0)},
     "walk": {"reward": dict(move_speed=_WALK_SPEED)},
     "run": {"reward": dict(move_speed=_RUN_SPEED)}},
    domain="humanoid", initialize=_initialize, observation=_observation, reward=_reward,
    control_timestep=_CONTROL_TIMESTEP, time_limit=_DEFAULT_TIME_LIMIT)
