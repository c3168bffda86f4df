"""Render model: physics untouched, seed-0 pixel parity, deterministic frames, dmcr-show.

Uses a small bank (a few procedural textures) so GL contexts start fast; the
full bank differs only in how many textures and materials are appended.
"""

import copy
import hashlib

import jax
import mujoco
import numpy as np
import pytest
from dm_control import suite
from mujoco import mjx

from dmcr_jax import visuals as V
from dmcr_jax.visuals import render_model as RM
from dmcr_jax.visuals import show
from dmcr_jax.visuals.moving import check_moving, look_at
from dmcr_jax.models.names import suite_model
from dmcr_jax.visuals import textures as T
from tests.banks import procedural_bank

TASKS = {"ball_in_cup": "catch", "cartpole": "swingup", "cheetah": "run",
         "finger": "spin", "fish": "swim", "hopper": "hop", "humanoid": "walk",
         "pendulum": "swingup", "reacher": "easy", "walker": "walk"}
H, W = 64, 80


@pytest.fixture(scope="module")
def bank():
  floors = [0, 3, 7, 10]                       # grass, gravel, brick, leaves
  skies = [0, 1, 2]
  return procedural_bank(floors, skies, "test-bank")


def dm_reference(domain, seed=1):
  env = suite.load(domain, TASKS[domain], task_kwargs={"random": seed})
  env.reset()
  ph = env.physics
  ref = ph.render(H, W, camera_id=0)
  qpos, variables = show.physics_state(ph, domain)
  ph.free()
  return ref, qpos, variables


def frame_hash(img):
  return hashlib.sha256(img.tobytes()).hexdigest()[:16]


@pytest.mark.parametrize("domain", V.DOMAINS)
def test_layout_and_additions_are_visual_only(domain, bank):
  rm = V.build_render_model(domain, bank)
  m, base = rm.model, suite_model(domain)
  for f in ("nq", "nv", "nu", "na", "nbody", "njnt", "ngeom", "nsite", "ncam", "nlight"):
    assert getattr(m, f) == getattr(base, f), f
  for f in ("jnt_qposadr", "jnt_dofadr", "jnt_type", "body_parentid", "geom_type",
            "geom_contype", "geom_conaffinity", "dof_damping", "body_mass", "opt.timestep"):
    a, b = (m.opt.timestep, base.opt.timestep) if f == "opt.timestep" else (
        getattr(m, f), getattr(base, f))
    np.testing.assert_array_equal(a, b, err_msg=f)
  names = lambda mm: [mujoco.mj_id2name(mm, mujoco.mjtObj.mjOBJ_JOINT, i) for i in range(mm.njnt)]
  assert names(m) == names(base)
  assert m.ntex == base.ntex + bank.num_floors + bank.num_backgrounds
  assert m.nmat == base.nmat + bank.num_floors
  np.testing.assert_array_equal(m.tex_data[m.tex_adr[rm.floor_mat0 - base.nmat + base.ntex]:][:9],
                                bank.floors[0].reshape(-1)[:9])


@pytest.mark.parametrize("domain", V.DOMAINS)
def test_mujoco_dynamics_unchanged_by_looks(domain, bank):
  """Stepping the render model with any look, static or moving, gives dm_control's
  trajectory bit for bit."""
  rm = copy.copy(V.build_render_model(domain, bank))
  base = suite_model(domain)
  looks = RM.prepare(rm, rm.sample([1, 2, 3], "all"))
  rng = np.random.default_rng(0)
  ctrl = rng.uniform(-1, 1, (25, base.nu))
  d0 = mujoco.MjData(base)
  for _ in range(25):
    d0.ctrl[:] = ctrl[_]
    mujoco.mj_step(base, d0)
  for i in range(len(looks)):
    RM.apply(rm, looks, i, context=None) if looks.skybox_tex[i] == rm.sky_tex else None
    RM.apply(rm, RM.Looks(**{**looks.__dict__, "skybox_tex": np.full(3, rm.sky_tex)}), i)
    d = mujoco.MjData(rm.model)
    for t in range(25):
      d.ctrl[:] = ctrl[t]
      mujoco.mj_step(rm.model, d)
    np.testing.assert_array_equal(d.qpos, d0.qpos)
    np.testing.assert_array_equal(d.qvel, d0.qvel)
    np.testing.assert_array_equal(d.act, d0.act)
  # Looks that move (every factor the domain has, a new look before every step).
  moving, _ = check_moving(domain, "all")
  params = rm.sample([1, 2, 3], "all")
  steps = np.tile(np.arange(25), 3)
  moved = RM.prepare(rm, look_at(params.take(np.repeat(np.arange(3), 25)), steps, moving,
                                 0.3, num_backgrounds=bank.num_backgrounds))
  assert len(np.unique(moved.cam_pos, axis=0)) == 75
  for i in range(3):
    d = mujoco.MjData(rm.model)
    for t in range(25):
      RM.apply(rm, RM.Looks(**{**moved.__dict__, "skybox_tex": np.full(75, rm.sky_tex)}),
               i * 25 + t)
      d.ctrl[:] = ctrl[t]
      mujoco.mj_step(rm.model, d)
    np.testing.assert_array_equal(d.qpos, d0.qpos)
    np.testing.assert_array_equal(d.qvel, d0.qvel)
    np.testing.assert_array_equal(d.act, d0.act)


