"""Jit-compiled, deterministic image augmentations of the DMCR paper's appendix.

The eleven augmentations of the appendix's "Augmentation Comparison" plus the
two "alterations" of the main results (Sec. 2 and 5, Table 3) and the paper's
pipelines SAC+AUG, SAC+CJ+AUG and SAC+NR+AUG (Sec. 3.2: CJ or NR, then the DrQ
crop). `get(name)` returns one; `NAMES` lists them; ``"a+b"`` applies a, then b.
Call it as ``aug(key, obs)`` or ``aug(key, (obs, next_obs))`` (any pytree):
uint8 images ``(B, H, W, 3·stack)``, channels-last, in; same shapes, uint8, out.

- ``rad``: RAD, zoom 84→100 and a random 84×84 crop (appendix item 1);
- ``cutout_color``: Cutout Color (2);
- ``drq``, ``drq_no_noise``: DrQ, 4-px replicate pad and crop, ± noise (3, 4);
- ``large_drq``, ``large_drq_no_noise``: the same with 12 px (5, 6);
- ``translate``, ``large_translate``: shift in a 4/12-px random-colour border (7, 8);
- ``rotate``: by 0, 90, 180 or 270° (9);
- ``vertical_flip``: 180° rotation of part of the batch (10);
- ``window``: a lens shows the image, 0 elsewhere (11);
- ``cj``, ``nr``: Color Jitter, Network Randomization;
- ``drq``, ``cj+drq``, ``nr+drq``: the pipelines of SAC+AUG, SAC+CJ+AUG, SAC+NR+AUG;
- ``none``: the identity (for baselines and benchmarks).

Your own augmentation: write it for ONE sample, ``fn(key, image) -> image`` on a
uint8 ``(H, W, 3·stack)`` image (the built-ins' convention, see below), then
``register("mine", fn)`` so that `get`, ``"mine+drq"``, `SACConfig.aug` and
``dmcr-train --aug`` know it, or name it by import path, ``"package.module:function"``
(`load`), which every one of those accepts too. `check` runs the properties the
learner relies on against real rendered observations (`dmcr_jax.augment_check`).

Randomness (appendix: identical for a sample's o and o′ and for the frames of its
stack; deterministically seeded): each augmentation is written for ONE sample as
``sample(key, (H, W)) -> params`` and ``apply(params, image (H, W, C)) -> image``.
Parameters never depend on C, so every frame of the stack gets them; the batch is
a `jax.vmap` at the edge; every array of a pytree is transformed with the same
parameters. Sample i draws from ``fold_in(key, i)`` (`sample_keys`), so its draw
does not depend on the batch size; Network Randomization draws one convolution
per call from ``key``. The same key gives bit-identical output on a backend:
integer arithmetic, or float32 rounded half to even.

Image sizes: every default is the paper's value for 84×84 images. Shifts (DrQ's
and Translate's pads) stay in pixels at any size; RAD zooms by 100/84; occluders
(Cutout Color's box, Window's lens) scale with the side, ``round(v · side / 84)``.
Rotate needs square images (ValueError otherwise). Where the paper gives no
value, each factory's docstring says which original (RAD, DrQ, NR, or DMCR's code
release) it follows.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import math
import os
import re
import sys
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

Params = Any
Images = Any  # a uint8 array (B, H, W, 3·stack) or a pytree of such arrays
SampleFn = Callable[[jax.Array, tuple[int, int]], Params]
ApplyFn = Callable[[Params, jax.Array], jax.Array]

_REF_SIDE = 84  # the paper's image size (its Table 6); defaults are for 84×84


# --------------------------------------------------------------------------- #
# The two types: one augmentation, and a composition of augmentations.
# --------------------------------------------------------------------------- #


@dataclasses.dataclass(frozen=True, eq=False)
class Augmentation:
  """One augmentation: a per-sample parameter draw and a per-sample transform.

  Calling it augments a batch (see `__call__`); `one` augments a single image;
  `params` returns the parameters a batch call would draw (for logging and tests).

  Attributes:
    name: the registry name (e.g. ``"drq"``).
    sample: ``sample(key, (H, W)) -> params``, the random draw for one sample.
    apply: ``apply(params, image) -> image`` for one uint8 image (H, W, C), C a
      multiple of 3 (frames stacked on channels); deterministic given params.
    per_batch: if True, one draw from ``key`` is shared by the whole batch
      (Network Randomization); otherwise sample ``i`` draws from
      ``fold_in(key, i)``.
  """
  name: str
  sample: SampleFn
  apply: ApplyFn
  per_batch: bool = False

  def __post_init__(self):
    object.__setattr__(self, "_jitted", jax.jit(functools.partial(_augment, self)))
    object.__setattr__(self, "_jitted_params", jax.jit(
        functools.partial(_draw_params, self), static_argnums=1))

  def __call__(self, key: jax.Array, images: Images) -> Images:
    """Augments a batch (jit-compiled; also callable inside an outer `jit`).

    Two compiled steps: `sample_keys` (shared by all augmentations, so compiled
    once per batch size) and the augmentation itself; inside an outer `jit` both
    are traced into one program.

    Args:
      key: a `jax.random` key (typed or raw uint32).
      images: a uint8 array (B, H, W, 3·stack), or a pytree (tuple, dict, …) of
        such arrays with the same B, H, W, e.g. ``(obs, next_obs)``; sample ``i``
        of every array gets the same parameters.

    Returns:
      The augmented images: the same structure, shapes and dtype (uint8).
    """
    batch = _check_images(images)[0]
    return self._jitted(key if self.per_batch else sample_keys(key, batch), images)

  def one(self, key: jax.Array, image: jax.Array) -> jax.Array:
    """Augments one uint8 image (H, W, C) with parameters drawn from `key`.

    For a per-sample augmentation, ``aug(key, x)[i] == aug.one(fold_in(key, i),
    x[i])``; for a per-batch one, ``aug(key, x)[i] == aug.one(key, x[i])``.

    Args:
      key: a `jax.random` key.
      image: uint8 (H, W, C), C a multiple of 3.

    Returns:
      uint8 (H, W, C).
    """
    _check_leaf(image, rank=3)
    return self.apply(self.sample(key, tuple(image.shape[:2])), image)

  def params(self, key: jax.Array, batch: int, hw: tuple[int, int]) -> Params:
    """The parameters that ``aug(key, images)`` draws for a (batch, H, W, ·) input.

    Args:
      key: a `jax.random` key.
      batch: the batch size B (static).
      hw: (H, W) (static).

    Returns:
      A pytree of arrays with leading axis B (or unbatched if `per_batch`).
    """
    return self._jitted_params(key if self.per_batch else sample_keys(key, batch),
                               tuple(hw))


@dataclasses.dataclass(frozen=True, eq=False)
class Composed:
  """Augmentations applied in order, e.g. ``"cj+drq"``: Color Jitter, then DrQ.

  Stage ``s`` draws from ``fold_in(key, s)``, so every stage is independent and
  each keeps the o/o′ and frame-stack consistency of `Augmentation`.

  Attributes:
    name: the ``+``-joined name.
    stages: the augmentations, first applied first.
  """
  name: str
  stages: tuple[Augmentation, ...]

  def __call__(self, key: jax.Array, images: Images) -> Images:
    """Augments a batch; same contract as `Augmentation.__call__`.

    Args:
      key: a `jax.random` key.
      images: a uint8 array (B, H, W, 3·stack) or a pytree of such arrays.

    Returns:
      The augmented images, same structure, shapes and dtype.
    """
    for s, stage in enumerate(self.stages):
      images = stage(jax.random.fold_in(key, s), images)
    return images


def _check_leaf(x, rank: int):
  if getattr(x, "dtype", None) != jnp.uint8:
    raise TypeError(f"augmentations take uint8 images, got dtype "
                    f"{getattr(x, 'dtype', type(x))}")
  if x.ndim != rank:
    dims = "B, H, W, 3·stack" if rank == 4 else "H, W, 3·stack"
    raise ValueError(f"expected a rank-{rank} image array ({dims}), got shape "
                     f"{x.shape}")
  if x.shape[-1] % 3:
    raise ValueError(f"channels must be a multiple of 3 (RGB frames stacked on "
                     f"the last axis), got {x.shape[-1]}")


def _check_images(images) -> tuple[int, int, int]:
  """Checks a pytree of uint8 (B, H, W, 3·k) arrays; returns the shared (B, H, W)."""
  leaves = jax.tree_util.tree_leaves(images)
  if not leaves:
    raise ValueError("no images given")
  for leaf in leaves:
    _check_leaf(leaf, rank=4)
  shape = leaves[0].shape[:3]
  for leaf in leaves[1:]:
    if leaf.shape[:3] != shape:
      raise ValueError(f"all arrays must share (B, H, W); got {leaf.shape[:3]} "
                       f"and {shape}")
  return shape


@functools.partial(jax.jit, static_argnums=1)
def sample_keys(key: jax.Array, batch: int) -> jax.Array:
  """The per-sample keys of a batch: ``fold_in(key, i)`` for i = 0 … batch − 1.

  Sample i's draw therefore does not depend on the batch size, and
  ``aug(key, x)[i] == aug.one(sample_keys(key, B)[i], x[i])``.

  Args:
    key: a `jax.random` key (typed or raw uint32).
    batch: the batch size (static).

  Returns:
    `batch` keys, stacked on a leading axis.
  """
  return jax.vmap(jax.random.fold_in, in_axes=(None, 0))(
      key, jnp.arange(batch, dtype=jnp.uint32))


def _draw_params(aug: Augmentation, keys, hw: tuple[int, int]):
  """Per-sample params from per-sample `keys`, or one draw from one key."""
  if aug.per_batch:
    return aug.sample(keys, hw)
  return jax.vmap(aug.sample, in_axes=(0, None))(keys, hw)


def _augment(aug: Augmentation, keys, images):
  """Batches `aug` over a pytree of (B, H, W, C) uint8 arrays (one param draw).

  `keys` holds one key per sample (`sample_keys`), or one key if `aug.per_batch`.
  """
  _, h, w = _check_images(images)
  params = _draw_params(aug, keys, (h, w))
  apply = jax.vmap(aug.apply, in_axes=(None if aug.per_batch else 0, 0))
  return jax.tree_util.tree_map(lambda x: apply(params, x), images)


# --------------------------------------------------------------------------- #
# Helpers for one image (H, W, C).
# --------------------------------------------------------------------------- #


def _key_words(key: jax.Array) -> jax.Array:
  """The raw uint32 words of a key (typed `jax.random.key` or raw `PRNGKey`)."""
  if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
    key = jax.random.key_data(key)
  return jnp.ravel(key).astype(jnp.uint32)


def _words(key: jax.Array, n: int) -> jax.Array:
  """n pseudo-random uint32 words, a hash of the (per-sample) key's bits.

  Word j is ``_hash32(_hash32(k0 + j·0x9E3779B9) ^ k1) …`` over the key's words
  k0, k1, …: far cheaper to compile and run than a threefry call per sample,
  and the per-sample key itself comes from `jax.random.fold_in`.
  """
  kw = _key_words(key)
  w = _hash32(kw[0] + jnp.arange(n, dtype=jnp.uint32) * jnp.uint32(0x9E3779B9))
  for i in range(1, kw.shape[0]):
    w = _hash32(w ^ kw[i])
  return w


def _randint(word: jax.Array, lo, hi) -> jax.Array:
  """An int32 in [lo, hi) from a uint32 word: lo + ((word >> 16) · (hi − lo)) >> 16.

  Exact integer arithmetic (hi − lo ≤ 2^16; `lo`, `hi` may be traced); every value
  has probability (hi − lo)^-1 to within 2^-16.
  """
  span = jnp.asarray(hi - lo).astype(jnp.uint32)
  return jnp.asarray(lo, jnp.int32) + (((word >> 16) * span) >> 16).astype(jnp.int32)


def _unit(word: jax.Array) -> jax.Array:
  """A float32 in [0, 1) from a uint32 word (its top 24 bits)."""
  return (word >> 8).astype(jnp.float32) * jnp.float32(2.0 ** -24)


def _hash32(x: jax.Array) -> jax.Array:
  """A 32-bit integer hash (Wellons' "lowbias32"), elementwise on uint32."""
  x = x ^ (x >> 16)
  x = x * jnp.uint32(0x7FEB352D)
  x = x ^ (x >> 15)
  x = x * jnp.uint32(0x846CA68B)
  return x ^ (x >> 16)


@functools.lru_cache(maxsize=None)
def _rounded_gaussian_thresholds(std: float) -> tuple[int, np.ndarray]:
  """(K, T): P(round(N(0, std²)) ≤ k) · 2^16 for k = −K … K−1, rounded."""
  k_max = max(1, math.ceil(6 * std))
  ks = np.arange(-k_max, k_max)
  cdf = np.array([0.5 * (1 + math.erf((k + 0.5) / (std * math.sqrt(2)))) for k in ks])
  return k_max, np.round(cdf * 65536).astype(np.uint32)


def _rounded_gaussian(seed: jax.Array, shape: tuple[int, ...], std: float) -> jax.Array:
  """Int32 noise round(N(0, std²)), clipped to ±⌈6·std⌉, a function of `seed`.

  Element ``i`` (row-major) takes the top 16 bits of
  ``_hash32(_hash32(i) ^ seed)`` through the inverse CDF of the rounded normal:
  exact integer arithmetic, cheap on any backend (no erf_inv), reproducible in
  NumPy.
  """
  k_max, thresholds = _rounded_gaussian_thresholds(float(std))
  idx = jnp.arange(math.prod(shape), dtype=jnp.uint32)
  u = (_hash32(_hash32(idx) ^ seed) >> 16)[:, None]
  n = jnp.sum(u >= jnp.asarray(thresholds)[None, :], axis=1, dtype=jnp.int32)
  return (n - k_max).reshape(shape)


def _scaled(v: float, side: int) -> int:
  """A length given for 84-pixel images, scaled to `side` pixels (at least 1)."""
  return max(1, int(round(v * side / _REF_SIDE)))


def _tile_frames(rgb: jax.Array, channels: int) -> jax.Array:
  """Repeats a (..., 3) array over the frames of a (..., channels) image."""
  return jnp.tile(rgb, (1,) * (rgb.ndim - 1) + (channels // 3,))


def _to_uint8(x: jax.Array) -> jax.Array:
  """Rounds float32 in 0..255 units half-to-even and clips to uint8."""
  return jnp.clip(jnp.round(x), 0, 255).astype(jnp.uint8)


def _gather(image: jax.Array, rows: jax.Array, cols: jax.Array) -> jax.Array:
  """``image[rows][:, cols]`` for integer index vectors (in range).

  Two one-axis gathers, columns first: batched, they index with (B, side)
  vectors, where the one-gather form ``image[rows[:, None], cols[None, :]]``
  has XLA build and read an index tuple per pixel. Columns first: on XLA:CPU the
  rows-first order gives batched pairs of outputs a transposed layout and a copy.
  "clip" skips the out-of-bounds fill.
  """
  return jnp.take(jnp.take(image, cols, axis=1, mode="clip"), rows, axis=0, mode="clip")


def _box_mask(h: int, w: int, top, left, box_h, box_w) -> jax.Array:
  """Bool (h, w, 1): True inside the box [top, top+box_h) × [left, left+box_w)."""
  r = jnp.arange(h)[:, None, None]
  c = jnp.arange(w)[None, :, None]
  return (r >= top) & (r < top + box_h) & (c >= left) & (c < left + box_w)


# --------------------------------------------------------------------------- #
# The augmentations (factories: keyword parameters in, `Augmentation` out).
# --------------------------------------------------------------------------- #


def identity() -> Augmentation:
  """No augmentation (``"none"``): returns the images unchanged.

  Returns:
    An `Augmentation`.
  """
  return Augmentation("none", lambda key, hw: {}, lambda p, x: x)


@functools.lru_cache(maxsize=None)
def _bilinear_table(n: int, up: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """1-D bilinear resize n → up, half-pixel centres (OpenCV INTER_LINEAR).

  Returns (i0, i1, w1) of length `up`: output u = (256-w1)·in[i0] + w1·in[i1],
  in 1/256 units, source coordinate (u + 0.5)·n/up − 0.5 clamped to [0, n−1].
  """
  src = np.clip((np.arange(up) + 0.5) * n / up - 0.5, 0, n - 1)
  i0 = np.floor(src).astype(np.int32)
  i1 = np.minimum(i0 + 1, n - 1).astype(np.int32)
  w1 = np.round((src - i0) * 256).astype(np.int32)
  return i0, i1, w1


def rad(scale: float = 100 / 84) -> Augmentation:
  """RAD: bilinear zoom 84→100, then a random 84×84 crop (paper appendix, item 1).

  Imitates RAD (Laskin et al. 2020), which renders at 100×100 and crops 84×84.
  The zoom maps side n to ``round(n · scale)`` (100 for 84) with half-pixel
  centres like OpenCV's INTER_LINEAR, in fixed point (weights in 1/256, the
  result rounded half up), so it is exact integer arithmetic. The crop's top-left
  corner is uniform over all ``round(n·scale) − n + 1`` positions per axis
  (0…16 at 84), as in RAD's `random_crop`. Only the cropped part is computed.

  Args:
    scale: zoom factor (the paper's 100/84).

  Returns:
    An `Augmentation`; params ``dy, dx`` (int32 crop offsets).
  """
  def sample(key, hw):
    (h, w), u = hw, _words(key, 2)
    return {"dy": _randint(u[0], 0, round(h * scale) - h + 1),
            "dx": _randint(u[1], 0, round(w * scale) - w + 1)}

  def apply(p, x):
    h, w, _ = x.shape
    iy0, iy1, wy = (jax.lax.dynamic_slice(jnp.asarray(t), (p["dy"],), (h,))
                    for t in _bilinear_table(h, round(h * scale)))
    ix0, ix1, wx = (jax.lax.dynamic_slice(jnp.asarray(t), (p["dx"],), (w,))
                    for t in _bilinear_table(w, round(w * scale)))
    xi = x.astype(jnp.int32)
    take = functools.partial(jnp.take, mode="clip")  # indices are in range
    cols = ((256 - wx)[None, :, None] * take(xi, ix0, axis=1)  # columns first,
            + wx[None, :, None] * take(xi, ix1, axis=1))       # see `_gather`
    out = ((256 - wy)[:, None, None] * take(cols, iy0, axis=0)
           + wy[:, None, None] * take(cols, iy1, axis=0))
    return ((out + 32768) >> 16).astype(jnp.uint8)

  return Augmentation("rad", sample, apply)


def cutout_color(min_size: int = 10, max_size: int = 30) -> Augmentation:
  """Cutout Color: one box of a random colour occludes the image (appendix, item 2).

  The paper gives no sizes; we use RAD's DMC values (`random_cutout_color`,
  ``min_cut=10, max_cut=30``): box height and width are drawn independently from
  {10, …, 29} (for 84 px; scaled by side/84 otherwise). RAD places the box at
  (h, w), its own size; we draw its top-left corner uniformly over all positions
  where it fits. The colour is uniform over {0, …, 255}³ and the same for all
  frames. (DMCR's code release used boxes of 7…21 px at a fixed offset.)

  Args:
    min_size: smallest box side at 84 px (inclusive).
    max_size: largest box side at 84 px (exclusive).

  Returns:
    An `Augmentation`; params ``top, left, h, w`` (int32), ``color`` (uint8 (3,)).
  """
  def sample(key, hw):
    (h, w), u = hw, _words(key, 7)
    lo_h, lo_w = min(_scaled(min_size, h), h), min(_scaled(min_size, w), w)
    bh = _randint(u[0], lo_h, max(lo_h + 1, min(_scaled(max_size, h), h + 1)))
    bw = _randint(u[1], lo_w, max(lo_w + 1, min(_scaled(max_size, w), w + 1)))
    return {"top": _randint(u[2], 0, h - bh + 1),
            "left": _randint(u[3], 0, w - bw + 1),
            "h": bh, "w": bw,
            "color": _randint(u[4:7], 0, 256).astype(jnp.uint8)}

  def apply(p, x):
    h, w, c = x.shape
    mask = _box_mask(h, w, p["top"], p["left"], p["h"], p["w"])
    return jnp.where(mask, _tile_frames(p["color"], c)[None, None, :], x)

  return Augmentation("cutout_color", sample, apply)


def drq(pad: int = 4, noise_std: float = 1.0, name: str | None = None
        ) -> Augmentation:
  """DrQ: replicate-pad by `pad` pixels, random crop back, small noise (items 3–6).

  As in DrQ (Kostrikov et al. 2020): the image is padded by replicating its
  border pixels, then a crop of the original size is taken whose top-left corner
  is uniform over the ``2·pad + 1`` positions per axis (0…8 for the paper's pad 4,
  0…24 for Large DrQ's 12). The paper mimics the resampling of DrQ's kornia crop
  with "small amounts of noise" without giving its scale; we follow DMCR's code
  release: Gaussian noise of std 1.0 in 0…255 units. Our output is uint8, so the
  noise is drawn already rounded, round(N(0, 1)) ∈ {−6, …, 6} (P(0) = .38,
  P(±1) = .24, P(±2) = .06, …), from an integer hash of a per-sample seed, added
  in int32 and clipped to 0…255. To keep the appendix's rule that all randomness
  is shared by the frames of a stack and by o and o′, the noise is one (H, W, 3)
  field per sample, added to every frame. `noise_std=0` gives "DrQ No Noise".

  Args:
    pad: the pad/crop margin in pixels (4: DrQ; 12: Large DrQ).
    noise_std: std of the additive noise in 0…255 units (0: no noise).
    name: registry name (default derived from pad and noise).

  Returns:
    An `Augmentation`; params ``dy, dx`` (int32 in [0, 2·pad]) and, if noisy,
    ``noise_seed`` (uint32; see `_rounded_gaussian`).
  """
  if name is None:
    name = ("drq" if pad == 4 else f"drq{pad}") + ("" if noise_std else "_no_noise")

  def sample(key, hw):
    u = _words(key, 3)
    p = {"dy": _randint(u[0], 0, 2 * pad + 1), "dx": _randint(u[1], 0, 2 * pad + 1)}
    if noise_std:
      p["noise_seed"] = u[2]
    return p

  def apply(p, x):
    h, w, c = x.shape
    rows = jnp.clip(jnp.arange(h) + p["dy"] - pad, 0, h - 1)
    cols = jnp.clip(jnp.arange(w) + p["dx"] - pad, 0, w - 1)
    y = _gather(x, rows, cols)
    if not noise_std:
      return y
    noise = _rounded_gaussian(p["noise_seed"], (h, w, 3), noise_std)
    return jnp.clip(y.astype(jnp.int32) + _tile_frames(noise, c), 0, 255
                    ).astype(jnp.uint8)

  return Augmentation(name, sample, apply)


def translate(pad: int = 4, name: str | None = None) -> Augmentation:
  """Translate: shift within a random-colour border of `pad` pixels (items 7–8).

  The paper pads with `pad` pixels of a random colour, shifts the image inside
  the padded area and centre-crops; equivalently the image moves by (ty, tx),
  each uniform over {−pad, …, pad} (DMCR's code drew {−pad, …, pad−1}), and
  the uncovered border takes the colour, uniform over {0, …, 255}³, the same for all
  frames. The paper's sizes: 4 (Translate), 12 (Large Translate).

  Args:
    pad: the largest shift in pixels.
    name: registry name (default ``"translate"`` or ``"translate<pad>"``).

  Returns:
    An `Augmentation`; params ``ty, tx`` (int32), ``color`` (uint8 (3,)).
  """
  if name is None:
    name = "translate" if pad == 4 else f"translate{pad}"

  def sample(key, hw):
    u = _words(key, 5)
    return {"ty": _randint(u[0], -pad, pad + 1), "tx": _randint(u[1], -pad, pad + 1),
            "color": _randint(u[2:5], 0, 256).astype(jnp.uint8)}

  def apply(p, x):
    h, w, c = x.shape
    rows, cols = jnp.arange(h) - p["ty"], jnp.arange(w) - p["tx"]
    inside = (((rows >= 0) & (rows < h))[:, None, None]
              & ((cols >= 0) & (cols < w))[None, :, None])
    y = _gather(x, jnp.clip(rows, 0, h - 1), jnp.clip(cols, 0, w - 1))
    return jnp.where(inside, y, _tile_frames(p["color"], c)[None, None, :])

  return Augmentation(name, sample, apply)


def rotate() -> Augmentation:
  """Rotate: by 0°, 90°, 180° or 270°, uniformly (paper appendix, item 9).

  Counter-clockwise as `numpy.rot90(image, k)`, k uniform over {0, 1, 2, 3} per
  sample. (The original implementation's RotateAug compared ``B·r + i`` with the
  angle index, so it almost never rotated anything; the tests check the pixels
  and that each angle occurs ~1/4 of the time.)
  Needs square images: a non-square input raises ValueError at trace time.

  Returns:
    An `Augmentation`; params ``k`` (int32 in {0, 1, 2, 3}).
  """
  def sample(key, hw):
    return {"k": _randint(_words(key, 1)[0], 0, 4)}

  def apply(p, x):
    if x.shape[0] != x.shape[1]:
      raise ValueError(f"rotate needs square images, got {x.shape[:2]}")
    return jax.lax.switch(p["k"], [lambda y, k=k: jnp.rot90(y, k) for k in range(4)], x)

  return Augmentation("rotate", sample, apply)


def vertical_flip(p: float = 0.5) -> Augmentation:
  """Vertical Flip: rotates a portion `p` of the batch by 180° (appendix, item 10).

  Each sample is rotated by 180° (flipped on both axes) with probability `p`.
  The paper does not give the portion; RAD has no such augmentation, so we take
  DMCR's code release value p = 0.5 (whose code flipped only the vertical axis;
  we follow the paper's text).

  Args:
    p: probability that a sample is rotated.

  Returns:
    An `Augmentation`; params ``flip`` (bool).
  """
  def sample(key, hw):
    return {"flip": _unit(_words(key, 1)[0]) < p}

  def apply(params, x):
    return jnp.where(params["flip"], x[::-1, ::-1], x)

  return Augmentation("vertical_flip", sample, apply)


def window(size: int = 64) -> Augmentation:
  """Window: a random lens shows the image, all other pixels become 0 (item 11).

  The paper gives no size; we follow DMCR's code release: a 64×64 lens on an
  84×84 image (scaled by side/84 otherwise), with its top-left corner uniform
  over all positions where it fits (0…20; the release drew 0…10 only).

  Args:
    size: the lens side at 84 px.

  Returns:
    An `Augmentation`; params ``top, left`` (int32).
  """
  def sample(key, hw):
    (h, w), u = hw, _words(key, 2)
    return {"top": _randint(u[0], 0, h - min(_scaled(size, h), h) + 1),
            "left": _randint(u[1], 0, w - min(_scaled(size, w), w) + 1)}

  def apply(p, x):
    h, w, _ = x.shape
    mask = _box_mask(h, w, p["top"], p["left"], min(_scaled(size, h), h),
                     min(_scaled(size, w), w))
    return jnp.where(mask, x, jnp.zeros((), x.dtype))

  return Augmentation("window", sample, apply)


def _planes(x: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
  """The R, G, B planes (H, W, frames) of a frame-stacked (H, W, 3·frames) image."""
  return x[..., 0::3], x[..., 1::3], x[..., 2::3]


def _interleave(r: jax.Array, g: jax.Array, b: jax.Array) -> jax.Array:
  """Inverse of `_planes`: (H, W, frames) ×3 → (H, W, 3·frames)."""
  return jnp.stack([r, g, b], axis=-1).reshape(*r.shape[:-1], 3 * r.shape[-1])


def rgb_to_hsv(r: jax.Array, g: jax.Array, b: jax.Array):
  """RGB in [0, 1] → HSV in [0, 1], elementwise (hue in turns; 0 for greys).

  The hue formula takes red, then green, then blue as the maximum on ties.

  Args:
    r, g, b: float arrays of one shape.

  Returns:
    (hue, saturation, value), float arrays of that shape.
  """
  v = jnp.maximum(jnp.maximum(r, g), b)
  delta = v - jnp.minimum(jnp.minimum(r, g), b)
  s = jnp.where(v > 0, delta / jnp.where(v > 0, v, 1), 0)
  d = jnp.where(delta > 0, delta, 1)
  hue_r = (g - b) / d  # in [-1, 1]: wrap with a select, not a (slow) float mod
  hue = jnp.where(v == r, jnp.where(hue_r < 0, hue_r + 6, hue_r),
                  jnp.where(v == g, (b - r) / d + 2, (r - g) / d + 4))
  return jnp.where(delta > 0, hue / 6, 0), s, v


def hsv_to_rgb(h: jax.Array, s: jax.Array, v: jax.Array):
  """HSV in [0, 1] → RGB in [0, 1], elementwise (hue in turns, any real value).

  Uses ``f(n) = v − v·s·clip(min(k, 4 − k), 0, 1)``, ``k = (n + 6h) mod 6``, with
  n = 5, 3, 1 for R, G, B (the piecewise formula, continuous in h).

  Args:
    h, s, v: float arrays of one shape.

  Returns:
    (r, g, b), float arrays of that shape.
  """
  def f(n):
    k = n + 6 * h
    k = k - 6 * jnp.floor(k / 6)  # mod 6 (floor vectorises; float mod does not)
    return v - v * s * jnp.clip(jnp.minimum(k, 4 - k), 0, 1)
  return f(5.0), f(3.0), f(1.0)


def color_jitter(brightness: float = 0.4, contrast: float = 0.4,
                 saturation: float = 0.4, hue: float = 0.5) -> Augmentation:
  """Color Jitter (CJ): random brightness, contrast, saturation and hue.

  The paper's "CJ" (Sec. 2, 5; Table 3) gives no ranges; we use RAD's
  `ColorJitterLayer` defaults (brightness = contrast = saturation = 0.4, hue =
  0.5, p = 1): factors b, c, s ~ U(1 − 0.4, 1 + 0.4) and a hue shift
  ~ U(−0.5, 0.5) turns (torchvision's meaning; RAD's code scales it by 255/360).
  As in RAD: contrast acts in RGB, ``(x − mean) · c + mean`` with the per-channel
  spatial mean of each frame, clipped to [0, 1]; brightness scales V, saturation
  scales S (each clipped to [0, 1]) and the hue rotates, in HSV; a fair coin per
  sample puts contrast before or after the HSV step. The same factors serve all
  frames of a stack. Computed in float32 on x/255; rounded half to even.

  Args:
    brightness: brightness factor spread around 1.
    contrast: contrast factor spread around 1.
    saturation: saturation factor spread around 1.
    hue: the largest hue shift in turns (≤ 0.5).

  Returns:
    An `Augmentation`; params ``brightness, contrast, saturation, hue`` (float32)
    and ``contrast_first`` (bool).
  """
  def sample(key, hw):
    w = _words(key, 5)
    u = lambda i, lo, hi: lo + (hi - lo) * _unit(w[i])
    return {"brightness": u(0, max(0.0, 1 - brightness), 1 + brightness),
            "contrast": u(1, max(0.0, 1 - contrast), 1 + contrast),
            "saturation": u(2, max(0.0, 1 - saturation), 1 + saturation),
            "hue": u(3, -hue, hue),
            "contrast_first": _unit(w[4]) < 0.5}

  def apply(p, x):
    rgb = [c.astype(jnp.float32) / 255.0 for c in _planes(x)]

    def adjust_contrast(planes):
      out = []
      for z in planes:
        mean = jnp.mean(z, axis=(0, 1), keepdims=True)
        out.append(jnp.clip((z - mean) * p["contrast"] + mean, 0, 1))
      return out

    first = p["contrast_first"]
    rgb = [jnp.where(first, c, z) for c, z in zip(adjust_contrast(rgb), rgb)]
    h, s, v = rgb_to_hsv(*rgb)
    h = h + p["hue"]
    rgb = hsv_to_rgb(h - jnp.floor(h),
                     jnp.clip(s * p["saturation"], 0, 1),
                     jnp.clip(v * p["brightness"], 0, 1))
    rgb = [jnp.where(first, z, c) for c, z in zip(adjust_contrast(rgb), rgb)]
    return _interleave(*(_to_uint8(c * 255.0) for c in rgb))

  return Augmentation("cj", sample, apply)


NR_INIT_STD = math.sqrt(2.0 / (27 + 27))
"""Std of Network Randomization's kernel: Xavier/Glorot normal for a 3×3 conv,
3 → 3 channels (fan_in = fan_out = 27), as in Lee et al. 2020 and DMCR's code."""


def network_randomization() -> Augmentation:
  """Network Randomization (NR): one random 3×3 convolution per batch.

  As in Lee et al. (2020, "Network randomization") and DMCR's code release: a
  3×3 conv, 3 → 3 channels, no bias, zero "same" padding (cross-correlation,
  like torch's Conv2d), weights drawn from Xavier/Glorot normal
  N(0, 2/(fan_in + fan_out)) = N(0, `NR_INIT_STD`²), fan_in = fan_out = 27
  (Box–Muller from uniform bits), applied to each RGB frame of x/255 and scaled
  back by 255. One kernel is drawn from ``key`` per call and shared by the whole
  batch, its frame stacks and its o/o′ (the paper re-draws it at every update).
  The output is rounded (half to even) and clipped to 0…255 (DMCR's code did not
  clip). The conv is written as 27 shifted multiply-adds per output channel in
  float32: elementwise work that XLA fuses, never TF32, and on CPU about twice
  as fast as `lax.conv` with 3 channels.

  Returns:
    An `Augmentation` with ``per_batch=True``; params ``kernel`` (float32
    (3, 3, 3, 3), HWIO: kernel[dy, dx, in, out]).
  """
  def sample(key, hw):
    u = _words(key, 82)
    u1 = ((u[:41] >> 8) + 1).astype(jnp.float32) * jnp.float32(2.0 ** -24)  # (0, 1]
    r, t = jnp.sqrt(-2 * jnp.log(u1)), 2 * jnp.pi * _unit(u[41:])
    z = jnp.concatenate([r * jnp.cos(t), r * jnp.sin(t)])[:81]  # Box–Muller
    return {"kernel": (NR_INIT_STD * z).reshape(3, 3, 3, 3)}

  def apply(p, x):
    h, w, _ = x.shape
    k = p["kernel"]
    padded = [jnp.pad(c.astype(jnp.float32) / 255.0, ((1, 1), (1, 1), (0, 0)))
              for c in _planes(x)]
    out = []
    for o in range(3):
      acc = None
      for dy in range(3):
        for dx in range(3):
          for i in range(3):
            term = k[dy, dx, i, o] * padded[i][dy:dy + h, dx:dx + w]
            acc = term if acc is None else acc + term
      out.append(_to_uint8(acc * 255.0))
    return _interleave(*out)

  return Augmentation("nr", sample, apply, per_batch=True)


# --------------------------------------------------------------------------- #
# The registry.
# --------------------------------------------------------------------------- #

_FACTORIES: dict[str, Callable[[], Augmentation]] = {
    "none": identity,
    "rad": rad,
    "cutout_color": cutout_color,
    "drq": drq,
    "drq_no_noise": lambda: drq(4, 0.0, name="drq_no_noise"),
    "large_drq": lambda: drq(12, name="large_drq"),
    "large_drq_no_noise": lambda: drq(12, 0.0, name="large_drq_no_noise"),
    "translate": translate,
    "large_translate": lambda: translate(12, name="large_translate"),
    "rotate": rotate,
    "vertical_flip": vertical_flip,
    "window": window,
    "cj": color_jitter,
    "nr": network_randomization,
}

NAMES: tuple[str, ...] = tuple(_FACTORIES) + ("cj+drq", "nr+drq")
"""Every registered name: ``"none"``, the appendix's eleven augmentations, Color
Jitter (``"cj"``), Network Randomization (``"nr"``), and the paper's SAC+CJ+AUG and
SAC+NR+AUG pipelines (``"cj+drq"``, ``"nr+drq"``). `get` also accepts any other
``+``-joined sequence of the single names."""


SampleAugFn = Callable[[jax.Array, jax.Array], jax.Array]
"""A user's augmentation of ONE sample: ``fn(key, image) -> image`` (`from_function`)."""

_USER: dict[str, Augmentation | Composed] = {}  # `register`ed names
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*\Z")
_SPEC = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_][\w.]*\Z")


def from_function(fn: SampleAugFn | Augmentation | Composed,
                  name: str | None = None) -> Augmentation | Composed:
  """An augmentation from a function of ONE sample, the built-ins' convention.

  `fn(key, image) -> image`: `key` is a `jax.random` key, `image` ONE uint8
  observation (H, W, 3·stack), RGB frames stacked on the last axis oldest
  first; it returns a uint8 image of the same shape. It must be pure and
  traceable (`jax.numpy` / `jax.lax` operations; no NumPy randomness, no Python
  side effects), draw all its randomness from `key`, and use the same draw for
  every frame of the stack. Like every built-in, the result calls it per
  sample under `jax.vmap`: sample ``i`` of a batch gets ``fold_in(key, i)``,
  and every array of a pytree the same keys, so ``aug(key, (obs, next_obs))``
  gives a sample's o and o′ the same draw by construction. `check` tests the
  rest (dtype, shape, determinism, jit, vmap, frames, range).

  Args:
    fn: the per-sample function; or an `Augmentation` / `Composed` (e.g.
      ``drq(pad=6)``), returned as it is, renamed if `name` is given.
    name: the augmentation's name (default: `fn`'s ``__name__``).

  Returns:
    An `Augmentation` (`Augmentation.one(key, image)` is ``fn(key, image)``).

  Raises:
    TypeError: `fn` is not callable.
  """
  if isinstance(fn, (Augmentation, Composed)):
    return fn if name is None else dataclasses.replace(fn, name=name)
  if not callable(fn):
    raise TypeError(f"an augmentation is a function fn(key, image) -> image, got "
                    f"{type(fn).__name__} {fn!r}")
  name = name or getattr(fn, "__name__", type(fn).__name__)
  return Augmentation(name, lambda key, hw: {"key": key},
                      lambda p, x: fn(p["key"], x))


def register(name: str, fn: SampleAugFn | Augmentation | Composed
             ) -> Augmentation | Composed:
  """Registers `fn` as augmentation `name` for `get`, ``"name+drq"`` and training.

  After ``register("mine", fn)``, ``get("mine")``, ``get("mine+drq")``,
  ``SACConfig(aug="drq,mine+drq")`` and ``dmcr-train --aug mine`` (in a process that
  registered it) accept the name. Registering a name again replaces it for later
  `get` calls (functions already compiled keep the old one).

  Args:
    name: letters, digits, ``_``, ``.`` and ``-``, starting with a letter or
      ``_`` (no ``+``, ``,`` or ``:``, which compose, list and import), not a
      built-in name (`NAMES`).
    fn: ``fn(key, image) -> image`` on ONE uint8 (H, W, 3·stack) sample (see
      `from_function`), or an `Augmentation` / `Composed`.

  Returns:
    The registered augmentation (what ``get(name)`` returns).

  Raises:
    ValueError: a malformed or built-in name.
    TypeError: `fn` is not callable.
  """
  if not isinstance(name, str) or not _NAME.match(name):
    raise ValueError(f"augmentation name {name!r}: use letters, digits, '_', '.' and "
                     "'-', starting with a letter or '_' ('+' composes, ',' lists "
                     "and ':' imports)")
  if name in _FACTORIES or name in NAMES:
    raise ValueError(f"{name!r} is a built-in augmentation; pick another name "
                     f"(built-ins: {', '.join(NAMES)})")
  aug = from_function(fn, name)
  _USER[name] = aug
  get.cache_clear()
  return aug


def unregister(name: str) -> None:
  """Forgets a `register`ed name (KeyError if it is not one)."""
  del _USER[name]
  get.cache_clear()


def registered() -> tuple[str, ...]:
  """The names added with `register`, in registration order."""
  return tuple(_USER)


def load(spec: str) -> Augmentation | Composed:
  """Imports the augmentation that ``"package.module:function"`` names.

  The module is imported as ``import package.module`` would, with the current
  directory searched first (as ``python -m`` does), so a module beside you, or
  in an installed package, is found. The attribute is a per-sample function
  (`from_function`), or an `Augmentation` / `Composed`; the result is named
  `spec`, so run configs that store it import it again (``--resume``,
  `evaluate`). `get` calls this for every name with a ``:``.

  Args:
    spec: ``module.path:attribute`` (the attribute may be dotted).

  Returns:
    The augmentation, named `spec`.

  Raises:
    ValueError: a one-paragraph message when the module cannot be imported (or
      raises while importing), has no such attribute, or it is not callable.
  """
  module_name, _, attr = spec.partition(":")
  usage = ("The form is package.module:function, e.g. "
           "examples.augmentations:hue_rotation, for a function fn(key, image) -> "
           "image of ONE uint8 (H, W, 3·stack) sample (see dmcr_jax.augment."
           "from_function)")
  if os.getcwd() not in sys.path and "" not in sys.path:
    sys.path.insert(0, os.getcwd())
  try:
    module = importlib.import_module(module_name)
  except Exception as e:  # noqa: BLE001 - the user's module may raise anything
    missing = isinstance(e, ModuleNotFoundError) and (
        e.name and (module_name == e.name or module_name.startswith(e.name + ".")))
    hint = (f"Python searched the current directory ({os.getcwd()}) and sys.path: "
            "run from the folder that holds the module (or its package), put that "
            "folder on PYTHONPATH, or install its package, and check the spelling. "
            if missing else "The module itself failed while importing; fix it (try "
            f"python -c 'import {module_name}'). ")
    raise ValueError(f"augmentation {spec!r}: cannot import module {module_name!r} "
                     f"({type(e).__name__}: {e}). {hint}{usage}.") from None
  obj = module
  for part in attr.split("."):
    if not hasattr(obj, part):
      public = sorted(n for n, v in vars(module).items()
                      if callable(v) and not n.startswith("_")
                      and getattr(v, "__module__", module_name) == module_name)
      raise ValueError(f"augmentation {spec!r}: module {module_name!r} "
                       f"({getattr(module, '__file__', '?')}) has no attribute {attr!r}; "
                       f"its functions: {', '.join(public) or 'none'}. {usage}.")
    obj = getattr(obj, part)
  try:
    return from_function(obj, spec)
  except TypeError as e:
    raise ValueError(f"augmentation {spec!r}: {e}. {usage}.") from None


@functools.lru_cache(maxsize=None)
def get(name: str) -> Augmentation | Composed:
  """The augmentation registered as `name`; ``"a+b"`` composes a then b.

  Results are cached, so repeated calls return the same (already compiled)
  function.

  Args:
    name: one of `NAMES`, a `register`ed name, a ``"package.module:function"``
      import path (`load`), or ``+``-joined such names (e.g. ``"cj+drq"``,
      ``"examples.augmentations:hue_rotation+drq"``).

  Returns:
    A callable ``aug(key, images) -> images`` (`Augmentation` or `Composed`).

  Raises:
    ValueError: for an unknown name, listing the valid ones; for an import path
      that cannot be imported (`load`'s message).
  """
  parts = name.split("+")
  unknown = [p for p in parts
             if p not in _FACTORIES and p not in _USER and not _SPEC.match(p)]
  if unknown:
    mine = f"; registered: {', '.join(_USER)}" if _USER else ""
    raise ValueError(f"unknown augmentation {name!r} (unknown part(s): "
                     f"{', '.join(map(repr, unknown))}); valid names: "
                     f"{', '.join(NAMES)}{mine}; or package.module:function for your "
                     "own (dmcr_jax.augment.load); or '+'-join single names")
  if len(parts) == 1:
    if name in _USER:
      return _USER[name]
    return load(name) if ":" in name else _FACTORIES[name]()
  return Composed(name, tuple(get(p) for p in parts))


def check(aug, **kwargs):
  """Checks an augmentation's properties on real observations; see
  `dmcr_jax.augment_check.check` (its arguments and the properties it runs)."""
  from dmcr_jax import augment_check
  return augment_check.check(aug, **kwargs)
