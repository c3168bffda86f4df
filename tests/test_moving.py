"""Moving looks (`visuals.moving`): a function of (seed, step), static at intensity 0,
bounded and smooth, the same per-step looks in the pool and the ray caster, argument
checks before anything is built, and (slow) moving envs with the physics and rewards of
static ones, the pool's frames the reference render of each step's look."""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dmcr_jax
from dmcr_jax import env as env_module
from dmcr_jax import env_pool
from dmcr_jax import jax_env
from dmcr_jax import visuals as V
from dmcr_jax.visuals import jax_render as JR
from dmcr_jax.visuals import jax_render_scene as JS
from dmcr_jax.visuals import moving as M
from dmcr_jax.visuals import render_model as rmod
from tests.banks import procedural_bank

# One worker runs the module, so that its module fixtures (two pool env rollouts) are
# built once and not in each xdist worker that gets one of their tests.
pytestmark = pytest.mark.xdist_group("moving")

ALL = M.MOVING_FACTORS


@pytest.fixture(scope="module")
def pendulum():
  """pendulum's render model and scene with a small bank (3 floors, 3 skies)."""
  bank = procedural_bank((0, 7, 10), (0, 1, 2), "moving-test-bank")
  rm = rmod.build_render_model("pendulum", bank)
  return rm, JS.build_scene(rm)


def _fields(p):
  return {k: np.asarray(v) for k, v in vars(p).items() if isinstance(v, jax.Array)}


def _assert_same(a, b, rtol=0.0, atol=0.0):
  fa, fb = _fields(a), _fields(b)
  assert fa.keys() == fb.keys()
  for k in fa:
    np.testing.assert_allclose(fa[k], fb[k], rtol=rtol, atol=atol, err_msg=k)


@pytest.mark.parametrize("kwargs, message", [
    (dict(moving="camera,sky", intensity=0.2),
     "Unknown moving factor.*'sky'.*camera, light, body, floor, background"),
    (dict(moving="camera", intensity=1.5), r"intensity must be a number in \[0, 1\]"),
    (dict(moving="camera", intensity=-0.1), r"intensity must be a number in \[0, 1\]"),
    (dict(moving="camera", intensity="0.2"), r"intensity must be a number in \[0, 1\]"),
    (dict(task="reacher-easy", moving="background", intensity=0.2),
     "background do.*not apply to reacher.*camera, light, body, floor"),
])
def test_bad_moving_is_refused_before_anything_is_built(kwargs, message, monkeypatch):
  def built(*a, **k):
    raise AssertionError("built something before checking moving/intensity")
  monkeypatch.setattr(dmcr_jax.models, "load", built)
  monkeypatch.setattr(env_pool, "RenderPool", built)
  task = kwargs.pop("task", "walker-walk")
  for renderer in ("pool", "jax"):
    with pytest.raises(ValueError, match=message):
      dmcr_jax.make(task, renderer=renderer, **kwargs)


def test_look_at_is_a_function_of_seed_and_step_with_a_stream_per_factor():
  p = V.sample("cheetah", [3, 0, 3, 9], "all")
  a = M.look_at(p, [5, 5, 5, 6], ALL, 0.2)
  one = M.look_at(p.take(2), [5], ALL, 0.2)               # another batch, same (seed, step)
  _assert_same(a.take(0), one)
  _assert_same(a.take(2), one)
  jitted = jax.jit(lambda p, t: M.look_at(p, t, ALL, 0.2))(p, jnp.array([5, 5, 5, 6]))
  _assert_same(a, jitted, atol=1e-6)
  later = M.look_at(p, [6, 6, 6, 6], ALL, 0.2)
  for name in ("cam_pos", "headlight_diffuse", "body_rgba", "floor_delta", "light_pos"):
    f = np.asarray(getattr(a, name))
    assert not np.array_equal(f[0], f[1]), name                          # seed matters
    assert not np.array_equal(f[0], np.asarray(getattr(later, name))[0]), name  # step too
  # Each factor draws from its own stream: moving one alone moves it as with all.
  for factor, names in (("camera", ("cam_pos", "cam_rot")),
                        ("background", ("background_mix", "background2_id"))):
    alone = M.look_at(p, [5, 5, 5, 6], (factor,), 0.2)
    for name in names:
      np.testing.assert_array_equal(getattr(alone, name), getattr(a, name))
    if factor != "camera":
      np.testing.assert_array_equal(alone.cam_pos, p.cam_pos)


