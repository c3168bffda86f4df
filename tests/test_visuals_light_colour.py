"""Finger's light colour (the original DMCR's light factor): its distribution, its
random words, that it leaves every existing look as it was, and that MuJoCo's
renderer and the JAX ray caster both draw it.

The original (`dmc_remastered/finger.py`, `get_model`) draws, for every visual
seed but 0 and applies with the light factor on:
  diffuse  = U(.5, 1.1) + (U(−.02, .02), U(−.02, .02), U(−.02, .02)),
  specular = U(0, 1.2)  + (U(−.02, .02), U(−.02, .02), U(−.02, .02)),
not clipped. No other domain's `get_model` changes its light's colour.
"""

import hashlib
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax import visuals as V
from dmcr_jax.benchmarks import jax_render_parity as parity
from dmcr_jax.visuals import jax_render as JR
from dmcr_jax.visuals import jax_render_scene as JS
from dmcr_jax.visuals import params as P
from dmcr_jax.visuals import ranges as R
from dmcr_jax.visuals import render_model as RM
from tests.banks import procedural_bank

COLOUR = ("light_diffuse", "light_specular")

# ---------------------------------------------------------------------------
# Existing looks are unchanged
# ---------------------------------------------------------------------------

# The fields every look had before the light colour was added, and their bytes for
# HASH_SEEDS as the code before it drew them (sha256 of the fields in this order,
# first 16 hex digits; computed with main at 970c6b5).
OLD_FIELDS = ("cam_pos", "cam_rot", "light_pos", "light_dir", "headlight_ambient",
              "headlight_diffuse", "headlight_specular", "body_rgba", "effector_rgba",
              "target_rgba", "floor_id", "background_id", "floor_reflectance", "varied",
              "seed")
HASH_SEEDS = [0, 1, 2, 3, 7, 1000, 123456, 2**31 - 1]
OLD_HASHES = {
    ("finger", "all"): "2f9cf71fd872cf2f", ("finger", "light"): "d6c2dd9604647e04",
    ("cheetah", "all"): "dfae16d8a0ac3b12", ("cheetah", "light"): "6517674f8dfea28e",
    ("reacher", "all"): "f5781b19e87229e2", ("reacher", "light"): "bc1aab3626698c30",
    ("walker", "all"): "23250fda2a609988", ("walker", "light"): "6497169698041e37",
    ("fish", "all"): "618fb3a165eb6079", ("fish", "light"): "5cd3b9822f586f9b",
}


@pytest.mark.parametrize("domain,vary", sorted(OLD_HASHES))
def test_existing_fields_are_bit_identical_to_before(domain, vary):
  p = V.sample(domain, HASH_SEEDS, vary)
  h = hashlib.sha256()
  for k in OLD_FIELDS:
    h.update(np.ascontiguousarray(np.asarray(getattr(p, k))).tobytes())
  assert h.hexdigest()[:16] == OLD_HASHES[(domain, vary)]


# ---------------------------------------------------------------------------
# The draws: words, distribution, where they apply
# ---------------------------------------------------------------------------


def test_draws_are_the_light_streams_fold_ins_4_and_5():
  """By construction: fold-ins 2·256 + 4 and + 5 of the seed's key (apart from the
  light factor's fold-ins 0–3 that the position and headlight use); high halves
  then low halves; diffuse base, specular base, 3 diffuse jitters, 3 specular."""
  seeds = [1, 2, 99, 2**31 - 1]
  p = V.sample("finger", seeds, "light")
  for i, seed in enumerate(seeds):
    key = jax.random.key(seed, impl="threefry2x32")
    words = np.concatenate([np.asarray(jax.random.key_data(jax.random.fold_in(
        key, V.FACTOR_IDS["light"] * 256 + j))) for j in (4, 5)])
    k = np.concatenate([words >> 16, words & 0xFFFF]).astype(np.float32)
    for j, (name, ((lo, hi), jit)) in enumerate((("light_diffuse", R.FINGER_LIGHT_DIFFUSE),
                                                  ("light_specular", R.FINGER_LIGHT_SPECULAR))):
      step = np.float32(P._round8(hi - lo) / 65536.0)
      jstep = np.float32(P._round8(2 * jit) / 65536.0)
      base = np.float32(lo) + k[j] * step
      jitter = np.float32(-jit) + k[2 + 3 * j:5 + 3 * j] * jstep
      np.testing.assert_array_equal(np.asarray(getattr(p, name))[i], base + jitter)