@pytest.mark.slow
def test_mjx_trajectories_identical_for_any_look(bank):
  """MJX steps the physics model and render models with different looks identically."""
  from dmcr_jax import models
  task = models.load("cartpole-swingup")

  def mjx_model(rm, index):
    m = copy.copy(rm.model)
    m.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    looks = RM.prepare(rm, rm.sample([index], "all"))
    looks.skybox_tex[:] = rm.sky_tex             # the skybox lives in the GL context
    RM.apply(dataclass_with_model(rm, m), looks, 0)
    return mjx.put_model(m)

  def dataclass_with_model(rm, m):
    out = copy.copy(rm)
    out.model = m
    return out

  @jax.jit
  def rollout(m, qpos, qvel, ctrl):
    d = mjx.make_data(m).replace(qpos=qpos, qvel=qvel)
    def step(d, u):
      d = mjx.step(m, d.replace(ctrl=u))
      return d, (d.qpos, d.qvel)
    return jax.lax.scan(step, d, ctrl)[1]

  key = jax.random.key(0)
  state = jax.jit(task.reset)(key)  # eager MJX runs op by op: far slower
  ctrl = jax.random.uniform(jax.random.key(1), (30, task.action_size), minval=-1, maxval=1)
  ref = rollout(task.mjx_model, state.data.qpos, state.data.qvel, ctrl)
  # A varied look of the whole bank, and one of a subset of it.
  small = bank.subset([1], [2])
  for rm, idx in ((V.build_render_model("cartpole", bank), 1),
                  (V.build_render_model("cartpole", small), 3)):
    out = rollout(mjx_model(rm, idx), state.data.qpos, state.data.qvel, ctrl)
    for a, b in zip(out, ref):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("domain", V.DOMAINS)
def test_seed_zero_matches_dm_control_pixels(domain, bank):
  rm = V.build_render_model(domain, bank)
  ref, qpos, variables = dm_reference(domain)
  with RM.FrameRenderer(rm, H, W) as fr:
    zero = fr.render(rm.sample([0]), qpos, model_variables=variables)
    # Any seed with every factor off is the default look too ...
    off = fr.render(rm.sample([5, 9], "none"), qpos, index=1, model_variables=variables)
    # ... and after drawing a varied look, seed 0 is still exact (no leftovers).
    varied = fr.render(rm.sample([3], "all"), qpos, model_variables=variables)
    again = fr.render(rm.sample([0]), qpos, model_variables=variables)
  for img in (zero, off, again):
    diff = np.abs(img.astype(int) - ref.astype(int))
    assert diff.max() <= 2 and diff.mean() <= 0.1, (diff.max(), diff.mean())
  assert np.abs(varied.astype(int) - ref.astype(int)).mean() > 5


def test_a_renderer_leaves_no_model_variables_in_the_shared_model(bank):
  """Renderers of one domain share its cached render model: the task variables one
  draws (finger-spin hides the target) do not stay in it for the next, closed or
  not (finger-turn_easy's target is still drawn as dm_control draws it)."""
  rm = V.build_render_model("finger", bank)

  def dm(task):
    env = suite.load("finger", task, task_kwargs={"random": 1})
    env.reset()
    ref = env.physics.render(H, W, camera_id=0)
    state = show.physics_state(env.physics, "finger")
    env.physics.free()
    return ref, state

  _, (q_spin, v_spin) = dm("spin")
  ref, (q_turn, v_turn) = dm("turn_easy")
  assert set(v_spin) - set(v_turn)             # spin writes variables turn_easy leaves
  with RM.FrameRenderer(rm, H, W) as spin:
    spin.render(rm.sample([0]), q_spin, model_variables=v_spin)
    with RM.FrameRenderer(rm, H, W) as turn:     # while the other is open
      open_img = turn.render(rm.sample([0]), q_turn, model_variables=v_turn)
  with RM.FrameRenderer(rm, H, W) as turn:       # after it closed
    closed_img = turn.render(rm.sample([0]), q_turn, model_variables=v_turn)
  for img in (open_img, closed_img):
    diff = np.abs(img.astype(int) - ref.astype(int))
    assert diff.max() <= 2 and diff.mean() <= 0.1, (diff.max(), diff.mean())


