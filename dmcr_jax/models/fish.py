"""Fish: upright, swim (dm_control `fish`).

A JAX port of `dm_control.suite.fish.Upright` and `Swim` on dm_control's own
`fish.xml` (0.004 s physics steps, 0.04 s control steps = 10 substeps,
40 s = 1,000 control steps, gravity off, fluid density 5000). Each episode
draws the root orientation as `normalize(N(0, 1)^4)` and the seven tail and fin
joints uniformly in [-.2, .2]; the root position stays at its default. Swim
also draws the target geom's position (x, y ~ U(-.4, .4), z ~ U(.1, .3)), a
model variable `geom_pos:target` in `info`; the target hangs on the world body,
so its world position is its `geom_pos`. Upright hides the target as dm_control
does (alpha 0: the visual model variable `geom_rgba:target`).
Observation: `joint_angles` (the seven joints' qpos), `upright` (torso zz),
swim's `target` (mouth → target in the mouth's frame), `velocity` = qvel.
Reward: upright = tolerance(zz, (1, 1), margin 1); swim = (7 · tolerance of the
mouth–target distance within the sum of their radii, margin twice that, +
(zz + 1) / 2) / 8.

The MJX fix (`model_edit`, shared by both tasks): every geom's `contype` and
`conaffinity` are set to 0. `mjx.put_model` rejects fish.xml as is: one of
its 31 candidate geom pairs, tail2 (ellipsoid) – torso_massive (box), has no
MJX collision function. Contacts can never reach the dynamics in
dm_control: fish.xml sets `<flag constraint="disable"/>`
(`mjDSBL_CONSTRAINT`), with which MuJoCo's `mj_collision` returns before any
collision check, so `ncon` is always 0 (even with the fish sunk into the
ground; with the flag cleared the same state gives 13 contacts). Zeroing the
collision masks therefore leaves MuJoCo's result exactly unchanged, contact
list included (empty in both), and gives MJX no pair to check: its contact
list is empty too, as MuJoCo's (zeroing only the box would leave MJX 30 pairs
to collide each substep, and contacts MuJoCo never reports).
`tests/test_fish_fix.py` proves it on dm_control's own environment (MuJoCo C,
float64): for each task, 2 episodes × 200 control steps with random actions,
unmodified vs. this edit applied in place, give bitwise-identical qpos, qvel,
act, qacc, qfrc_passive, sensordata, time, ncon (0), observations and rewards
(max difference 0.0).

Fluid forces: fish.xml uses the global inertia-box fluid model (`density`
5000, `viscosity` 0, `wind` 0; no geom sets `fluidshape`, so `geom_fluid` is
all zero), which MJX implements (`passive._fluid`, enabled because density >
0); MJX lacks only the per-geom ellipsoid fluid model, which fish does not use.
On 100 dm_control states, MJX's `qfrc_passive` (springs, dampers, fluid) and
`qacc` match MuJoCo's to 9e-14 relative in float64 and 2.2e-5 in float32
(checked in `tests/test_fish_fix.py`): MJX ignores none of fish.xml's
dynamics.

Against dm_control, float64 MJX follows full swim episodes to rounding, so the
physics is dm_control's and float32 MJX's drift is float32 rounding; state and
trajectory parity are tested in `tests/test_models.py`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dmcr_jax.models import names
from dmcr_jax.models.base import TaskSpec
from dmcr_jax.models.rewards import tolerance

_DEFAULT_TIME_LIMIT = 40
_CONTROL_TIMESTEP = .04
_JOINTS = ("tail1", "tail_twist", "tail2", "finright_roll", "finright_pitch",
           "finleft_roll", "finleft_pitch")
_JOINT_RANGE = .2

_TARGET_POS = "geom_pos:target"
_TARGET_RGBA = "geom_rgba:target"


# Model lookups ----------------------------------------------------------------

def _joint_qpos(m) -> np.ndarray:
  """Static `qpos` addresses of the seven tail and fin joints, in `_JOINTS` order."""
  return np.array([names.qpos_adr(m, j) for j in _JOINTS])


def disable_collisions(model: mujoco.MjModel) -> None:
  """The MJX fix: no geom collides (contacts are disabled by fish.xml anyway).

  fish.xml disables constraints, so MuJoCo never runs collision detection for
  it; clearing every geom's `contype`/`conaffinity` leaves its dynamics
  bitwise unchanged and removes the ellipsoid pairs MJX cannot collide.
  """
  model.geom_contype[:] = 0
  model.geom_conaffinity[:] = 0


# Initial state ----------------------------------------------------------------

def _random_pose(key, m, qpos):
  """Root orientation normalize(N(0,1)^4), joints U(-.2, .2), as dm_control."""
  k_quat, k_joints = jax.random.split(key)
  quat = jax.random.normal(k_quat, (4,))
  root = names.qpos_adr(m, "root")
  qpos = qpos.at[root + 3:root + 7].set(quat / jnp.linalg.norm(quat))
  angles = jax.random.uniform(k_joints, (len(_JOINTS),), minval=-_JOINT_RANGE,
                              maxval=_JOINT_RANGE)
  return qpos.at[_joint_qpos(m)].set(angles)


def _initialize_upright(key, m, d):
  rgba = jnp.asarray(m.geom_rgba)[names.geom_id(m, "target")].at[3].set(0.)  # hidden
  info = {_TARGET_RGBA: rgba.astype(jnp.float32)}
  return d.replace(qpos=_random_pose(key, m, d.qpos)), info


def _initialize_swim(key, m, d):
  k_pose, k_target = jax.random.split(key)
  target = jax.random.uniform(k_target, (3,), minval=jnp.array([-.4, -.4, .1]),
                              maxval=jnp.array([.4, .4, .3]))
  info = {_TARGET_POS: target.astype(jnp.float32)}
  return d.replace(qpos=_random_pose(k_pose, m, d.qpos)), info


# Observation and reward -------------------------------------------------------

def _upright(m, d):
  """Projection of the torso's z-axis on the world's z-axis."""
  return d.xmat[names.body_id(m, "torso"), 2, 2]


def _mouth_to_target(m, d, info):
  """The mouth → target vector in the mouth geom's frame."""
  mouth = names.geom_id(m, "mouth")
  # The target geom is attached to the world body: world position = geom_pos.
  to_target = info[_TARGET_POS] - d.geom_xpos[mouth]
  return to_target @ d.geom_xmat[mouth]