def test_distribution_is_the_originals():
  n = 20_000
  p = V.sample("finger", np.arange(1, n + 1), "light")
  for name, ((lo, hi), jit) in (("light_diffuse", R.FINGER_LIGHT_DIFFUSE),
                                ("light_specular", R.FINGER_LIGHT_SPECULAR)):
    x = np.asarray(getattr(p, name), np.float64)
    tol = 0.01 * (hi - lo)                     # draws' steps have 8 significant bits
    assert x.min() >= lo - jit and x.max() <= hi + jit + tol, name
    # Not clipped: the base's edges plus the jitter go past the base's range.
    assert x.min() < lo and x.max() > hi, name
    # One scalar base shared by the channels, a small per-channel jitter.
    spread = x.max(1) - x.min(1)
    assert spread.max() <= 2 * jit * 1.01 and spread.max() > 2 * jit * 0.9, name
    diff = x[:, 0] - x[:, 1]                   # jitter_r − jitter_g: var 2·(2j)²/12
    assert abs(diff.mean()) < 1e-3 and abs(diff.std() - np.sqrt(2 / 12) * 2 * jit) < 1e-3
    m = x.mean(1)                              # base + mean jitter, ~ U(lo, hi)
    assert abs(m.mean() - (lo + hi) / 2) < 0.01 * (hi - lo), name
    assert abs(m.std() - (hi - lo) / np.sqrt(12)) < 0.01 * (hi - lo), name
    hist, _ = np.histogram(m, bins=10, range=(lo + jit, hi - jit))
    assert hist.min() > 0.8 * hist.mean(), (name, hist)
  d, s = np.asarray(p.light_diffuse), np.asarray(p.light_specular)
  # Independent of each other and of the light's position and the headlight.
  cols = [d[:, 0], s[:, 0], d[:, 0] - d[:, 1], np.asarray(p.light_pos)[:, 0],
          np.asarray(p.light_pos)[:, 2], np.asarray(p.headlight_diffuse)[:, 0]]
  corr = np.corrcoef(np.stack(cols))
  assert np.abs(corr - np.eye(len(cols))).max() < 0.05, corr


@pytest.mark.parametrize("domain", V.DOMAINS)
def test_only_finger_and_only_with_the_light_factor(domain):
  seeds = np.arange(0, 64)
  dflt = V.defaults(domain)
  rm_free = [f for f in V.FACTORS if f != "light"]
  for vary in ("all", "light", rm_free, "none"):
    p = V.sample(domain, seeds, vary)
    for k in COLOUR:
      x = np.asarray(getattr(p, k))
      coloured = domain == "finger" and vary in ("all", "light")
      np.testing.assert_array_equal(x[0], dflt[k], err_msg=k)     # seed 0
      if coloured:
        assert (x[1:] != dflt[k]).all(), (domain, vary, k)
      else:
        np.testing.assert_array_equal(x, np.broadcast_to(dflt[k], x.shape),
                                      err_msg=f"{domain} {vary} {k}")
  # The defaults are dm_control's model values.
  from dmcr_jax.models import names
  sm = names.suite_model(domain)
  light = names.obj_id(sm, P.mujoco.mjtObj.mjOBJ_LIGHT, R.DOMAIN_RANGES[domain].light)
  for k in COLOUR:
    np.testing.assert_array_equal(dflt[k], getattr(sm, k)[light].astype(np.float32))


def test_only_finger_has_colour_ranges():
  assert [d for d in V.DOMAINS if R.DOMAIN_RANGES[d].light_diffuse is not None] == ["finger"]
  assert [d for d in V.DOMAINS if R.DOMAIN_RANGES[d].light_specular is not None] == ["finger"]
  assert R.FINGER_LIGHT_DIFFUSE == ((0.5, 1.1), 0.02)
  assert R.FINGER_LIGHT_SPECULAR == ((0.0, 1.2), 0.02)