def test_intensity_zero_or_no_factor_is_the_static_look(pendulum):
  p = V.sample("walker", [0, 4], "all")
  assert M.look_at(p, 7, ALL, 0.0) is p and M.look_at(p, 7, (), 0.3) is p
  rm, scene = pendulum
  static = JS.look_maker(scene, rm, "all")(jnp.array([0, 4]))
  zero = JS.look_maker(scene, rm, "all", ALL, 0.0)(jnp.array([0, 4]), jnp.array([3, 3]))
  assert jax.tree.structure(static) == jax.tree.structure(zero)
  for x, y in zip(jax.tree.leaves(static), jax.tree.leaves(zero)):
    np.testing.assert_array_equal(x, y)
  # the pool env's per-step looks at intensity 0: the static ones, so seed 0 is dm_control's
  fake = types.SimpleNamespace(_static_params=None, vary="all", moving=ALL, intensity=0.0,
                               _pool=types.SimpleNamespace(rm=rm))
  looks = rmod.prepare(rm, env_module.PixelVectorEnv.step_params(fake, [0], [40]))
  ref = rmod.prepare(rm, rm.sample([0], vary="none"))
  for k, v in vars(ref).items():
    np.testing.assert_array_equal(getattr(looks, k), v, err_msg=k)


def test_moving_looks_stay_in_range_and_change_smoothly():
  T, I = 800, 0.3
  p = V.sample("cheetah", [0, 11], "all")                   # its light moves
  steps = np.tile(np.arange(T), 2)
  rows = np.repeat(np.arange(2), T)
  base, a = p.take(rows), M.look_at(p.take(rows), steps, ALL, I)
  f = lambda x: np.asarray(x, np.float64).reshape((2, T) + np.shape(x)[1:])
  c = M._consts("cheetah")
  half = c["light_half"]
  checks = {  # name: (largest offset from the static look, largest change per step)
      "cam_rot": (M.MAX_ANGLE * I, M.MAX_ANGLE * I * M.max_step_change("camera")),
      "headlight_diffuse": (I, I * M.max_step_change("light")),
      "body_rgba": (I, I * M.max_step_change("body")),
      "light_pos": (I * half.max(), I * half.max() * M.max_step_change("light")),
  }
  for name, (bound, smooth) in checks.items():
    x, x0 = f(getattr(a, name)), f(getattr(base, name))
    assert np.abs(x - x0).max() <= bound * (1 + 1e-5), name
    step = np.abs(np.diff(x, axis=1)).max()
    assert 0.05 * smooth < step <= smooth * (1 + 1e-4), (name, step, smooth)
  assert np.all((f(a.body_rgba) >= 0) & (f(a.body_rgba) <= 1))
  np.testing.assert_array_equal(f(a.body_rgba)[..., 3], f(base.body_rgba)[..., 3])
  delta = f(a.floor_delta)
  assert np.abs(delta).max() <= I * (1 + 1e-6) and np.abs(np.diff(delta, axis=1)).max() <= (
      I * M.max_step_change("floor") * (1 + 1e-4))
  mix = f(a.background_mix)
  assert mix.min() >= 0 and mix.max() <= I * (1 + 1e-6) and mix.max() > 0.9 * I
  assert np.abs(np.diff(mix, axis=1)).max() <= I * M.max_step_change("background") * 1.0001
  # the second sky changes only where its weight is 0 (a new sky each period)
  sky2 = f(a.background2_id)
  switch = np.diff(sky2, axis=1) != 0
  assert switch.any() and np.all(mix[:, 1:][switch] == 0)
  # the camera orbits the point it looked at: on its new view axis, at a zoomed distance
  d = float(c["distance"])
  for i in range(2):
    for t in (0, 97, 401):
      look = np.asarray(base.cam_pos[i * T + t]) - d * np.asarray(
          M._backward(c["cam_quat"], base.cam_rot[i * T + t]))
      back = np.asarray(M._backward(c["cam_quat"], a.cam_rot[i * T + t]))
      off = np.asarray(a.cam_pos[i * T + t]) - look
      r = np.linalg.norm(off)
      assert (1 - M.ZOOM_IN * I) * d - 1e-5 <= r <= (1 + M.ZOOM_OUT * I) * d + 1e-5
      np.testing.assert_allclose(off / r, back, atol=1e-5)