def test_rendered_frames_are_deterministic(bank):
  rm = V.build_render_model("walker", bank)
  _, qpos, _ = dm_reference("walker")
  looks = RM.prepare(rm, rm.sample([1, 2, 3, 4], "all"))
  with RM.FrameRenderer(rm, H, W) as fr:
    first = [frame_hash(fr.render(looks, qpos, index=i)) for i in range(4)]
    fr.render(rm.sample([0]), qpos)
    backwards = [frame_hash(fr.render(looks, qpos, index=i)) for i in (3, 2, 1, 0)][::-1]
  with RM.FrameRenderer(rm, H, W) as fr:
    fresh = [frame_hash(fr.render(looks, qpos, index=i)) for i in range(4)]
  assert first == backwards == fresh
  assert len(set(first)) == 4


@pytest.mark.parametrize("domain, factors", [
    ("cheetah", ("camera", "light", "body", "floor", "background", "reflectance")),
    ("reacher", ("target",)),
])
def test_each_factor_changes_the_frame(domain, factors, bank):
  rm = V.build_render_model(domain, bank)
  ref, qpos, variables = dm_reference(domain)
  with RM.FrameRenderer(rm, H, W) as fr:
    for f in factors:
      seeds = [1, 2, 3, 4]
      p = rm.sample(seeds, [f])
      changed = [np.abs(fr.render(p, qpos, index=i, model_variables=variables).astype(int)
                        - ref).sum() for i in range(len(seeds))]
      assert max(changed) > 0, f


def test_background_is_chosen_in_the_context(bank):
  rm = V.build_render_model("cartpole", bank)
  p = rm.sample(range(1, 40), "background")
  i = int(np.nonzero(np.asarray(p.background_id) == 2)[0][0])
  looks = RM.prepare(rm, p)
  assert looks.skybox_tex[i] == rm.bg_tex0 + 2
  with pytest.raises(ValueError, match="context"):
    RM.apply(rm, looks, i)
  with RM.FrameRenderer(rm, H, W) as fr:
    img = fr.render(looks, mujoco.MjData(rm.model).qpos, index=i)
    tt = fr.context.textureType
    assert tt[rm.bg_tex0 + 2] == mujoco.mjtTexture.mjTEXTURE_SKYBOX
    assert tt[rm.sky_tex] == mujoco.mjtTexture.mjTEXTURE_CUBE
  assert img[:10].std() > 0 or img[:10].mean() > 0


def test_apply_rejects_mismatched_params(bank):
  rm = V.build_render_model("walker", bank)
  with pytest.raises(ValueError, match="domain"):
    RM.prepare(rm, V.sample("cheetah", [1]))
  with pytest.raises(ValueError, match="bank"):
    RM.prepare(rm, V.sample("walker", range(1, 50), "floor"))     # ids up to 319


def test_show_grid_first_tile_is_dm_control(tmp_path, monkeypatch):
  import imageio.v3 as iio
  monkeypatch.setattr(T, "_BANK_CACHE", {})
  for sub, n in (("floors", 2), ("skies", 2)):
    (tmp_path / sub).mkdir()
    for k in range(n):
      iio.imwrite(tmp_path / sub / f"{k}.png", np.full((16, 16, 3), 60 * (k + 1), np.uint8))
  size = 48
  grid = show.render_grid("cartpole-balance", [0, 1, 2], "all", size=size, cols=3,
                          floor_dir=str(tmp_path / "floors"),
                          background_dir=str(tmp_path / "skies"), pad=2)
  assert grid.shape == (size + 4, 3 * (size + 2) + 2, 3)
  env = suite.load("cartpole", "balance", task_kwargs={"random": 0})
  env.reset()
  ref = env.physics.render(size, size, camera_id=0)
  env.physics.free()
  tile = lambda k: grid[2:2 + size, 2 + k * (size + 2):2 + k * (size + 2) + size]
  assert np.abs(tile(0).astype(int) - ref).max() <= 2
  assert np.abs(tile(1).astype(int) - ref).mean() > 5
  assert show.parse_seeds("0-3,7, 9") == [0, 1, 2, 3, 7, 9]
  for bad in ("", "3-1", "a", "-2", "2147483648"):
    with pytest.raises(ValueError):
      show.parse_seeds(bad)
