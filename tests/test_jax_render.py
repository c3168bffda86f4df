"""JAX ray caster: intersections vs NumPy, a known tiny image, jit/vmap invariance,
determinism, and silhouette/pixel parity with MuJoCo's renderer (cartpole, walker).

Small bank (a few textures) and small images keep compilation and the GL contexts
cheap; the whole file runs in well under a minute on two CPU cores.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from dmcr_jax.benchmarks import jax_render_parity as parity
from dmcr_jax.visuals import jax_render as JR
from dmcr_jax.visuals import jax_render_scene as JS
from dmcr_jax.visuals import render_model as RM
from tests.banks import procedural_bank

# --------------------------------------------------------------------------
# Intersections against a NumPy reference (root finding along the ray)
# --------------------------------------------------------------------------


def _inside(typ, p, size):
  """NumPy point-inside tests of the primitives (MuJoCo's size layout)."""
  x, y, z = p[..., 0], p[..., 1], p[..., 2]
  if typ == JS.SPHERE:
    return x * x + y * y + z * z <= size[0] ** 2
  if typ == JS.ELLIPSOID:
    return (x / size[0]) ** 2 + (y / size[1]) ** 2 + (z / size[2]) ** 2 <= 1
  if typ == JS.CAPSULE:
    zc = np.clip(z, -size[1], size[1])
    return x * x + y * y + (z - zc) ** 2 <= size[0] ** 2
  if typ == JS.CYLINDER:
    return (x * x + y * y <= size[0] ** 2) & (np.abs(z) <= size[1])
  if typ == JS.BOX:
    return np.all(np.abs(p) <= size, axis=-1)
  raise ValueError(typ)


def _numpy_hit(typ, o, d, size, tmax=20.0, steps=4000):
  """First t where the ray enters the solid: dense march + bisection (float64)."""
  ts = np.linspace(0, tmax, steps)
  pts = o[:, None] + ts[None, :, None] * d[:, None]
  ins = _inside(typ, pts, size)
  out = np.full(len(o), np.inf)
  for i in range(len(o)):
    if ins[i, 0]:
      continue                       # starts inside: culled, like MuJoCo
    idx = np.flatnonzero(ins[i])
    if not len(idx):
      continue
    lo, hi = ts[idx[0] - 1], ts[idx[0]]
    for _ in range(50):
      mid = 0.5 * (lo + hi)
      if _inside(typ, (o[i] + mid * d[i])[None], size)[0]:
        hi = mid
      else:
        lo = mid
    out[i] = hi
  return out


@pytest.mark.parametrize("typ,size", [
    (JS.SPHERE, [0.7, 0, 0]), (JS.ELLIPSOID, [0.9, 0.4, 0.6]),
    (JS.CAPSULE, [0.3, 0.8, 0]), (JS.CYLINDER, [0.5, 0.6, 0]),
    (JS.BOX, [0.5, 0.3, 0.8])])
def test_intersections_match_numpy(typ, size):
  rng = np.random.default_rng(typ)
  n = 200
  o = rng.normal(size=(n, 3)) * 0.5 + np.array([0, 0, 3.0])
  target = rng.uniform(-1, 1, size=(n, 3))
  d = target - o
  d /= np.linalg.norm(d, axis=-1, keepdims=True)
  size = np.asarray(size, np.float64)
  want = _numpy_hit(typ, o, d, size)
  got = np.asarray(JR.intersect(typ, jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32),
                                jnp.asarray(size, jnp.float32)))
  hit = np.isfinite(want)
  assert 20 < hit.sum() < n, "the rays should both hit and miss"
  # grazing rays may flip between hit/miss within the march's resolution
  agree = (got < JR.INF) == hit
  assert agree.mean() > 0.97
  both = hit & (got < JR.INF)
  np.testing.assert_allclose(got[both], want[both], atol=2e-3)


