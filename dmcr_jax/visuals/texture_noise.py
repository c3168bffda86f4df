"""Exact, machine-independent primitives of the procedural textures.

A per-texture parameter stream (`_Params`, PCG64's raw output keyed by `VERSION`),
a uint32 integer hash, value noise, fBm and cellular (Worley) noise, and the colour
helpers the floors and skies share (palette ramps, fake relief shading, the uint8
conversion). Pixel arithmetic is float32 `+ - * /`, `sqrt`, `floor`, `min`/`max` and
comparisons only, so the bytes are the same on every machine.
"""

from __future__ import annotations

import hashlib
from typing import Sequence

import numpy as np

from dmcr_jax.visuals.texture_spec import FLOOR_SIZE, VERSION

F32 = np.float32
U32 = np.uint32

# ---------------------------------------------------------------------------
# Deterministic parameter stream and integer hash
# ---------------------------------------------------------------------------


class _Params:
  """Per-texture parameters from PCG64's raw stream (fixed by its specification)."""

  def __init__(self, *key: int):
    digest = hashlib.sha256(repr((VERSION,) + key).encode()).digest()
    self._bg = np.random.PCG64(int.from_bytes(digest[:16], "little"))

  def u(self, lo: float = 0.0, hi: float = 1.0) -> float:
    """A float64 uniform in [lo, hi) (53-bit, like `Generator.random`)."""
    raw = int(self._bg.random_raw())
    return lo + (hi - lo) * ((raw >> 11) * 2.0**-53)

  def i(self, lo: int, hi: int) -> int:
    """An integer uniform in [lo, hi) (modulo of 64 bits; bias < 2**-50)."""
    return lo + int(self._bg.random_raw()) % (hi - lo)

  def seed(self) -> int:
    """A 32-bit seed for the pixel hash."""
    return int(self._bg.random_raw()) & 0xFFFFFFFF

  def color(self, base: Sequence[float], jitter: float = 0.06) -> np.ndarray:
    """`base` RGB (0..1) with a per-channel jitter, as float32."""
    return np.array([min(1.0, max(0.0, c + self.u(-jitter, jitter))) for c in base],
                    F32)

  def pick(self, seq):
    return seq[self.i(0, len(seq))]


_M1, _M2, _GOLD = U32(0x7FEB352D), U32(0x846CA68B), U32(0x9E3779B9)


def _mix(h: np.ndarray) -> np.ndarray:
  """A uint32 avalanche finaliser (exact integer arithmetic)."""
  h = h ^ (h >> U32(16))
  h = h * _M1
  h = h ^ (h >> U32(15))
  h = h * _M2
  return h ^ (h >> U32(16))


def _hash(seed: int, *coords: np.ndarray) -> np.ndarray:
  """uint32 hash of integer coordinate arrays and a seed."""
  h = np.full(np.shape(coords[0]), U32(seed & 0xFFFFFFFF), U32)
  for c in coords:
    h = _mix(h ^ (np.asarray(c).astype(np.int64).astype(U32) * _GOLD))
  return _mix(h)


def _unit(h: np.ndarray) -> np.ndarray:
  """uint32 hash → float32 uniform in [0, 1) (24 bits, exact)."""
  return (h >> U32(8)).astype(F32) * F32(2.0**-24)


# ---------------------------------------------------------------------------
# Noise (float32, exact operations only)
# ---------------------------------------------------------------------------


def _smooth(t):
  return t * t * (F32(3) - F32(2) * t)


def _lerp(a, b, t):
  return a + (b - a) * t


def _smoothstep(e0: float, e1: float, x):
  t = np.clip((x - F32(e0)) * F32(1.0 / (e1 - e0)), F32(0), F32(1))
  return _smooth(t)


_TABLE = 64    # lattice period of non-periodic noise (each octave has its own table)


def _lattice(seed: int, px: int, py: int) -> np.ndarray:
  """Lattice values in [0, 1) for a (py, px) periodic grid, padded by one row and
  column (wrapped) so that neighbours never need a modulo: shape (py+1, px+1)."""
  yy, xx = np.meshgrid(np.arange(py + 1, dtype=np.int64) % py,
                       np.arange(px + 1, dtype=np.int64) % px, indexing="ij")
  return _unit(_hash(seed, xx, yy))


def _cells(x, p: int):
  """Integer cell (mod p, int32) and smoothed fraction of lattice coordinates x."""
  xf = np.floor(x)
  i = xf.astype(np.int32)
  if p & (p - 1) == 0:
    i &= p - 1
  else:
    i %= p
  return i, _smooth(x - xf)


