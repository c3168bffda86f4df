"""Finger: spin, turn_easy, turn_hard (dm_control `finger`).

A JAX port of `dm_control.suite.finger.Spin` and `Turn` on dm_control's own
`finger.xml` (elliptic cones, 0.01 s physics step, 2 substeps per 0.02 s control
step, 20 s = 1,000 steps). Every episode draws the joints with dm_control's
randomizer (finger joints uniform in their ranges, the spinner hinge in [-π, π]),
redrawn in a `lax.while_loop` (at most 1,000 tries, as dm_control) until MJX's
collision pass finds no penetrating contact. Turn first draws a target angle
U(-π, π) and puts the world-attached `target` site on the circle of radius
`cap1` size-sum around the hinge anchor; its `site_pos` and `site_size`
(.07 easy, .03 hard) are model variables in `info`, and since MJX's `target`
framepos sensor reads the model's default site, the target observation is
computed from `info` (world site position = `site_pos`). Spin hides the `target`
and `tip` sites (alpha 0, visual `site_rgba` variables) and sets the spinner's
hinge damping to .03, a constant that dm_control writes into the model every
episode; we write it once in the compiled model (Spin's `model_edit`). All other
observations are dm_control's sensor readings; `touch` = log1p of the two
acceleration-stage touch sensors. Rewards are dm_control's sparse indicators
(hinge velocity ≤ -15 rad/s; tip inside the target sphere).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from dmcr_jax._mjx import mjx  # mujoco.mjx, quietly

from dmcr_jax.models import names, randomizers
from dmcr_jax.models.base import TaskSpec

_TIME_LIMIT = 20.0
_CONTROL_TIMESTEP = .02
_EASY_TARGET_SIZE = 0.07
_HARD_TARGET_SIZE = 0.03
_SPIN_VELOCITY = 15.0
_SPIN_HINGE_DAMPING = .03
_MAX_ATTEMPTS = 1000

_TARGET_POS = "site_pos:target"
_TARGET_SIZE = "site_size:target"


# Model lookups ----------------------------------------------------------------

def _read(m, d, *sensors: str) -> jax.Array:
  """`sensordata` of the named sensors, concatenated (dm_control's named read)."""
  return d.sensordata[np.concatenate([names.sensor_indices(m, n) for n in sensors])]


# Initial state ----------------------------------------------------------------

def _has_contact(m, d) -> jax.Array:
  """Whether MuJoCo would report `ncon > 0` (finger.xml has zero margins)."""
  d = mjx.collision(m, mjx.kinematics(m, d))
  return jnp.any(d._impl.contact.dist < 0)  # pylint: disable=protected-access


def _random_collision_free_qpos(key, m, d) -> jax.Array:
  """dm_control's `_set_random_joint_angles` as a bounded rejection loop."""

  def draw(i):
    qpos = randomizers.randomize_limited_and_rotational_joints(
        jax.random.fold_in(key, i), m, d.qpos)
    return qpos, _has_contact(m, d.replace(qpos=qpos))

  def cond(carry):
    i, _, hit = carry
    return hit & (i < _MAX_ATTEMPTS)

  def body(carry):
    i, _, _ = carry
    return (i + 1, *draw(i + 1))

  _, qpos, _ = jax.lax.while_loop(cond, body, (0, *draw(0)))
  return qpos


@functools.cache
def _site_rgba(name: str) -> np.ndarray:
  """A site's compiled `site_rgba` (MJX models do not carry this visual field)."""
  return np.array(names.suite_model("finger").site(name).rgba, np.float32)


def _initialize_spin(key, m, d):
  info = {}
  for name in ("target", "tip"):  # hidden: alpha 0, as dm_control
    info[f"site_rgba:{name}"] = jnp.asarray(_site_rgba(name)).at[3].set(0.)
  return d.replace(qpos=_random_collision_free_qpos(key, m, d)), info


def _initialize_turn(key, m, d, target_radius: float):
  k_angle, k_joints = jax.random.split(key)
  target_angle = jax.random.uniform(k_angle, minval=-jnp.pi, maxval=jnp.pi)
  hinge = names.joint_id(m, "hinge")
  anchor = mjx.kinematics(m, d).xanchor[hinge]  # fixed: the spinner is welded
  radius = jnp.asarray(m.geom_size)[names.geom_id(m, "cap1")].sum()
  target = names.site_id(m, "target")
  pos = jnp.asarray(m.site_pos)[target].at[0].set(anchor[0] + radius * jnp.sin(target_angle))
  pos = pos.at[2].set(anchor[2] + radius * jnp.cos(target_angle))
  size = jnp.asarray(m.site_size)[target].at[0].set(target_radius)
  info = {_TARGET_POS: pos.astype(jnp.float32), _TARGET_SIZE: size.astype(jnp.float32)}
  return d.replace(qpos=_random_collision_free_qpos(k_joints, m, d)), info


def _spin_model(model: mujoco.MjModel) -> None:
  """Spin's constant model edit: the hinge damping dm_control sets each episode."""
  hinge = names.joint_id(model, "hinge")
  model.dof_damping[model.jnt_dofadr[hinge]] = _SPIN_HINGE_DAMPING


# Observation and reward -------------------------------------------------------

def _xz(v):
  return v[jnp.array([0, 2])]


def _tip_position(m, d):
  return _xz(_read(m, d, "tip")) - _xz(_read(m, d, "spinner"))


def _target_position(m, d, info):
  # The target site hangs on the world body: its world position is `site_pos`.
  return _xz(info[_TARGET_POS]) - _xz(_read(m, d, "spinner"))


def _dist_to_target(m, d, info):
  to_target = _target_position(m, d, info) - _tip_position(m, d)
  return jnp.linalg.norm(to_target) - info[_TARGET_SIZE][0]


def _observation(m, d, info, turn: bool):
  obs = {
      "position": jnp.concatenate([_read(m, d, "proximal", "distal"),
                                   _tip_position(m, d)]),
      "velocity": _read(m, d, "proximal_velocity", "distal_velocity",
                        "hinge_velocity"),
      "touch": jnp.log1p(_read(m, d, "touchtop", "touchbottom")),
  }
  if turn:
    obs["target_position"] = _target_position(m, d, info)
    obs["dist_to_target"] = _dist_to_target(m, d, info)
  return obs


def _reward_spin(m, d, info):
  del info
  return jnp.where(_read(m, d, "hinge_velocity")[0] <= -_SPIN_VELOCITY, 1.0, 0.0)


def _reward_turn(m, d, info):
  return jnp.where(_dist_to_target(m, d, info) <= 0, 1.0, 0.0)


def _turn(task: str, target_radius: float) -> TaskSpec:
  return TaskSpec(
      domain="finger", task=task,
      initialize=functools.partial(_initialize_turn, target_radius=target_radius),
      observation=functools.partial(_observation, turn=True),
      reward=_reward_turn,
      control_timestep=_CONTROL_TIMESTEP, time_limit=_TIME_LIMIT,
      model_variables=(("site_pos", "target"), ("site_size", "target")))


TASKS = {
    "spin": TaskSpec(
        domain="finger", task="spin", initialize=_initialize_spin,
        observation=functools.partial(_observation, turn=False),
        reward=_reward_spin,
        control_timestep=_CONTROL_TIMESTEP, time_limit=_TIME_LIMIT,
        model_variables=(("site_rgba", "target"), ("site_rgba", "tip")),
        model_edit=_spin_model),
    "turn_easy": _turn("turn_easy", _EASY_TARGET_SIZE),
    "turn_hard": _turn("turn_hard", _HARD_TARGET_SIZE),
}
