"""Tests of `dmcr_jax.augment` (the paper's appendix augmentations).

For every augmentation: the jitted batch call equals the single-sample function
applied per sample, and both equal a plain NumPy reference written here from the
parameters the call drew; the frames of a stack and the o/o′ of a pair see the
same parameters; shape and dtype are kept and values saturate instead of
wrapping; the drawn parameters lie in their documented ranges with the expected
frequencies (Rotate really produces each of its four angles ~1/4 of the time).
Small images (12×16) keep compile times low; one 84×84×9 case per augmentation.
"""

import colorsys
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax import augment

BASE = [n for n in augment.NAMES if "+" not in n]
KEY = jax.random.key(42)
SMALL = (4, 12, 16, 6)       # non-square on purpose: catches H/W mix-ups
SMALL_SQUARE = (4, 12, 12, 6)  # rotate needs square images


def _images(shape, seed=0):
  return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


def _small(name):
  return SMALL_SQUARE if name == "rotate" else SMALL


def _np(tree):
  return jax.tree_util.tree_map(np.asarray, tree)


# --------------------------------------------------------------------------- #
# Plain NumPy references: (params of one sample, image (H, W, C)) -> image.
# --------------------------------------------------------------------------- #


def _scaled(v, side):
  return max(1, int(round(v * side / 84)))


def _hash32(x):
  x = np.asarray(x, np.uint32)
  with np.errstate(over="ignore"):
    x = x ^ (x >> np.uint32(16))
    x = x * np.uint32(0x7FEB352D)
    x = x ^ (x >> np.uint32(15))
    x = x * np.uint32(0x846CA68B)
    return x ^ (x >> np.uint32(16))


def _resize_axis_fixed_point(a, axis, up):
  """Bilinear n → up along `axis`, half-pixel centres, weights in 1/256 (int64)."""
  n = a.shape[axis]
  out = []
  for u in range(up):
    s = min(max((u + 0.5) * n / up - 0.5, 0.0), n - 1.0)
    i0 = int(math.floor(s))
    i1 = min(i0 + 1, n - 1)
    w1 = int(round((s - i0) * 256))
    out.append((256 - w1) * np.take(a, i0, axis=axis) + w1 * np.take(a, i1, axis=axis))
  return np.stack(out, axis=axis)


def ref_none(p, x):
  return x


def ref_rad(p, x, scale=100 / 84):
  h, w, _ = x.shape
  up = _resize_axis_fixed_point(x.astype(np.int64), 0, round(h * scale))
  up = _resize_axis_fixed_point(up, 1, round(w * scale))
  crop = up[p["dy"]:p["dy"] + h, p["dx"]:p["dx"] + w]
  return ((crop + 32768) >> 16).astype(np.uint8)