def test_pool_and_ray_caster_compute_the_same_step_looks(pendulum):
  rm, scene = pendulum
  seeds, steps = np.array([0, 5, 2**30 + 1], np.int32), np.array([0, 37, 250], np.int32)
  fake = types.SimpleNamespace(_static_params=None, vary="all", moving=ALL, intensity=0.3,
                               _pool=types.SimpleNamespace(rm=rm))
  host = env_module.PixelVectorEnv.step_params(fake, seeds, steps)
  maker = JS.look_maker(scene, rm, "all", ALL, 0.3)
  _assert_same(host, jax.jit(lambda m, s, t: m.params(s, t))(maker, seeds, steps), atol=1e-6)
  # and the ray caster's looks equal the pool's prepared looks, put on the device
  want = JS.device_looks(scene, rm, rmod.prepare(rm, host), ALL)
  got = jax_env.make_looks_at(maker, seeds, steps)
  assert jax.tree.structure(want) == jax.tree.structure(got)
  for x, y in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
    np.testing.assert_allclose(x, y, atol=1e-5)


def test_ray_caster_blends_the_skies_and_tints_the_floor(pendulum):
  rm, scene = pendulum
  look = JS.look_maker(scene, rm, "all", ("floor", "background"), 0.6)(
      jnp.array([3]), jnp.array([40])).take(0)
  w = float(look.sky_mix)
  assert 0 < w <= 0.6 and int(look.sky2) != int(look.sky)
  bp = JS.poses(_data(rm))
  _, _, _, rgba = JR._objects(scene, bp, look, None)
  np.testing.assert_array_equal(rgba[scene.floor_obj], look.floor_rgba)
  assert not np.array_equal(look.floor_rgba, scene.rgba[scene.floor_obj])

  @jax.jit
  def sky(scene, lk):
    floats, ints = JR.pack_env(scene, bp, lk)
    reader = JR.ArrayReader(floats, ints, None, scene.skies.reshape(-1))
    L = JR.look_layout(scene, lk)
    d, _ = JR._camera_rays(L, reader, jnp.arange(64), 8, 8, 1)
    return jnp.stack(JR._sky_color(L, reader, d), -1)

  a = sky(scene, look.replace(sky2=None, sky_mix=None))
  b = sky(scene, look.replace(sky=look.sky2, sky2=None, sky_mix=None))
  np.testing.assert_allclose(sky(scene, look), (1 - w) * a + w * b, atol=1e-6)


def _data(rm):
  import mujoco
  d = mujoco.MjData(rm.model)
  mujoco.mj_forward(rm.model, d)
  return d


KW = dict(num_envs=2, visual_seeds=[0, 5], vary="all", frame_skip=100, image_size=16,
          frame_stack=1, seed=3)
PENDULUM_MOVING = M.check_moving("pendulum", "all")[0]


def _rollout(**extra):
  """12 steps (an episode is 10: one auto-reset) of 2 pendulum envs: frames, rewards,
  states, episode steps and qpos."""
  rng = np.random.default_rng(0)
  with dmcr_jax.make("pendulum-swingup", **KW, **extra) as env:
    obs, info = env.reset(seed=1)
    out = dict(obs=[obs], reward=[], state=[info["state"]], step=[info["episode_step"]],
               qpos=[np.asarray(env.state.task.data.qpos)])
    for _ in range(12):
      obs, reward, _, _, info = env.step(rng.uniform(-1, 1, (2, 1)).astype(np.float32))
      out["obs"].append(np.asarray(obs))
      out["reward"].append(reward)
      out["state"].append(info["state"])
      out["step"].append(info["episode_step"])
      out["qpos"].append(np.asarray(env.state.task.data.qpos))
  return out


