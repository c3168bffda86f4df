"""Ball-in-Cup: catch (dm_control `ball_in_cup`).

A JAX port of `dm_control.suite.ball_in_cup.BallInCup` on dm_control's own
`ball_in_cup.xml` (2 ms physics steps, 10 per 20 ms control step, 20 s = 1,000
steps). The episode starts with the cup at rest and the ball at x ~ U(-.2, .2),
z ~ U(.2, .5) (joint offsets), redrawn until nothing touches: dm_control loops
while `ncon > 0` after `mj_forward`; here a `lax.while_loop` redraws with
`fold_in(key, attempt)` while any MJX contact has `dist` below the pair's
margin, MuJoCo C's rule for generating a contact (see `_penetrating`).
Observation: `position` = qpos, `velocity` = qvel. Reward (sparse): 1 when the
ball centre lies inside the cup's target box shrunk by the ball radius (in x
and z), else 0. The only model edit is the `energy` flag.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from dmcr_jax._mjx import mjx  # mujoco.mjx, quietly

from dmcr_jax.models import names
from dmcr_jax.models.base import TaskSpec

_DEFAULT_TIME_LIMIT = 20.0
_CONTROL_TIMESTEP = .02


def _penetrating(m, d) -> jax.Array:
  """dm_control's `physics.data.ncon > 0` after `mj_forward`, from MJX contacts.

  MJX keeps every candidate geom pair in fixed-size arrays; MuJoCo C emits a
  contact when its distance is below the margin, `max` of the two geoms'
  margins (MJX's `includemargin` is their sum; the DMCR models have no margins,
  pairs or gaps, so both are 0).
  """
  d = mjx.collision(m, mjx.kinematics(m, d))
  contact = d._impl.contact  # pylint: disable=protected-access
  if contact.dist.size == 0:
    return jnp.zeros((), bool)
  margin = jnp.max(jnp.asarray(m.geom_margin)[contact.geom], axis=-1)
  return jnp.any(contact.dist < margin)


def rejection_sample(key, m, d, draw):
  """Redraws `qpos = draw(fold_in(key, attempt), qpos)` until nothing penetrates."""
  def body(carry):
    attempt, _ = carry
    qpos = draw(jax.random.fold_in(key, attempt), d.qpos)
    return attempt + 1, qpos

  def cond(carry):
    attempt, qpos = carry
    return (attempt == 0) | _penetrating(m, d.replace(qpos=qpos))

  _, qpos = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), d.qpos))
  return d.replace(qpos=qpos)


def _draw_ball(key, m, qpos):
  kx, kz = jax.random.split(key)
  qpos = qpos.at[names.qpos_adr(m, "ball_x")].set(
      jax.random.uniform(kx, (), minval=-.2, maxval=.2))
  return qpos.at[names.qpos_adr(m, "ball_z")].set(
      jax.random.uniform(kz, (), minval=.2, maxval=.5))


def _initialize(key, m, d):
  return rejection_sample(key, m, d, lambda k, q: _draw_ball(k, m, q)), {}


def _observation(m, d, info):
  del m, info
  return {"position": d.qpos, "velocity": d.qvel}


def _reward(m, d, info):
  del info
  target = d.site_xpos[names.site_id(m, "target")]
  ball = d.xpos[names.body_id(m, "ball")]
  ball_to_target = jnp.abs((target - ball)[jnp.array([0, 2])])
  target_size = m.site_size[
      names.site_id(m, "target")][[0, 2]]
  ball_size = m.geom_size[names.geom_id(m, "ball"), 0]
  return jnp.all(ball_to_target < target_size - ball_size).astype(jnp.float32)


TASKS = {
    "catch": TaskSpec(
        domain="ball_in_cup", task="catch", initialize=_initialize,
        observation=_observation, reward=_reward,
        control_timestep=_CONTROL_TIMESTEP, time_limit=_DEFAULT_TIME_LIMIT),
}