def ref_cutout_color(p, x):
  y = x.copy()
  y[p["top"]:p["top"] + p["h"], p["left"]:p["left"] + p["w"]] = np.tile(
      p["color"], x.shape[-1] // 3)
  return y


def _rounded_gaussian_np(seed, n, std=1.0):
  k = math.ceil(6 * std)
  cdf = [0.5 * (1 + math.erf((j + 0.5) / (std * math.sqrt(2)))) for j in range(-k, k)]
  thresholds = np.round(np.array(cdf) * 65536).astype(np.int64)
  u = _hash32(_hash32(np.arange(n, dtype=np.uint32)) ^ np.uint32(seed)) >> 16
  u = u.astype(np.int64)
  return np.searchsorted(thresholds, u, side="right") - k


def _ref_drq(p, x, pad, noisy):
  h, w, c = x.shape
  y = np.pad(x, ((pad, pad), (pad, pad), (0, 0)), mode="edge")[
      p["dy"]:p["dy"] + h, p["dx"]:p["dx"] + w]
  if not noisy:
    return y
  noise = _rounded_gaussian_np(p["noise_seed"], h * w * 3).reshape(h, w, 3)
  return np.clip(y.astype(np.int64) + np.tile(noise, c // 3), 0, 255).astype(np.uint8)


def _ref_translate(p, x, pad):
  h, w, c = x.shape
  big = np.empty((h + 2 * pad, w + 2 * pad, c), np.uint8)
  big[...] = np.tile(p["color"], c // 3)
  big[pad + p["ty"]:pad + p["ty"] + h, pad + p["tx"]:pad + p["tx"] + w] = x
  return big[pad:pad + h, pad:pad + w]


def ref_rotate(p, x):
  return np.rot90(x, int(p["k"])).copy()


def ref_vertical_flip(p, x):
  return np.rot90(x, 2).copy() if p["flip"] else x


def ref_window(p, x):
  h, w, _ = x.shape
  sh, sw = _scaled(64, h), _scaled(64, w)
  y = np.zeros_like(x)
  y[p["top"]:p["top"] + sh, p["left"]:p["left"] + sw] = x[
      p["top"]:p["top"] + sh, p["left"]:p["left"] + sw]
  return y


def ref_cj(p, x):
  h, w, c = x.shape
  out = np.empty((h, w, c), np.float64)
  for f in range(c // 3):
    z = x[..., 3 * f:3 * f + 3].astype(np.float64) / 255

    def contrast(z):
      mean = z.mean(axis=(0, 1), keepdims=True)
      return np.clip((z - mean) * p["contrast"] + mean, 0, 1)

    def hsv(z):
      res = np.empty_like(z)
      for i in range(h):
        for j in range(w):
          hh, ss, vv = colorsys.rgb_to_hsv(*z[i, j])
          res[i, j] = colorsys.hsv_to_rgb((hh + p["hue"]) % 1.0,
                                          min(max(ss * p["saturation"], 0), 1),
                                          min(max(vv * p["brightness"], 0), 1))
      return res

    out[..., 3 * f:3 * f + 3] = (hsv(contrast(z)) if p["contrast_first"]
                                 else contrast(hsv(z)))
  return np.clip(np.round(out * 255), 0, 255).astype(np.uint8)


def ref_nr(p, x):
  h, w, c = x.shape
  k = p["kernel"].astype(np.float64)
  out = np.empty((h, w, c), np.float64)
  for f in range(c // 3):
    z = x[..., 3 * f:3 * f + 3].astype(np.float64) / 255
    z = np.pad(z, ((1, 1), (1, 1), (0, 0)))
    acc = np.zeros((h, w, 3))
    for dy in range(3):
      for dx in range(3):
        acc += z[dy:dy + h, dx:dx + w] @ k[dy, dx]
    out[..., 3 * f:3 * f + 3] = acc
  return np.clip(np.round(out * 255), 0, 255).astype(np.uint8)


REFS = {
    "none": ref_none,
    "rad": ref_rad,
    "cutout_color": ref_cutout_color,
    "drq": lambda p, x: _ref_drq(p, x, 4, True),
    "drq_no_noise": lambda p, x: _ref_drq(p, x, 4, False),
    "large_drq": lambda p, x: _ref_drq(p, x, 12, True),
    "large_drq_no_noise": lambda p, x: _ref_drq(p, x, 12, False),
    "translate": lambda p, x: _ref_translate(p, x, 4),
    "large_translate": lambda p, x: _ref_translate(p, x, 12),
    "rotate": ref_rotate,
    "vertical_flip": ref_vertical_flip,
    "window": ref_window,
    "cj": ref_cj,
    "nr": ref_nr,
}
FLOAT_MATH = {"cj", "nr"}  # float32 in the module vs float64 here: ±1 allowed


def _reference(name, params, x, per_batch):
  out = []
  for i in range(x.shape[0]):
    p = params if per_batch else jax.tree_util.tree_map(lambda a: a[i], params)
    out.append(REFS[name](p, x[i]))
  return np.stack(out)


def _assert_matches_reference(name, got, want):
  assert got.dtype == np.uint8 and got.shape == want.shape
  if name in FLOAT_MATH:
    diff = np.abs(got.astype(int) - want.astype(int))
    assert diff.max() <= 1, (name, diff.max())
    assert (diff == 0).mean() > 0.97, (name, (diff == 0).mean())
  else:
    np.testing.assert_array_equal(got, want)


def test_registry_covers_the_paper():
  assert set(REFS) == set(BASE)
  assert len(set(BASE) - {"none", "cj", "nr"}) == 11  # the appendix's eleven
  assert {"drq", "cj+drq", "nr+drq"} <= set(augment.NAMES)


# --------------------------------------------------------------------------- #
# Per augmentation: batch == single == NumPy, consistency, determinism.
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("name", BASE)
def test_batch_equals_single_equals_numpy(name):
  aug = augment.get(name)
  x = _images(_small(name))
  got = np.asarray(aug(KEY, jnp.asarray(x)))
  params = _np(aug.params(KEY, x.shape[0], x.shape[1:3]))
  _assert_matches_reference(name, got, _reference(name, params, x, aug.per_batch))
  keys = augment.sample_keys(KEY, x.shape[0])
  one = jax.jit(aug.one)
  for i in range(2):  # the single-sample function on sample i's key
    y = one(KEY if aug.per_batch else keys[i], jnp.asarray(x[i]))
    np.testing.assert_array_equal(np.asarray(y), got[i])


@pytest.mark.parametrize("name", BASE)
def test_full_size_pair_84x84x9(name):
  """(obs, next_obs) of 84×84×9 in one call: each matches the NumPy reference
  under the one set of parameters drawn per sample, so o and o′ share them."""
  aug = augment.get(name)
  o, o2 = _images((2, 84, 84, 9), seed=1), _images((2, 84, 84, 9), seed=2)
  got = _np(aug(KEY, (jnp.asarray(o), jnp.asarray(o2))))
  params = _np(aug.params(KEY, 2, (84, 84)))
  _assert_matches_reference(name, got[0], _reference(name, params, o, aug.per_batch))
  _assert_matches_reference(name, got[1], _reference(name, params, o2, aug.per_batch))
  if name != "none":
    assert (got[0] != o).any()


def test_stack_frames_transform_as_if_alone_and_any_pytree_works():
  aug = augment.get("drq")
  x = jnp.asarray(_images((4, 12, 16, 9), seed=2))
  full = np.asarray(aug(KEY, x))
  for f in range(3):
    np.testing.assert_array_equal(full[..., 3 * f:3 * f + 3],
                                  np.asarray(aug(KEY, x[..., 3 * f:3 * f + 3])))
  as_dict = _np(jax.jit(aug)(KEY, {"obs": x[..., :6], "next_obs": x[..., 6:]}))
  np.testing.assert_array_equal(as_dict["obs"], full[..., :6])
  np.testing.assert_array_equal(as_dict["next_obs"], full[..., 6:])


@pytest.mark.parametrize("name", BASE)
def test_deterministic_per_key(name):
  aug = augment.get(name)
  x = jnp.asarray(_images(_small(name), seed=3))
  a, b = np.asarray(aug(KEY, x)), np.asarray(aug(KEY, x))
  np.testing.assert_array_equal(a, b)
  if name != "none":
    c = np.asarray(aug(jax.random.key(7), x))
    assert (a != c).any()


def test_raw_prng_keys_work_and_samples_do_not_depend_on_batch_size():
  aug = augment.get("drq")
  x = jnp.asarray(_images((4, 12, 16, 6), seed=4))
  raw = jax.random.PRNGKey(3)
  np.testing.assert_array_equal(np.asarray(aug(raw, x)), np.asarray(aug(raw, x)))
  # sample i's key is fold_in(key, i) whatever the batch size
  np.testing.assert_array_equal(jax.random.key_data(augment.sample_keys(KEY, 2)),
                                jax.random.key_data(augment.sample_keys(KEY, 4))[:2])


# --------------------------------------------------------------------------- #
# Ranges: saturation, not wrap-around; parameter statistics.
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("name", ["drq", "large_drq"])
def test_noise_saturates_and_is_a_rounded_unit_gaussian(name):
  aug = augment.get(name)
  flat = lambda v: jnp.full((2, 84, 84, 9), v, jnp.uint8)
  white, black, grey = _np(aug(KEY, (flat(255), flat(0), flat(128))))
  assert white.min() >= 255 - 6 and black.max() <= 6  # saturates, no wrap-around
  n = grey.astype(int) - 128  # a crop of a flat image is flat: this is the noise
  assert abs(n.mean()) < 0.02
  assert abs(n.std() - math.sqrt(1 + 1 / 12)) < 0.02  # var of round(N(0, 1))
  assert abs((n == 0).mean() - 0.3829) < 0.01
  assert abs((n == 1).mean() - 0.2417) < 0.01


def _params(name, batch=4096, hw=(84, 84), key=KEY):
  return _np(augment.get(name).params(key, batch, hw))


def _assert_uniform_ints(v, lo, hi):
  """All of lo..hi occur, nothing else, with roughly equal frequencies."""
  v = np.asarray(v).ravel()
  assert v.min() == lo and v.max() == hi
  counts = np.bincount(v - lo, minlength=hi - lo + 1)
  expected = v.size / (hi - lo + 1)
  assert np.all(np.abs(counts - expected) < 5 * math.sqrt(expected) + 1), counts


def test_param_ranges_crops_and_shifts():
  p = _params("rad")
  _assert_uniform_ints(p["dy"], 0, 16)
  _assert_uniform_ints(p["dx"], 0, 16)
  for name, pad in [("drq", 4), ("drq_no_noise", 4), ("large_drq", 12),
                    ("large_drq_no_noise", 12)]:
    p = _params(name)
    _assert_uniform_ints(p["dy"], 0, 2 * pad)
    _assert_uniform_ints(p["dx"], 0, 2 * pad)
  for name, pad in [("translate", 4), ("large_translate", 12)]:
    p = _params(name)
    _assert_uniform_ints(p["ty"], -pad, pad)
    _assert_uniform_ints(p["tx"], -pad, pad)
    _assert_uniform_ints(p["color"], 0, 255)
  p = _params("window")
  _assert_uniform_ints(p["top"], 0, 20)
  _assert_uniform_ints(p["left"], 0, 20)
  p = _params("window", hw=(12, 16))  # lens scaled to 9×12: offsets 0..3, 0..4
  _assert_uniform_ints(p["top"], 0, 3)
  _assert_uniform_ints(p["left"], 0, 4)


def test_param_ranges_cutout_color():
  p = _params("cutout_color")
  _assert_uniform_ints(p["h"], 10, 29)
  _assert_uniform_ints(p["w"], 10, 29)
  _assert_uniform_ints(p["color"], 0, 255)
  assert np.all(p["top"] >= 0) and np.all(p["top"] + p["h"] <= 84)
  assert np.all(p["left"] >= 0) and np.all(p["left"] + p["w"] <= 84)
  assert p["top"].min() == 0 and (p["top"] + p["h"]).max() == 84


def test_rotate_produces_each_angle_a_quarter_of_the_time():
  """The original RotateAug was a silent no-op: check the pixels, not just k."""
  n = 4096
  x = np.broadcast_to(np.arange(75, dtype=np.uint8).reshape(5, 5, 3), (n, 5, 5, 3))
  y = np.asarray(augment.get("rotate")(KEY, jnp.asarray(x)))
  found = np.array([[np.array_equal(y[i], np.rot90(x[i], k)) for k in range(4)]
                    for i in range(n)])
  assert np.all(found.sum(axis=1) == 1)  # every output is exactly one rotation
  counts = found.sum(axis=0)
  assert np.all(np.abs(counts - n / 4) < 5 * math.sqrt(n * 3 / 16)), counts
  k = _params("rotate", batch=n, hw=(5, 5))["k"]
  np.testing.assert_array_equal(found.argmax(axis=1), k)


def test_vertical_flip_rotates_about_half_the_batch_by_180():
  n = 4096
  x = np.broadcast_to(np.arange(72, dtype=np.uint8).reshape(4, 6, 3), (n, 4, 6, 3))
  y = np.asarray(augment.get("vertical_flip")(KEY, jnp.asarray(x)))
  rotated = np.array([np.array_equal(y[i], x[i, ::-1, ::-1]) for i in range(n)])
  same = np.array([np.array_equal(y[i], x[i]) for i in range(n)])
  assert np.all(rotated ^ same)
  assert abs(rotated.mean() - 0.5) < 5 * math.sqrt(0.25 / n)


def test_param_ranges_color_jitter():
  p = _params("cj")
  for f in ("brightness", "contrast", "saturation"):
    assert 0.6 <= p[f].min() < 0.61 and 1.39 < p[f].max() < 1.4
    assert abs(p[f].mean() - 1.0) < 0.02
  assert -0.5 <= p["hue"].min() < -0.49 and 0.49 < p["hue"].max() < 0.5
  assert abs(p["hue"].mean()) < 0.02
  assert abs(p["contrast_first"].mean() - 0.5) < 0.04


def test_network_randomization_kernel_is_xavier_normal_and_per_batch():
  kernels = np.stack([_params("nr", batch=1, key=jax.random.key(s))["kernel"]
                      for s in range(100)])
  assert kernels.shape == (100, 3, 3, 3, 3)
  assert abs(augment.NR_INIT_STD - math.sqrt(2 / 54)) < 1e-12
  assert abs(kernels.std() / augment.NR_INIT_STD - 1) < 0.05
  assert abs(kernels.mean()) < 0.01
  within_1_std = np.mean(np.abs(kernels) < augment.NR_INIT_STD)
  assert within_1_std == pytest.approx(0.6827, abs=0.03)
  # one conv per batch: identical inputs give identical outputs across the batch
  x = jnp.asarray(np.repeat(_images((1, 12, 16, 6), seed=5), 4, axis=0))
  y = np.asarray(augment.get("nr")(KEY, x))
  assert all(np.array_equal(y[0], y[i]) for i in range(1, 4))


def test_rad_fixed_point_is_bilinear():
  """The 8-bit fixed-point zoom is within one grey level of float bilinear."""
  x = _images((1, 84, 84, 3), seed=6)[0].astype(np.float64)
  src = np.clip((np.arange(100) + 0.5) * 84 / 100 - 0.5, 0, 83)
  i0 = np.floor(src).astype(int)
  i1 = np.minimum(i0 + 1, 83)
  f = src - i0
  rows = x[i0] * (1 - f)[:, None, None] + x[i1] * f[:, None, None]
  up = rows[:, i0] * (1 - f)[None, :, None] + rows[:, i1] * f[None, :, None]
  fixed = ref_rad({"dy": 16, "dx": 0}, x.astype(np.uint8))
  assert np.abs(fixed.astype(int) - np.round(up[16:100, 0:84])).max() <= 1


# --------------------------------------------------------------------------- #
# Registry, composition, errors, compilation.
# --------------------------------------------------------------------------- #


def test_composition_applies_stages_in_order_with_folded_keys():
  x = jnp.asarray(_images((4, 12, 16, 6), seed=7))
  got = np.asarray(augment.get("cj+drq")(KEY, x))
  cj = augment.get("cj")(jax.random.fold_in(KEY, 0), x)
  want = augment.get("drq")(jax.random.fold_in(KEY, 1), cj)
  np.testing.assert_array_equal(got, np.asarray(want))
  assert augment.get("cj+drq") is augment.get("cj+drq")  # cached, compiled once


def test_composition_keeps_pair_consistency():
  aug = augment.get("nr+drq")
  o = jnp.asarray(_images(SMALL, seed=0))
  o2 = jnp.asarray(_images(SMALL, seed=8))
  pair = aug(KEY, (o, o2))
  np.testing.assert_array_equal(np.asarray(pair[0]), np.asarray(aug(KEY, o)))
  np.testing.assert_array_equal(np.asarray(pair[1]), np.asarray(aug(KEY, o2)))


def test_composition_runs_inside_jit():
  aug = augment.get("vertical_flip+drq_no_noise")
  x = jnp.asarray(_images(SMALL, seed=0))
  np.testing.assert_array_equal(np.asarray(jax.jit(aug)(KEY, x)),
                                np.asarray(aug(KEY, x)))


def test_unknown_names_raise_listing_the_valid_ones():
  with pytest.raises(ValueError) as err:
    augment.get("crop")
  for name in augment.NAMES:
    assert name in str(err.value)
  with pytest.raises(ValueError, match="foo"):
    augment.get("drq+foo")


def test_bad_inputs_raise():
  aug = augment.get("drq")
  with pytest.raises(TypeError):
    aug(KEY, jnp.zeros((2, 8, 8, 3), jnp.float32))
  with pytest.raises(ValueError):
    aug(KEY, jnp.zeros((2, 8, 8, 4), jnp.uint8))
  with pytest.raises(ValueError):
    aug(KEY, (jnp.zeros((2, 8, 8, 3), jnp.uint8), jnp.zeros((2, 8, 9, 3), jnp.uint8)))
  with pytest.raises(ValueError, match="square"):
    augment.get("rotate")(KEY, jnp.zeros((2, 8, 10, 3), jnp.uint8))


def test_compiled_once_for_new_keys():
  traces = []

  def apply(p, x):
    traces.append(1)
    return jnp.where(p["flip"], x[::-1], x)

  aug = augment.Augmentation("counting", augment.get("vertical_flip").sample, apply)
  x = jnp.asarray(_images((4, 12, 16, 6), seed=9))
  for s in range(3):
    aug(jax.random.key(s), x)
  assert len(traces) == 1