@pytest.mark.parametrize("unit", [False, True])
def test_capsule_from_every_side(unit):
  """Rays from all around a capsule, some along its axis, against the NumPy march:
  the capsule tests one end sphere, chosen from where the ray meets its cylinder."""
  rng = np.random.default_rng(1)
  size = np.array([0.3, 0.8, 0.0])
  o = rng.normal(size=(300, 3))
  o *= 2.5 / np.linalg.norm(o, axis=-1, keepdims=True)
  d = rng.uniform(-0.5, 0.5, size=(300, 3)) * [1, 1, 2] - o
  axis = np.array([[0, 0, 2.0], [0, 0, -2.0], [0.1, 0, 2.0], [0, 0.2, -2.0], [0, 0, 2.0]])
  o = np.concatenate([o, axis])
  d = np.concatenate([d, [[0, 0, -1.0], [0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0], [0, 0, 1]]])
  d /= np.linalg.norm(d, axis=-1, keepdims=True)
  want = _numpy_hit(JS.CAPSULE, o, d, size)
  got = np.asarray(JR.intersect(JS.CAPSULE, jnp.asarray(o, jnp.float32),
                                jnp.asarray(d, jnp.float32), jnp.asarray(size, jnp.float32),
                                unit=unit))
  hit = np.isfinite(want)
  assert 100 < hit.sum() < len(o)
  assert ((got < JR.INF) == hit).mean() > 0.98
  both = hit & (got < JR.INF)
  np.testing.assert_allclose(got[both], want[both], atol=2e-3)
  # along the axis: the near end's pole (t = 2 − 0.8 − 0.3), and a ray leaving it misses
  np.testing.assert_allclose(got[-5:-3], 0.9, atol=1e-5)
  assert got[-1] == JR.INF


def test_plane_front_side_and_extent():
  o = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0, 1.0]])
  d = jnp.array([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
  t = np.asarray(JR.intersect(JS.PLANE, o, d, jnp.array([0.5, 0.5, 0.1])))
  assert t[0] == pytest.approx(1.0)
  assert t[1] == JR.INF                  # hits z = 0 at x = 0.75 > 0.5: outside
  assert t[2] == JR.INF and t[3] == JR.INF   # from behind / away: culled
  t_inf = np.asarray(JR.intersect(JS.PLANE, o, d, jnp.array([0.0, 0.0, 0.1])))
  assert t_inf[1] == pytest.approx(1.25)     # size 0: infinite plane


def test_normals_are_unit_and_outward():
  rng = np.random.default_rng(0)
  for typ, size in ((JS.SPHERE, [0.5, 0, 0]), (JS.CAPSULE, [0.2, 0.4, 0]),
                    (JS.CYLINDER, [0.3, 0.2, 0]), (JS.BOX, [0.2, 0.3, 0.4]),
                    (JS.ELLIPSOID, [0.3, 0.5, 0.2])):
    o = rng.normal(size=(64, 3)) + np.array([0, 0, 4.0])
    d = -o / np.linalg.norm(o, axis=-1, keepdims=True)
    s = jnp.asarray(size, jnp.float32)
    t = JR.intersect(typ, jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32), s)
    p = o + np.asarray(t)[:, None] * d
    size = tuple(jnp.broadcast_to(s[i], (64,)) for i in range(3))
    n = np.stack(JR._normal_local(jnp.full((64,), typ), JR._v(jnp.asarray(p, jnp.float32)),
                                  size, [typ]), -1)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-5)
    assert np.all(np.sum(n * d, -1) < 1e-6)       # the ray enters against the normal


# --------------------------------------------------------------------------
# Scenes from real models (small bank)
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bank():
  floors = [0, 7]
  skies = [0, 1]
  return procedural_bank(floors, skies, "jax-render-test-bank")


def _setup(domain, bank, seeds):
  rm = RM.build_render_model(domain, bank)
  scene = JS.build_scene(rm)
  looks = RM.prepare(rm, rm.sample(seeds))
  return rm, scene, looks, JS.device_looks(scene, rm, looks)