def value_noise(x, y, seed: int, period: tuple[int, int] | None = None,
                grid: bool = False):
  """2-D value noise in [0, 1) at lattice coordinates (x, y).

  With `period=(px, py)` the noise repeats every px along x and py along y;
  without, it repeats every 64 lattice cells. With `grid=True`, x and y are
  1-D and the noise is evaluated (separably) on their grid: shape (len(y), len(x)).
  """
  px, py = period if period is not None else (_TABLE, _TABLE)
  table = _lattice(seed, px, py)
  xi, fx = _cells(x, px)
  yi, fy = _cells(y, py)
  if grid:
    # Separable: interpolate lattice rows along y, then gather columns along x.
    rows = _lerp(table[yi], table[yi + 1], fy[:, None])        # (H, px+1)
    return _lerp(rows[:, xi], rows[:, xi + 1], fx[None, :])
  flat = table.ravel()
  r0 = yi * np.int32(px + 1) + xi
  a = _lerp(flat.take(r0), flat.take(r0 + 1), fx)
  r0 += np.int32(px + 1)
  return _lerp(a, _lerp(flat.take(r0), flat.take(r0 + 1), fx), fy)


def fbm(x, y, seed: int, octaves: int = 5, gain: float = 0.5,
        period: tuple[int, int] | None = None, ridged: bool = False,
        grid: bool = False):
  """Fractal sum of value noise, normalised to about [0, 1].

  Args:
    x, y: float32 lattice coordinates of the first octave.
    seed: hash seed; octave k uses seed + 7919 k.
    octaves: number of octaves (frequency doubles each octave).
    gain: amplitude factor per octave.
    period: lattice period of the first octave (doubles with the frequency).
    ridged: use 1 − |2n − 1| per octave (sharp ridges).
    grid: x, y are 1-D axes of a grid (see `value_noise`).
  """
  total = None
  amp, norm = 1.0, 0.0
  for k in range(octaves):
    f = F32(2**k)
    per = None if period is None else (period[0] * 2**k, period[1] * 2**k)
    if per is not None and max(per) > FLOOR_SIZE and k > 0:
      break     # finer than a texel of the tile: adds nothing but cost
    n = value_noise(x * f, y * f, seed + 7919 * k, per, grid)
    if ridged:
      n = F32(1) - np.abs(F32(2) * n - F32(1))
    total = F32(amp) * n if total is None else total + F32(amp) * n
    norm += amp
    amp *= gain
  return total * F32(1.0 / norm)


def worley(x, y, seed: int, period: int, jitter: float = 0.9):
  """Periodic cellular noise on a `period`×`period` cell grid.

  Args:
    x, y: 1-D float32 axes (cell units) of the grid to evaluate on.
    seed: hash seed.
    period: cells per side of the periodic tile.
    jitter: how far feature points may move inside their cell (0..1).

  Returns:
    (f1, f2, cell), each (len(y), len(x)): distance to the nearest and second-
    nearest feature point (cell units) and a uint32 hash of the nearest cell.
  """
  yy, xx = np.meshgrid(np.arange(period, dtype=np.int64),
                       np.arange(period, dtype=np.int64), indexing="ij")
  hid = _hash(seed, xx, yy).ravel()
  jx = F32((1 - jitter) / 2) + F32(jitter) * _unit(hid)
  jy = F32((1 - jitter) / 2) + F32(jitter) * _unit(_mix(hid ^ U32(0x5BD1E995)))
  xf, yf = np.floor(x), np.floor(y)
  xi, yi = xf.astype(np.int32), yf.astype(np.int32)
  fx, fy = (x - xf)[None, :], (y - yf)[:, None]
  shape = (len(y), len(x))
  f1 = np.full(shape, F32(9), F32)
  f2 = np.full(shape, F32(9), F32)
  cell = np.zeros(shape, U32)
  for oy in (-1, 0, 1):
    row = (((yi + oy) % period) * period)[:, None]
    for ox in (-1, 0, 1):
      idx = row + ((xi + ox) % period)[None, :]
      dx = (F32(ox) + jx[idx]) - fx
      dy = (F32(oy) + jy[idx]) - fy
      d = np.sqrt(dx * dx + dy * dy)
      closer = d < f1
      f2 = np.minimum(f2, np.maximum(f1, d))
      cell = np.where(closer, hid[idx], cell)
      f1 = np.minimum(f1, d)
  return f1, f2, cell


def _palette(t, stops: Sequence[np.ndarray], pos: Sequence[float] | None = None):
  """Piecewise-linear colour ramp: t (...,) in [0, 1] → (..., 3) float32."""
  n = len(stops)
  pos = list(pos) if pos is not None else [k / (n - 1) for k in range(n)]
  t = np.clip(t, F32(0), F32(1))[..., None]
  out = np.broadcast_to(np.asarray(stops[0], F32), t.shape[:-1] + (3,)).copy()
  for k in range(1, n):
    a = F32(pos[k - 1])
    w = np.clip((t - a) * F32(1.0 / max(pos[k] - pos[k - 1], 1e-6)), F32(0), F32(1))
    out = out + (np.asarray(stops[k], F32) - np.asarray(stops[k - 1], F32)) * w
  return out


def _to_uint8(img) -> np.ndarray:
  return (np.clip(img, F32(0), F32(1)) * F32(255) + F32(0.5)).astype(np.uint8)


def _shade(height, strength: float):
  """Fake directional lighting from a periodic height map (light from +x+y)."""
  gx = np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)
  gy = np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)
  return F32(1) + F32(strength) * (gx + gy)