def test_deterministic_jit_and_batch_independent():
  seeds = np.arange(1, 65)
  a = V.sample("finger", seeds, "all")
  b = jax.jit(lambda s: V.sample("finger", s, "all"))(jnp.asarray(seeds, jnp.int32))
  c = V.sample("finger", seeds[::-1].copy(), "all")
  one = V.sample("finger", [int(seeds[5])], "light")
  for k in COLOUR:
    x = np.asarray(getattr(a, k))
    np.testing.assert_array_equal(x, np.asarray(getattr(b, k)))
    np.testing.assert_array_equal(x, np.asarray(getattr(c, k))[::-1])
    np.testing.assert_array_equal(x[5], np.asarray(getattr(one, k))[0])


# ---------------------------------------------------------------------------
# Both renderers
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bank():
  return procedural_bank((0, 7), (0, 1), "light-colour-test-bank")


def test_render_model_applies_and_resets_the_colour(bank):
  import copy
  rm = copy.copy(V.build_render_model("finger", bank))
  p = rm.sample(np.arange(0, 8), "light")
  looks = RM.prepare(rm, p)
  l = rm.light_id
  for k in COLOUR:
    np.testing.assert_array_equal(getattr(looks, k), np.asarray(getattr(p, k)))
    assert getattr(looks, k).dtype == np.float32
  RM.apply(rm, looks, 3)
  np.testing.assert_array_equal(rm.model.light_diffuse[l], looks.light_diffuse[3])
  np.testing.assert_array_equal(rm.model.light_specular[l], looks.light_specular[3])
  back = RM.with_default_look(rm).model
  np.testing.assert_array_equal(back.light_diffuse[l], rm.dflt["light_diffuse"])
  np.testing.assert_array_equal(back.light_specular[l], rm.dflt["light_specular"])
  RM.apply(rm, looks, 0)                     # seed 0: dm_control's colour again
  np.testing.assert_array_equal(rm.model.light_diffuse[l], np.float32([.6, .6, .6]))
  np.testing.assert_array_equal(rm.model.light_specular[l], np.float32([.3, .3, .3]))
  # Another domain's looks keep the model's colour.
  cr = V.build_render_model("cheetah", bank)
  cl = RM.prepare(cr, cr.sample(np.arange(0, 8), "all"))
  np.testing.assert_array_equal(cl.light_diffuse, np.broadcast_to(
      cr.dflt["light_diffuse"], (8, 3)))


def test_device_looks_have_the_hosts_colour(bank):
  rm = V.build_render_model("finger", bank)
  scene = JS.build_scene(rm)
  seeds = np.arange(0, 17, dtype=np.int32)
  for vary in ("all", "camera,body"):
    host = JS.device_looks(scene, rm, RM.prepare(rm, rm.sample(seeds, vary)))
    dev = JS.look_maker(scene, rm, vary)(jnp.asarray(seeds))
    for k in COLOUR:
      np.testing.assert_array_equal(np.asarray(getattr(dev, k)), np.asarray(getattr(host, k)))


def _extreme_seeds():
  """Finger seeds in 1..2000 with the brightest and the dimmest light colour
  (sum of diffuse and specular), the dim one with a negative specular channel."""
  p = V.sample("finger", np.arange(1, 2001), "light")
  d, s = np.asarray(p.light_diffuse), np.asarray(p.light_specular)
  total = d.mean(1) + s.mean(1)
  bright, dim = int(np.argmax(total)), int(np.argmin(total))
  assert s[dim].min() < 0 and d[bright].max() > 1.1 and s[bright].max() > 1.15
  return [bright + 1, dim + 1]


def _with_default_colour(rm, looks):
  """The same `Looks` with the light's colour dm_control's (its position as drawn)."""
  n = len(looks)
  return RM.Looks(**{**looks.__dict__, **{
      k: np.broadcast_to(rm.dflt[k], (n, 3)).astype(np.float32) for k in COLOUR}})