def test_scene_ignores_the_look_a_mujoco_render_left_in_the_model(bank):
  # `RM.apply` (MuJoCo's renderer, e.g. `dmcr-show`'s grid) writes a look into the
  # shared model; a scene built afterwards (the JAX renderer in the same process)
  # still shows dm_control's look, with the same material slots.
  import copy
  rm = copy.copy(RM.build_render_model("cartpole", bank))
  scene = JS.build_scene(rm)
  slots = JS.material_slots(scene, rm)
  looks = RM.prepare(rm, rm.sample(np.arange(1, 9), "floor,light,camera,body"))
  index = int(np.flatnonzero(looks.floor_matid != rm.dflt["floor_matid"])[0])
  RM.apply(rm, looks, index)
  assert rm.model.geom_matid[rm.floor_geom] != rm.dflt["floor_matid"]
  after = JS.build_scene(rm)
  np.testing.assert_array_equal(JS.material_slots(after, rm), slots)
  assert jax.tree.structure(after) == jax.tree.structure(scene)
  for a, b in zip(jax.tree.leaves(after), jax.tree.leaves(scene)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _poses(rm, qpos):
  d = mujoco.MjData(rm.model)
  d.qpos[:] = qpos
  mujoco.mj_fwdPosition(rm.model, d)
  return JS.poses(d)


def test_tiny_scene_known_image(bank):
  """Cartpole seen by its fixed camera: the sky above the horizon (unlit skybox
  texels, exactly), the floor below, the cart (its material's hue) in the middle."""
  rm, scene, looks, dl = _setup("cartpole", bank, [0])
  img = np.asarray(JR.render(scene, _poses(rm, rm.model.qpos0), dl.take(0), height=16,
                             width=16, shadows=False, reflection=False))
  assert img.shape == (16, 16, 3) and img.dtype == np.uint8
  # the cart (self material, orange) covers the middle pixels of row 8 or 9
  body = np.asarray(rm.dflt["mat_rgba"][rm.body_mats[0]][:3])
  mid = img[7:10, 7:9].reshape(-1, 3).astype(float) / 255
  assert np.any(np.linalg.norm(mid / mid.sum(-1, keepdims=True)
                               - body / body.sum(), axis=-1) < 0.05)
  # the top row is pure skybox: equal to the skybox texture looked up directly
  floats, ints = JR.pack_env(scene, _poses(rm, rm.model.qpos0), dl.take(0))
  reader = JR.ArrayReader(floats, ints, None, scene.skies.reshape(-1))
  d, _ = JR._camera_rays(JR.layout(scene), reader, jnp.arange(256), 16, 16, 1)
  sky = np.stack(JR._sky_color(JR.layout(scene), reader, d), -1).reshape(16, 16, 3)
  np.testing.assert_array_equal(img[0], np.round(sky[0] * 255).astype(np.uint8))
  # ids: sky at the top, the floor (world body) at the bottom, the cart in the middle
  _, ids = JR.render_with_ids(scene, _poses(rm, rm.model.qpos0), dl.take(0), height=16,
                              width=16)
  ids = np.asarray(ids)
  cart = mujoco.mj_name2id(rm.model, mujoco.mjtObj.mjOBJ_BODY, "cart")
  assert np.all(ids[0] == -1) and np.all(ids[-1] == 0) and cart in ids[6:10, 6:10]


def test_fences_leave_the_render_unchanged(bank, monkeypatch):
  """The fenced per-pixel graph (`ArrayReader.fence`, on by default off the CPU) draws
  what the unfenced one draws: the same colours to float rounding and the same ids,
  on a scene with shadows, the floor's reflection and several lights."""
  from dmcr_jax.visuals import jax_render_pack
  rm, scene, looks, dl = _setup("walker", bank, [3])
  bp = _poses(rm, rm.model.qpos0)
  draws = {}
  for fences in (False, True):
    monkeypatch.setattr(jax_render_pack, "fences_by_default", lambda f=fences: f)
    lowered = jax.jit(lambda b, l: JR._render(  # a fresh trace for each setting
        scene, b, l, None, height=12, width=12, shadows=True, reflection=True,
        supersample=1)).lower(bp, dl.take(0))
    assert ("optimization_barrier" in lowered.as_text()) == fences
    draws[fences] = lowered.compile()(bp, dl.take(0))
  (c0, ids0), (c1, ids1) = draws[False], draws[True]
  np.testing.assert_allclose(np.asarray(c1), np.asarray(c0), rtol=0, atol=1e-5)
  np.testing.assert_array_equal(np.asarray(ids1), np.asarray(ids0))
  assert np.ptp(np.asarray(c0)) > 0.1 and len(np.unique(np.asarray(ids0))) > 2


@pytest.mark.slow
def test_jit_vmap_invariance_and_determinism(bank):
  rm, scene, looks, dl = _setup("cartpole", bank, [0, 1, 2])
  rng = np.random.default_rng(0)
  qs = [rm.model.qpos0 + 0.3 * rng.standard_normal(rm.model.nq) for _ in range(3)]
  bps = [_poses(rm, q) for q in qs]
  one = [np.asarray(JR.render(scene, bps[i], dl.take(i), height=12, width=12))
         for i in range(3)]
  batch = jax.tree.map(lambda *x: jnp.stack(x), *bps)
  many = np.asarray(JR.render_batch(scene, batch, dl, height=12, width=12))
  for i in range(3):
    np.testing.assert_array_equal(many[i], one[i])
  again = np.asarray(JR.render_batch(scene, batch, dl, height=12, width=12))
  np.testing.assert_array_equal(many, again)
  assert not np.array_equal(one[0], one[1])       # looks and states matter


@pytest.mark.slow
@pytest.mark.parametrize("domain", ["walker", "finger"])
def test_running_minima_equal_stacked_distances(domain, bank):
  """The GPU's nearest-hit form (running minima over the objects) and the CPU's
  (stacked distances, argmin) give the same colours and ids, with transparent
  objects in front of opaque ones (half the material slots at alpha 0.8)."""
  rm, scene, looks, dl = _setup(domain, bank, [0, 1])
  rgba = dl.mat_rgba.at[:, ::2, 3].set(0.8)
  dl = dl.replace(mat_rgba=rgba)
  rng = np.random.default_rng(1)
  for i in range(2):
    bp = _poses(rm, rm.model.qpos0 + 0.2 * rng.standard_normal(rm.model.nq))
    out = [JR._render(scene, bp, dl.take(i), None, height=20, width=20, shadows=True,
                      reflection=True, supersample=1, running=running)
           for running in (False, True)]
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    assert np.any(np.asarray(out[0][1]) >= 0)
  assert JR.running_minima() == (jax.default_backend() != "cpu")


# --------------------------------------------------------------------------
# The fused GPU kernel (run here by Pallas' interpreter; lowered for CUDA)
# --------------------------------------------------------------------------


def _batch(rm, n, seed=0):
  rng = np.random.default_rng(seed)
  bps = [_poses(rm, rm.model.qpos0 + 0.2 * rng.standard_normal(rm.model.nq))
         for _ in range(n)]
  return jax.tree.map(lambda *x: jnp.stack(x), *bps)


@pytest.mark.slow
def test_kernel_frames_equal_xla_frames(bank):
  """The kernel's code (the same `trace_pixels`, read through `RefReader`) gives
  the XLA renderer's frames (up to float rounding: ≤ 1 level in < 1 % of the
  values) and ids, with transparent objects, a pixel block that does not divide
  the rays (the padding is cut off), supersampling, and blocks skipping what none
  of their pixels needs (the top block sees only sky)."""
  from dmcr_jax.visuals import jax_render_kernel as JK
  rm, scene, looks, dl = _setup("cartpole", bank, [0, 1])
  dl = dl.replace(mat_rgba=dl.mat_rgba.at[:, ::2, 3].set(0.8))
  bp = _batch(rm, 2)
  opts = dict(height=10, width=10, shadows=True, reflection=True, supersample=2)
  floats, ints = jax.vmap(JR.pack_env, in_axes=(None, 0, 0))(scene, bp, dl)
  colour, ids = JK.trace_batch(JR.layout(scene), floats, ints,
                               scene.floor_texels.reshape(-1), scene.skies.reshape(-1),
                               block=64, skip_empty=True, interpret=True, **opts)
  assert colour.shape == (2, 3, 448) and ids.shape == (2, 448)     # 400 rays, 7 blocks
  assert np.any(np.all(np.asarray(ids)[:, :64] < 0, axis=1))      # a block of sky only
  fused = np.asarray(JR.image_from_planes(colour, 10, 10, 2)).astype(int)
  xla = np.asarray(JR.render_batch(scene, bp, dl, kernel=False, **opts))
  diff = np.abs(fused - xla)
  assert diff.max() <= 1 and np.mean(diff > 0) < 0.01, (diff.max(), np.mean(diff > 0))
  for i in range(2):
    _, ref = JR._render(scene, jax.tree.map(lambda x: x[i], bp), dl.take(i), None, **opts)
    np.testing.assert_array_equal(np.asarray(ids)[i, :400], np.asarray(ref))
    assert np.any(np.asarray(ref) >= 0)
  with pytest.raises(ValueError, match="power of two"):
    JK.render_batch(scene, bp, dl, height=10, width=10, block=100, interpret=True)


def test_kernel_is_the_gpu_default():
  """`render_batch` uses the fused kernel on a GPU only (None, its default), refuses
  it without one when asked (True), and skips it on request (False)."""
  gpu = jax.default_backend() == "gpu"
  assert JR.use_kernel(None) is gpu and JR.use_kernel(False) is False
  if not gpu:
    with pytest.raises(ValueError, match="needs a GPU"):
      JR.use_kernel(True)


@pytest.mark.slow
def test_kernel_lowers_for_cuda(bank):
  """The kernel lowers to Triton for a CUDA GPU (Pallas' own lowering, on this
  machine without one): every op of the per-pixel code has a Triton form."""
  from dmcr_jax.visuals import jax_render_kernel as JK
  rm, scene, looks, dl = _setup("walker", bank, [0, 1])
  for skip in (False, True):
    fn = jax.jit(lambda bp, look: JK.render_batch(scene, bp, look, height=84, width=84,
                                                  skip_empty=skip))
    text = fn.trace(_batch(rm, 2), dl).lower(lowering_platforms=("cuda",)).as_text()
    assert "__gpu$xla.gpu.triton" in text and "dmcr_ray_cast" in text


@pytest.mark.slow
def test_variables_move_the_reacher_target(bank):
  rm, scene, looks, dl = _setup("reacher", bank, [0])
  bp = _poses(rm, rm.model.qpos0)
  a = np.asarray(JR.render(scene, bp, dl.take(0), {"geom_pos:target": jnp.array(
      [0.1, 0.1, 0.01]), "geom_size:target": jnp.array([0.05, 0, 0])}, height=24, width=24))
  b = np.asarray(JR.render(scene, bp, dl.take(0), {"geom_pos:target": jnp.array(
      [-0.1, -0.1, 0.01]), "geom_size:target": jnp.array([0.05, 0, 0])}, height=24,
      width=24))
  assert np.abs(a.astype(int) - b.astype(int)).sum() > 0


# --------------------------------------------------------------------------
# Parity with MuJoCo (segmentation IoU per body, mean absolute difference)
# --------------------------------------------------------------------------

# Bounds from `python -m dmcr_jax.benchmarks.jax_render_parity` (the full bank, 100 seeds x 3
# states: mean 2.1 / 5.4, max 3.9 / 12.1): the test checks three frames with margin.
MAD_BOUND = {"cartpole": 4.0, "walker": 9.0}


@pytest.mark.parametrize("domain", ["cartpole", "walker"])
def test_parity_with_mujoco(domain, bank):
  rm = RM.build_render_model(domain, bank)
  res = parity.compare(domain, [0, 1, 2], states=1, size=84, rm=rm, min_pixels=10)
  for frame in res["iou"]:
    assert frame, "no bodies seen"
    for body, iou in frame.items():
      assert iou >= 0.95, (domain, body, iou)
  assert max(res["mad"]) < MAD_BOUND[domain], res["mad"]
  # and the comparison can fail: a wrong look (another seed) is far off
  ref, _ = res["frames"][0]
  _, other = res["frames"][1]
  assert np.abs(ref.astype(int) - other.astype(int)).mean() > MAD_BOUND[domain]


def test_parity_summary_per_body():
  # Two frames: body 1 scored twice (IoU 1.0 and 0.9), body 2 once (0.96).
  res = {"mad": [2.0, 4.0], "iou": [{1: 1.0, 2: 0.96}, {1: 0.9}], "frames": []}
  row = parity.parity_row("cartpole", res, ["", "cart", "pole"], seeds=2)
  assert row["frames"] == 2 and row["seeds"] == 2
  assert row["mad_mean"] == 3.0 and row["mad_max"] == 4.0
  assert row["iou_min"] == 0.9 and row["iou_mean"] == pytest.approx((1.0 + 0.96 + 0.9) / 3)
  assert row["frac_body_iou_ge_095"] == pytest.approx(2 / 3)
  assert row["iou_per_body"] == {"1:cart": 0.95, "2:pole": 0.96}
  assert row["iou_min_per_body"] == {"1:cart": 0.9, "2:pole": 0.96}
  assert row["frac_ge_095_per_body"] == {"1:cart": 0.5, "2:pole": 1.0}
  assert row["frames_per_body"] == {"1:cart": 2, "2:pole": 1}
  table = parity.parity_markdown([dict(row, min_pixels=10)])
  assert "| cartpole | 10 | 2 | 3.00 / 4.00 | 3 |" in table
  assert "1:cart (0.950 mean, 50% ≥ 0.95 of 2 frames)" in table
