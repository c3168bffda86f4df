"""The fish MJX fix leaves dm_control's dynamics unchanged; MJX's fluid forces match.

`dmcr_jax.models.fish.disable_collisions` clears every geom's collision masks
so that `mjx.put_model` accepts fish.xml (MJX has no ellipsoid–box collision).
These tests prove, on dm_control's own environment (MuJoCo C, float64), that
the edit changes nothing: fish.xml disables constraints, MuJoCo then skips
collision detection altogether, and episodes with and without the edit (same
seed, same random actions) are bitwise identical. The last test checks that
MJX's passive forces (joint and tendon springs, dampers and the inertia-box
fluid model of `density=5000`) match MuJoCo's on dm_control states.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from dm_control import suite
from mujoco import mjx

from dmcr_jax.models import fish

EPISODES = 2
STEPS = 200  # control steps per episode (10 physics steps each)


def _compiled_model() -> mujoco.MjModel:
  return mujoco.MjModel.from_xml_string(*suite.fish.get_model_and_assets())


def _rollout(task: str, edit: bool, seed: int = 0) -> dict:
  """Physics state, contacts, observations and rewards of random-action episodes."""
  env = suite.load("fish", task, task_kwargs={"random": seed})
  if edit:
    fish.TASKS[task].model_edit(env.physics.model.ptr)  # in place
  spec = env.action_spec()
  rng = np.random.RandomState(seed)
  rec = {k: [] for k in ("qpos", "qvel", "act", "qacc", "sensordata",
                         "qfrc_passive", "time", "ncon", "obs", "reward")}
  for _ in range(EPISODES):
    ts = env.reset()
    rec["obs"].append(np.concatenate([np.ravel(v) for v in ts.observation.values()]))
    for _ in range(STEPS):
      ts = env.step(rng.uniform(spec.minimum, spec.maximum))
      d = env.physics.data
      for k in ("qpos", "qvel", "act", "qacc", "sensordata", "qfrc_passive"):
        rec[k].append(np.array(getattr(d, k)))
      rec["time"].append(d.time)
      rec["ncon"].append(d.ncon)
      rec["obs"].append(np.concatenate([np.ravel(v) for v in ts.observation.values()]))
      rec["reward"].append(ts.reward)
  return {k: np.asarray(v) for k, v in rec.items()}


def test_fish_disables_constraints_so_mujoco_never_collides():
  m = _compiled_model()
  assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
  d = mujoco.MjData(m)
  d.qpos[2] = 0.  # torso centre on the ground plane: the fish interpenetrates it
  mujoco.mj_forward(m, d)
  assert d.ncon == 0
  m.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
  mujoco.mj_forward(m, d)
  assert d.ncon > 0  # the same state does collide once constraints are on


def test_mjx_needs_the_fix_and_accepts_it():
  m = _compiled_model()
  with pytest.raises(NotImplementedError, match="ELLIPSOID.*BOX"):
    mjx.put_model(m)
  fish.disable_collisions(m)
  mjx.put_model(m)


@pytest.mark.parametrize("task", ["upright", "swim"])
def test_fix_leaves_dm_control_bitwise_unchanged(task):
  assert fish.TASKS[task].model_edit is fish.disable_collisions
  ref = _rollout(task, edit=False)
  fixed = _rollout(task, edit=True)
  assert ref["reward"].shape == (EPISODES * STEPS,)
  assert not ref["ncon"].any()
  assert np.ptp(ref["qpos"], axis=0).max() > .1  # the fish does move
  for k in ref:
    np.testing.assert_array_equal(fixed[k], ref[k], err_msg=k)


def test_mjx_passive_and_fluid_forces_match_mujoco():
  """MJX (float32) qfrc_passive and qacc vs MuJoCo (float64) on 100 states.

  Measured: 2.2e-5 of each dof's largest magnitude in float32 (9e-14 with
  float64 MJX, i.e. MJX's inertia-box fluid model is MuJoCo's).
  """
  m = _compiled_model()
  fish.disable_collisions(m)
  env = suite.load("fish", "swim", task_kwargs={"random": 1})
  spec = env.action_spec()
  rng = np.random.RandomState(1)
  env.reset()
  states = []
  for t in range(500):
    env.step(rng.uniform(spec.minimum, spec.maximum))
    if t % 5 == 4:
      d = env.physics.data
      states.append((d.qpos.copy(), d.qvel.copy(), d.ctrl.copy()))
  qpos, qvel, ctrl = (np.stack(x) for x in zip(*states))

  ref_passive, ref_qacc, ref_fluid = [], [], []
  d = mujoco.MjData(m)
  for q, v, c in zip(qpos, qvel, ctrl):
    d.qpos, d.qvel, d.ctrl = q, v, c
    mujoco.mj_forward(m, d)
    ref_passive.append(d.qfrc_passive.copy())
    ref_fluid.append(d.qfrc_fluid.copy())
    ref_qacc.append(d.qacc.copy())
  ref_passive, ref_qacc, ref_fluid = map(np.stack, (ref_passive, ref_qacc, ref_fluid))
  assert np.abs(ref_fluid).max() > .1 * np.abs(ref_passive).max()  # fluid matters

  mx = mjx.put_model(m)
  f32 = lambda x: jnp.asarray(x, jnp.float32)

  @jax.jit
  @jax.vmap
  def forward(q, v, c):
    return mjx.forward(mx, mjx.make_data(mx).replace(qpos=q, qvel=v, ctrl=c))

  out = forward(f32(qpos), f32(qvel), f32(ctrl))
  for name, got, ref in (("qfrc_passive", out.qfrc_passive, ref_passive),
                         ("qacc", out.qacc, ref_qacc)):
    err = np.abs(np.asarray(got, np.float64) - ref)
    scale = np.abs(ref).max(axis=0)  # per dof
    # float32 rounding: relative to each dof's largest magnitude.
    assert (err.max(axis=0) <= 1e-4 * scale + 1e-12).all(), (
        name, err.max(axis=0) / scale)