@pytest.fixture(scope="module")
def pool_runs():
  return (_rollout(renderer="pool", workers=1),
          _rollout(renderer="pool", workers=1, moving="all", intensity=0.3))


@pytest.mark.slow
def test_moving_pool_env_keeps_the_physics_and_draws_each_steps_look(pool_runs):
  """Moving looks change the frames, not the physics or rewards; the pool's frames are
  MuJoCo's render of each step's look (`look_at` of the seed and episode step; a
  blended sky as the blend of two renders)."""
  static, pool = pool_runs
  np.testing.assert_array_equal(pool["reward"], static["reward"])
  np.testing.assert_array_equal(pool["state"], static["state"])
  rm = rmod.build_render_model("pendulum")
  with rmod.FrameRenderer(rm, 16, 16) as fr:
    for t in (3, 11):
      looks = rmod.prepare(rm, M.look_at(rm.sample([0, 5], "all"), pool["step"][t],
                                         PENDULUM_MOVING, 0.3))
      for i in range(2):
        a = fr.render(looks, pool["qpos"][t][i], index=i).astype(np.float32)
        b = fr.render(rmod.Looks(**{**vars(looks), "skybox_tex": looks.skybox_tex2}),
                      pool["qpos"][t][i], index=i).astype(np.float32)
        w = looks.sky_mix[i]
        want = np.rint((1 - w) * a + w * b) if w > 0 else a
        np.testing.assert_array_equal(pool["obs"][t][i], want.astype(np.uint8))
  assert all(not np.array_equal(p, s) for p, s in zip(pool["obs"][1:], static["obs"][1:]))


@pytest.mark.slow
def test_moving_jax_env_keeps_the_physics_and_draws_the_pools_looks(pool_runs):
  """The ray caster's moving env: the same physics and rewards, and frames close to
  the pool's frames of the same moving looks."""
  static, pool = pool_runs
  ray = _rollout(renderer="jax", moving="all", intensity=0.3, shadows=False, reflection=False)
  np.testing.assert_allclose(ray["reward"], static["reward"], atol=1e-4)
  np.testing.assert_allclose(ray["state"], static["state"], atol=1e-4)
  mad = [np.abs(np.asarray(r, np.float32) - np.asarray(p, np.float32)).mean()
         for r, p in zip(ray["obs"], pool["obs"])]
  assert max(mad) < 8.0, mad
  moved = [np.abs(np.asarray(r, np.float32) - np.asarray(s, np.float32)).mean()
           for r, s in zip(ray["obs"][1:], static["obs"][1:])]
  assert min(moved) > 0.5, moved


def test_dmcr_train_moving_flags_are_checked_and_reach_the_env(monkeypatch, tmp_path, capsys):
  import re
  from dmcr_jax.train import loop
  from dmcr_jax.train.__main__ import parse
  base = ["--task", "pendulum-swingup", "--out", str(tmp_path / "run")]
  cfg, _ = parse(base + ["--moving", "camera,background", "--intensity", "0.2"])
  assert (cfg.moving, cfg.intensity) == ("camera,background", 0.2)
  seen = {}
  monkeypatch.setattr(dmcr_jax, "make", lambda *a, **k: seen.update(k))
  loop.make_env(cfg)
  assert (seen["moving"], seen["intensity"]) == ("camera,background", 0.2)
  assert parse(base)[0].moving == "none"
  for argv, message in ((["--moving", "sky", "--intensity", ".2"], "Valid moving factors"),
                        (["--moving", "camera"], "needs an intensity in"),
                        (["--moving", "camera", "--intensity", "2"], r"in \[0, 1\]")):
    with pytest.raises(SystemExit):
      parse(base + argv)
    assert re.search(message, capsys.readouterr().err), argv