def _observation(m, d, info, swim: bool):
  obs = {"joint_angles": d.qpos[_joint_qpos(m)], "upright": _upright(m, d)}
  if swim:
    obs["target"] = _mouth_to_target(m, d, info)
  obs["velocity"] = d.qvel
  return obs


def _reward_upright(m, d, info):
  del info
  return tolerance(_upright(m, d), bounds=(1., 1.), margin=1.)


def _reward_swim(m, d, info):
  # Constant sizes (dm_control never changes them): static tolerance bounds.
  size = np.asarray(m.geom_size)
  radii = float(size[names.geom_id(m, "mouth"), 0] + size[names.geom_id(m, "target"), 0])
  in_target = tolerance(jnp.linalg.norm(_mouth_to_target(m, d, info)),
                        bounds=(0., radii), margin=2 * radii)
  is_upright = 0.5 * (_upright(m, d) + 1)
  return (7 * in_target + is_upright) / 8


TASKS = {
    "upright": TaskSpec(
        domain="fish", task="upright", initialize=_initialize_upright,
        observation=functools.partial(_observation, swim=False),
        reward=_reward_upright,
        control_timestep=_CONTROL_TIMESTEP, time_limit=_DEFAULT_TIME_LIMIT,
        model_variables=(("geom_rgba", "target"),),
        model_edit=disable_collisions),
    "swim": TaskSpec(
        domain="fish", task="swim", initialize=_initialize_swim,
        observation=functools.partial(_observation, swim=True),
        reward=_reward_swim,
        control_timestep=_CONTROL_TIMESTEP, time_limit=_DEFAULT_TIME_LIMIT,
        model_variables=(("geom_pos", "target"),),
        model_edit=disable_collisions),
}