@pytest.mark.slow
def test_both_renderers_draw_the_colour(bank):
  """MuJoCo's renderer and the ray caster agree on finger looks whose light colour
  varies, and both change with the colour alone (same light position)."""
  rm = V.build_render_model("finger", bank)
  scene = JS.build_scene(rm)
  seeds = _extreme_seeds()
  looks = RM.prepare(rm, rm.sample(seeds, "light"))
  plain = _with_default_colour(rm, looks)     # light moved, colour dm_control's
  qpos, variables = parity.dm_states("finger", 1)[0]
  data = P.mujoco.MjData(rm.model)
  data.qpos[:] = qpos
  P.mujoco.mj_fwdPosition(rm.model, data)
  bp = JS.poses(data)
  keys = {k for k, _, _ in scene.variables}
  var = {k: jnp.asarray(v, jnp.float32) for k, v in variables.items() if k in keys} or None
  fr = RM.FrameRenderer(rm, 84, 84)
  try:
    out = {}
    for tag, lk in (("varied", looks), ("plain", plain)):
      dl = JS.device_looks(scene, rm, lk)
      for i in range(2):
        ref = fr.render(lk, qpos, index=i, model_variables=variables).astype(int)
        img = np.asarray(JR.render(scene, bp, dl.take(i), var, height=84, width=84))
        out[tag, i] = ref, img.astype(int)
  finally:
    fr.close()
  for i in range(2):
    (ref_v, jax_v), (ref_p, jax_p) = out["varied", i], out["plain", i]
    assert np.abs(ref_v - jax_v).mean() < 5.0          # the parity table's finger max 4.67
    assert np.abs(ref_p - jax_p).mean() < 5.0
    # The colour changes the picture, by the same amount in both renderers (to 10%).
    dm, dj = (ref_v - ref_p).mean(), (jax_v - jax_p).mean()
    assert abs(dj - dm) < 0.1 * abs(dm), (i, dm, dj)
  # Bright seed brighter than dm_control's colour (.6 diffuse, .3 specular), dim
  # seed (diffuse ~.5, specular ~0, one channel below 0) darker.
  assert (out["varied", 0][0] - out["plain", 0][0]).mean() > 3.0
  assert (out["varied", 1][0] - out["plain", 1][0]).mean() < -0.5


@pytest.mark.slow
def test_parity_with_mujoco_all_factors(bank):
  """Finger with every factor on (light colour included): silhouettes and pixels
  as the parity table's finger row."""
  rm = V.build_render_model("finger", bank)
  res = parity.compare("finger", [0, 1, 2, 3], states=1, size=84, rm=rm, min_pixels=10)
  for frame in res["iou"]:
    assert frame, "no bodies seen"
    for body, iou in frame.items():
      assert iou >= 0.95, (body, iou)
  assert max(res["mad"]) < 5.0, res["mad"]


def test_render_pool_carries_the_colour():
  """The multi-process pool writes the colour in its workers: its frames equal the
  single-frame reference, and differ from the same looks with dm_control's colour."""
  from dmcr_jax.visuals.render_pool import RenderPool
  with RenderPool("finger-turn_easy", max_batch=4, workers=1) as pool:
    rm = pool.rm
    looks = RM.prepare(rm, rm.sample(_extreme_seeds(), "light"))
    plain = _with_default_colour(rm, looks)
    q, variables = parity.dm_states("finger", 1)[0]
    qpos = np.stack([q, q])
    var = {k: np.stack([v, v]) for k, v in variables.items() if ":" in k}
    frames = pool.render(qpos, looks, var)
    plain_frames = pool.render(qpos, plain, var)
  fr = RM.FrameRenderer(rm)
  try:
    ref = np.stack([fr.render(looks, q, index=i, model_variables=variables)
                    for i in range(2)])
  finally:
    fr.close()
  np.testing.assert_array_equal(frames, ref)
  for i in range(2):
    assert (frames[i] != plain_frames[i]).any()
