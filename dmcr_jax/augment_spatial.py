"""The spatial augmentations: crops, shifts, rotations, flips and occluders.

RAD, DrQ (± noise, any pad), Translate, Rotate, Vertical Flip, Cutout Color and
Window, each a factory (keyword parameters in, `Augmentation` out) written for one
uint8 (H, W, 3·stack) image, with the helpers they share (index gathers, box
masks, lengths scaled from the paper's 84-pixel images).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.augment_core import Augmentation
from dmcr_jax.augment_random import _randint, _rounded_gaussian, _unit, _words

_REF_SIDE = 84  # the paper's image size (its Table 6); defaults are for 84×84


def _scaled(v: float, side: int) -> int:
  """A length given for 84-pixel images, scaled to `side` pixels (at least 1)."""
  return max(1, int(round(v * side / _REF_SIDE)))


def _tile_frames(rgb: jax.Array, channels: int) -> jax.Array:
  """Repeats a (..., 3) array over the frames of a (..., channels) image."""
  return jnp.tile(rgb, (1,) * (rgb.ndim - 1) + (channels // 3,))

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
