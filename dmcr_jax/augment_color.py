"""The colour augmentations: Color Jitter and Network Randomization.

Both work on the RGB planes of each stacked frame in float32 on x/255 and round
back to uint8 half to even; `rgb_to_hsv` and `hsv_to_rgb` are the elementwise
conversions Color Jitter uses.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from dmcr_jax.augment_core import Augmentation
from dmcr_jax.augment_random import _unit, _words


def _to_uint8(x: jax.Array) -> jax.Array:
  """Rounds float32 in 0..255 units half-to-even and clips to uint8."""
  return jnp.clip(jnp.round(x), 0, 255).astype(jnp.uint8)


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
