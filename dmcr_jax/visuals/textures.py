"""Procedural texture banks (floors and skyboxes), their disk cache, and user folders.

The original DMCR shipped 383 floor photos and 116 landscape photos that we
cannot redistribute. This module generates a replacement bank procedurally and
deterministically: `NUM_FLOORS` tileable 256×256 floor textures in 16 kinds
(grass, soil, sand, gravel, rock, ice, concrete, brick, tiles, moss, leaves,
lichen, snow, mud, cobblestone, frozen ground) and `NUM_BACKGROUNDS` skybox cube
maps (6 faces of 192×192: sky gradients, sun, clouds, stars, mountain ridges,
tree lines, fields, dunes, snow and water with reflections).

Determinism: texture `i` is a pure function of `(VERSION, i)`. Per-texture
parameters come from NumPy's PCG64 raw stream (`PCG64(seed).random_raw`, whose
output is fixed by its specification), pixel noise from an integer hash
(uint32 multiply/xor/shift), and all pixel arithmetic uses only float32 `+ - * /`,
`sqrt`, `floor`, `min`/`max` and comparisons: operations that IEEE 754 rounds
exactly, so the bytes are the same on every machine (tests check hashes). No
transcendental functions, reductions or library interpolation touch pixels.

The bank is built once (with a progress bar) and
cached as `.npy` files under `$XDG_CACHE_HOME/dmcr_jax` (or `~/.cache/dmcr_jax`)
in a folder named by `VERSION`. `load_bank(floor_dir=..., background_dir=...)`
uses a user's image folders instead (files sorted by name, so a seed means the
same image on every machine).

Cube-map layout: `backgrounds[b]` has shape (6, W, W, 3), the faces of an OpenGL
cube map in the order +X, −X, +Y, −Y, +Z, −Z, as MuJoCo uploads a cube texture
whose height is 6× its width. MuJoCo's skybox looks a world direction (x, y, z)
up at cube coordinates (x, z, −y), so world "up" is the +Y face.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pathlib
import tempfile
from typing import Callable, Sequence

import numpy as np

from dmcr_jax._files import write_atomic

VERSION = "dmcr-textures-v1"
FLOOR_SIZE = 256
BACKGROUND_SIZE = 192
FLOOR_KINDS: tuple[str, ...] = (
    "grass", "soil", "sand", "gravel", "rock", "ice", "concrete", "brick",
    "tiles", "moss", "leaves", "lichen", "snow", "mud", "cobblestone",
    "frozen_ground")
FLOORS_PER_KIND = 20
NUM_FLOORS = len(FLOOR_KINDS) * FLOORS_PER_KIND          # 320
NUM_BACKGROUNDS = 120
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".gif", ".tif", ".tiff", ".webp")

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


# ---------------------------------------------------------------------------
# Floors (tileable 256×256)
# ---------------------------------------------------------------------------

_N = FLOOR_SIZE
_YY, _XX = np.meshgrid(np.arange(_N, dtype=F32) + F32(0.5),
                       np.arange(_N, dtype=F32) + F32(0.5), indexing="ij")
_U = _XX * F32(1.0 / _N)   # tile coordinates in [0, 1)
_V = _YY * F32(1.0 / _N)
_U1 = _U[0]                 # the same, as 1-D vectors (separable noise)
_V1 = _V[:, 0]


def _pfbm(p: _Params, cells: int, octaves: int = 5, gain: float = 0.5,
          ridged: bool = False, warp: float = 0.0):
  """Tileable fBm over the floor tile with `cells` lattice cells per side."""
  if not warp:
    return fbm(_U1 * F32(cells), _V1 * F32(cells), p.seed(), octaves, gain,
               period=(cells, cells), ridged=ridged, grid=True)
  x, y = _U * F32(cells), _V * F32(cells)
  if warp:
    s = p.seed()
    wx = fbm(_U1 * F32(4), _V1 * F32(4), s, 3, period=(4, 4), grid=True) - F32(0.5)
    wy = fbm(_U1 * F32(4), _V1 * F32(4), s + 1, 3, period=(4, 4), grid=True) - F32(0.5)
    x = x + F32(warp * cells) * wx
    y = y + F32(warp * cells) * wy
  return fbm(x, y, p.seed(), octaves, gain, period=(cells, cells), ridged=ridged)


def _grain(p: _Params, amount: float):
  """Fine per-pixel grain, centred on 1."""
  return F32(1) + F32(amount) * (_unit(_hash(p.seed(), _XX, _YY)) - F32(0.5))


def _floor_grass(p: _Params):
  hue = p.pick([(0.22, 0.42, 0.12), (0.30, 0.45, 0.15), (0.38, 0.45, 0.18),
                (0.18, 0.35, 0.12), (0.45, 0.47, 0.22), (0.28, 0.50, 0.20)])
  base = p.color(hue, 0.05)
  dark, light = base * F32(0.45), np.minimum(base * F32(1.45), F32(1))
  patches = _pfbm(p, 4, 4)
  blades = _pfbm(p, 64, 3, 0.6)
  streak = fbm(_U1 * F32(128), _V1 * F32(16), p.seed(), 2, period=(128, 16),
               grid=True)
  t = F32(0.35) * patches + F32(0.4) * blades + F32(0.25) * streak
  col = _palette(t, [dark, base, light], [0.15, 0.5, 0.9])
  dry = _smoothstep(0.55, 0.8, _pfbm(p, 6, 4))[..., None] * F32(p.u(0.0, 0.6))
  straw = p.color((0.62, 0.55, 0.30), 0.05)
  col = _lerp(col, straw * (F32(0.6) + F32(0.6) * blades[..., None]), dry)
  return col * _grain(p, 0.25)[..., None]


def _floor_soil(p: _Params):
  base = p.color(p.pick([(0.40, 0.28, 0.18), (0.33, 0.25, 0.17), (0.50, 0.36, 0.22),
                         (0.28, 0.20, 0.14), (0.45, 0.33, 0.25)]), 0.05)
  n = _pfbm(p, 8, 6, 0.55, warp=0.3)
  col = _palette(n, [base * F32(0.55), base, base * F32(1.3)], [0.2, 0.5, 0.85])
  f1, _, cell = worley(_U1 * F32(24), _V1 * F32(24), p.seed(), 24)
  pebble = (f1 < F32(p.u(0.15, 0.3))) & (_unit(cell) < F32(p.u(0.2, 0.5)))
  pcol = _palette(_unit(_mix(cell)), [base * F32(0.8), p.color((0.6, 0.55, 0.5), 0.08)])
  col = np.where(pebble[..., None], pcol * (F32(1.15) - f1[..., None]), col)
  return col * _shade(n, 4.0)[..., None] * _grain(p, 0.2)[..., None]


def _floor_sand(p: _Params):
  base = p.color(p.pick([(0.86, 0.76, 0.55), (0.80, 0.68, 0.48), (0.90, 0.82, 0.65),
                         (0.76, 0.58, 0.40), (0.70, 0.66, 0.58)]), 0.04)
  n = _pfbm(p, 4, 5, 0.5)
  kx, ky = p.i(3, 9), p.i(-3, 4)
  warp = _pfbm(p, 3, 3)
  phase = _U * F32(kx) + _V * F32(ky) + F32(p.u(0.5, 1.5)) * warp
  tri = np.abs(F32(2) * (phase - np.floor(phase)) - F32(1))
  ripple = _smooth(tri)
  h = F32(0.6) * ripple + F32(0.4) * n
  col = _palette(h, [base * F32(0.78), base, np.minimum(base * F32(1.12), 1)])
  return col * _shade(ripple, p.u(0.5, 1.5))[..., None] * _grain(p, 0.18)[..., None]


def _floor_gravel(p: _Params):
  cells = p.i(16, 33)
  f1, f2, cell = worley(_U1 * F32(cells), _V1 * F32(cells), p.seed(), cells)
  stones = [p.color(c, 0.05) for c in ((0.55, 0.53, 0.50), (0.42, 0.40, 0.38),
                                       (0.65, 0.60, 0.52), (0.35, 0.33, 0.32),
                                       (0.58, 0.50, 0.42))]
  col = _palette(_unit(cell), stones)
  edge = _smoothstep(0.0, 0.25, f2 - f1)
  bump = F32(1) - f1
  col = col * (F32(0.55) + F32(0.6) * bump)[..., None] * edge[..., None]
  col = col + F32(0.06) * (F32(1) - edge)[..., None] * stones[1]
  return col * _grain(p, 0.3)[..., None]


def _floor_rock(p: _Params):
  base = p.color(p.pick([(0.50, 0.48, 0.45), (0.45, 0.40, 0.35), (0.58, 0.55, 0.50),
                         (0.40, 0.38, 0.40), (0.55, 0.45, 0.38)]), 0.05)
  n = _pfbm(p, 4, 6, 0.55, ridged=True, warp=0.2)
  f1, f2, _ = worley(_U1 * F32(6), _V1 * F32(6), p.seed(), 6)
  crack = _smoothstep(0.0, 0.06, f2 - f1)
  col = _palette(n, [base * F32(0.5), base, np.minimum(base * F32(1.35), 1)])
  col = col * (F32(0.35) + F32(0.65) * crack)[..., None]
  return col * _shade(n, 3.0)[..., None] * _grain(p, 0.2)[..., None]


def _floor_ice(p: _Params):
  base = p.color(p.pick([(0.75, 0.86, 0.93), (0.65, 0.80, 0.90), (0.85, 0.90, 0.95),
                         (0.60, 0.75, 0.85)]), 0.04)
  n = _pfbm(p, 3, 5, 0.5, warp=0.4)
  f1, f2, _ = worley(_U1 * F32(5), _V1 * F32(5), p.seed(), 5)
  crack = F32(1) - _smoothstep(0.0, 0.03, f2 - f1)
  deep = base * F32(0.7)
  col = _palette(n, [deep, base, np.ones(3, F32)], [0.1, 0.55, 1.0])
  col = col + F32(0.35) * crack[..., None]
  return col * _grain(p, 0.06)[..., None]


def _floor_concrete(p: _Params):
  g = p.u(0.45, 0.72)
  base = p.color((g, g * p.u(0.97, 1.02), g * p.u(0.93, 1.0)), 0.02)
  stains = _pfbm(p, 4, 5, 0.55)
  fine = _pfbm(p, 64, 2)
  col = base * (F32(0.8) + F32(0.35) * stains + F32(0.15) * fine)[..., None]
  joints = p.pick([0, 1, 2])
  if joints:
    d = np.minimum(np.abs(_U * F32(joints) - np.floor(_U * F32(joints) + F32(0.5))),
                   np.abs(_V * F32(joints) - np.floor(_V * F32(joints) + F32(0.5))))
    col = col * (F32(0.55) + F32(0.45) * _smoothstep(0.0, 0.012, d))[..., None]
  pits = _unit(_hash(p.seed(), _XX, _YY)) < F32(0.01)
  col = np.where(pits[..., None], col * F32(0.6), col)
  return col * _grain(p, 0.12)[..., None]


def _floor_brick(p: _Params):
  rows = p.pick([4, 6, 8])
  cols = rows // 2
  base = p.color(p.pick([(0.60, 0.25, 0.18), (0.55, 0.30, 0.22), (0.70, 0.40, 0.28),
                         (0.45, 0.22, 0.18), (0.65, 0.55, 0.45), (0.50, 0.45, 0.42)]), 0.05)
  mortar = p.color(p.pick([(0.75, 0.72, 0.66), (0.55, 0.53, 0.50), (0.35, 0.33, 0.30)]), 0.04)
  ry = _V * F32(rows)
  row = np.floor(ry)
  shift = (row.astype(np.int64) % 2).astype(F32) * F32(0.5)
  rx = _U * F32(cols) + shift
  colidx = np.floor(rx)
  fx, fy = rx - colidx, ry - row
  mw = F32(p.u(0.03, 0.07))
  inside = np.minimum(np.minimum(fx, F32(1) - fx) * F32(2.0 * cols / rows),
                      np.minimum(fy, F32(1) - fy))
  brick_mask = _smoothstep(float(mw) * 0.6, float(mw), inside)
  bid = _hash(p.seed(), colidx.astype(np.int64) % cols, row.astype(np.int64))
  var = F32(0.75) + F32(0.5) * _unit(bid)
  n = _pfbm(p, 32, 3)
  bcol = base * (var * (F32(0.85) + F32(0.3) * n))[..., None]
  col = _lerp(mortar * (F32(0.8) + F32(0.3) * n)[..., None], bcol, brick_mask[..., None])
  return col * _grain(p, 0.15)[..., None]


def _floor_tiles(p: _Params):
  k = p.pick([2, 4, 4, 8])
  palette = [p.color(c, 0.05) for c in p.pick([
      ((0.85, 0.83, 0.78), (0.75, 0.72, 0.68)),
      ((0.55, 0.35, 0.25), (0.65, 0.45, 0.30)),
      ((0.30, 0.40, 0.50), (0.80, 0.82, 0.85)),
      ((0.25, 0.25, 0.25), (0.85, 0.85, 0.85)),
      ((0.45, 0.55, 0.45), (0.70, 0.72, 0.60)),
      ((0.72, 0.55, 0.38), (0.60, 0.42, 0.30))])]
  pattern = p.pick(["checker", "random", "plain"])
  tx, ty = _U * F32(k), _V * F32(k)
  ix, iy = np.floor(tx), np.floor(ty)
  fx, fy = tx - ix, ty - iy
  if pattern == "checker":
    t = ((ix + iy).astype(np.int64) % 2).astype(F32)
  elif pattern == "random":
    t = _unit(_hash(p.seed(), ix.astype(np.int64), iy.astype(np.int64)))
  else:
    t = np.zeros_like(fx)
  col = _palette(t, palette)
  gw = F32(p.u(0.02, 0.05))
  edge = np.minimum(np.minimum(fx, F32(1) - fx), np.minimum(fy, F32(1) - fy))
  mask = _smoothstep(float(gw) * 0.5, float(gw), edge)
  grout = p.color(p.pick([(0.6, 0.6, 0.58), (0.3, 0.3, 0.3), (0.9, 0.9, 0.88)]), 0.03)
  n = _pfbm(p, 8, 4)
  col = col * (F32(0.9) + F32(0.2) * n)[..., None]
  bevel = F32(1) + F32(0.25) * (_smoothstep(0.0, 0.15, fx) - _smoothstep(0.0, 0.15, fy))
  col = _lerp(grout[None, None, :] * np.ones_like(col), col * bevel[..., None], mask[..., None])
  return col * _grain(p, 0.08)[..., None]


def _floor_moss(p: _Params):
  base = p.color(p.pick([(0.30, 0.45, 0.12), (0.38, 0.50, 0.15), (0.25, 0.38, 0.15),
                         (0.45, 0.52, 0.20)]), 0.05)
  f1, _, cell = worley(_U1 * F32(12), _V1 * F32(12), p.seed(), 12)
  clump = F32(1) - np.clip(f1, F32(0), F32(1))
  n = _pfbm(p, 16, 5, 0.6)
  h = F32(0.5) * clump + F32(0.5) * n
  col = _palette(h, [base * F32(0.3), base, np.minimum(base * F32(1.5), 1)], [0.2, 0.55, 1.0])
  col = col * (F32(0.85) + F32(0.3) * _unit(cell))[..., None]
  return col * _shade(h, 2.0)[..., None] * _grain(p, 0.25)[..., None]


def _splat_leaves(p: _Params, img, count: int, colors, size: tuple[float, float]):
  """Draws `count` oriented ellipses (leaves) on a periodic tile, in order."""
  for _ in range(count):
    cx, cy = p.u(0, _N), p.u(0, _N)
    a = p.u(size[0], size[1])
    b = a * p.u(0.35, 0.55)
    dx, dy = p.u(-1, 1), p.u(-1, 1)
    norm = float(np.sqrt(F32(dx * dx + dy * dy))) + 1e-6
    ux, uy = F32(dx / norm), F32(dy / norm)
    r = int(a) + 2
    x0, y0 = int(cx) - r, int(cy) - r
    xs = np.arange(x0, x0 + 2 * r + 1)
    ys = np.arange(y0, y0 + 2 * r + 1)
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    px = gx.astype(F32) + F32(0.5) - F32(cx)
    py = gy.astype(F32) + F32(0.5) - F32(cy)
    lu = (px * ux + py * uy) * F32(1.0 / a)
    lv = (py * ux - px * uy) * F32(1.0 / b)
    d = lu * lu + lv * lv
    m = d < F32(1)
    if not m.any():
      continue
    c = colors[p.i(0, len(colors))] * F32(p.u(0.75, 1.1))
    shade = (F32(1.05) - F32(0.3) * d)[m][:, None] * (
        F32(1) - F32(0.35) * (np.abs(lv) < F32(0.08))[m][:, None])
    img[gy[m] % _N, gx[m] % _N] = c * shade


def _floor_leaves(p: _Params):
  ground = p.color((0.28, 0.20, 0.13), 0.04)
  img = ground * (F32(0.7) + F32(0.5) * _pfbm(p, 16, 4))[..., None]
  autumn = p.u() < 0.75
  base = ([(0.75, 0.35, 0.10), (0.85, 0.60, 0.15), (0.55, 0.20, 0.08),
           (0.45, 0.30, 0.15), (0.70, 0.50, 0.20)] if autumn else
          [(0.30, 0.45, 0.15), (0.40, 0.50, 0.20), (0.25, 0.35, 0.12),
           (0.45, 0.40, 0.18)])
  colors = [p.color(c, 0.06) for c in base]
  img = np.ascontiguousarray(img)
  _splat_leaves(p, img, p.i(160, 260), colors, (9.0, 18.0))
  return img * _grain(p, 0.12)[..., None]


def _floor_lichen(p: _Params):
  rock = _floor_rock(p)
  f1, _, cell = worley(_U1 * F32(10), _V1 * F32(10), p.seed(), 10)
  n = _pfbm(p, 20, 4)
  radius = F32(0.25) + F32(0.35) * _unit(cell)
  patch = _smoothstep(-0.05, 0.05, radius - f1 + F32(0.3) * (n - F32(0.5)))
  patch = patch * (_unit(_mix(cell)) < F32(p.u(0.4, 0.8)))
  lc = [p.color(c, 0.05) for c in ((0.75, 0.70, 0.30), (0.60, 0.65, 0.35),
                                   (0.85, 0.55, 0.20), (0.70, 0.72, 0.60))]
  lcol = _palette(_unit(_mix(cell ^ U32(77))), lc) * (F32(0.8) + F32(0.4) * n)[..., None]
  return _lerp(rock, lcol, patch[..., None])


def _floor_snow(p: _Params):
  base = p.color((0.92, 0.94, 0.97), 0.03)
  shadow = p.color((0.70, 0.78, 0.90), 0.04)
  n = _pfbm(p, 4, 5, 0.5, warp=0.3)
  col = _palette(n, [shadow, base, np.ones(3, F32)], [0.15, 0.6, 1.0])
  col = col * _shade(n, 1.5)[..., None]
  sparkle = _unit(_hash(p.seed(), _XX, _YY)) > F32(0.995)
  col = np.where(sparkle[..., None], np.ones(3, F32), col)
  return col * _grain(p, 0.05)[..., None]


def _floor_mud(p: _Params):
  base = p.color(p.pick([(0.30, 0.22, 0.15), (0.35, 0.28, 0.20), (0.25, 0.20, 0.16)]), 0.04)
  n = _pfbm(p, 6, 6, 0.55, warp=0.4)
  col = _palette(n, [base * F32(0.6), base, base * F32(1.4)], [0.2, 0.5, 0.9])
  water = _smoothstep(0.55, 0.62, _pfbm(p, 3, 4))
  wet = base * F32(0.45) + F32(0.08)
  col = _lerp(col * _shade(n, 3.0)[..., None], wet * np.ones_like(col), water[..., None])
  return col * _grain(p, 0.15)[..., None]


def _floor_cobblestone(p: _Params):
  cells = p.i(6, 13)
  f1, f2, cell = worley(_U1 * F32(cells), _V1 * F32(cells), p.seed(), cells, 0.7)
  stones = [p.color(c, 0.05) for c in p.pick([
      ((0.50, 0.48, 0.45), (0.40, 0.38, 0.36), (0.60, 0.57, 0.52)),
      ((0.55, 0.45, 0.35), (0.45, 0.38, 0.30), (0.62, 0.52, 0.40)),
      ((0.42, 0.42, 0.45), (0.35, 0.35, 0.38), (0.55, 0.55, 0.58))])]
  col = _palette(_unit(cell), stones)
  edge = _smoothstep(0.02, 0.2, f2 - f1)
  dome = F32(1) - F32(0.6) * f1
  n = _pfbm(p, 32, 3)
  col = col * (dome * (F32(0.85) + F32(0.3) * n))[..., None]
  gap = p.color((0.22, 0.20, 0.17), 0.03) * (F32(0.7) + F32(0.6) * n)[..., None]
  return _lerp(gap, col, edge[..., None]) * _grain(p, 0.12)[..., None]


def _floor_frozen_ground(p: _Params):
  soil = _floor_soil(p)
  n = _pfbm(p, 8, 5, 0.55, warp=0.3)
  frost = _smoothstep(p.u(0.35, 0.5), p.u(0.55, 0.7), n)
  fine = _pfbm(p, 64, 2)
  white = p.color((0.85, 0.88, 0.92), 0.03) * (F32(0.85) + F32(0.2) * fine)[..., None]
  return _lerp(soil * F32(0.85), white, (frost * F32(0.9))[..., None])


_FLOOR_FNS: dict[str, Callable[[_Params], np.ndarray]] = {
    "grass": _floor_grass, "soil": _floor_soil, "sand": _floor_sand,
    "gravel": _floor_gravel, "rock": _floor_rock, "ice": _floor_ice,
    "concrete": _floor_concrete, "brick": _floor_brick, "tiles": _floor_tiles,
    "moss": _floor_moss, "leaves": _floor_leaves, "lichen": _floor_lichen,
    "snow": _floor_snow, "mud": _floor_mud, "cobblestone": _floor_cobblestone,
    "frozen_ground": _floor_frozen_ground,
}


def floor_name(index: int) -> str:
  """Name of procedural floor `index`, e.g. "grass_03" (kinds interleave)."""
  kind = FLOOR_KINDS[index % len(FLOOR_KINDS)]
  return f"{kind}_{index // len(FLOOR_KINDS):02d}"


def procedural_floor(index: int) -> np.ndarray:
  """Generates procedural floor texture `index` (deterministic).

  Args:
    index: 0 ≤ index < NUM_FLOORS. Kinds interleave: index % 16 is the kind
      (see `FLOOR_KINDS`), so any run of 16 consecutive ids has every kind.

  Returns:
    uint8 array (FLOOR_SIZE, FLOOR_SIZE, 3), tileable.
  """
  if not 0 <= index < NUM_FLOORS:
    raise ValueError(f"floor index must be in [0, {NUM_FLOORS}), got {index}.")
  kind = FLOOR_KINDS[index % len(FLOOR_KINDS)]
  p = _Params("floor", index)
  img = _FLOOR_FNS[kind](p)
  # Overall brightness/contrast variation so kinds do not all look alike.
  gain = F32(p.u(0.8, 1.15))
  return _to_uint8(img * gain)


# ---------------------------------------------------------------------------
# Backgrounds (skybox cube maps)
# ---------------------------------------------------------------------------


def cube_directions(size: int) -> np.ndarray:
  """Unit world directions of every cube-map texel, shape (6, size, size, 3).

  Face order +X, −X, +Y, −Y, +Z, −Z of the OpenGL cube map; row r of a face is
  t = (r + ½)/size and column c is s = (c + ½)/size (OpenGL's convention,
  MuJoCo uploads rows in memory order). MuJoCo's skybox maps world (x, y, z)
  to cube coordinates (x, z, −y).
  """
  t, s = np.meshgrid((np.arange(size, dtype=F32) + F32(0.5)) * F32(2.0 / size) - F32(1),
                     (np.arange(size, dtype=F32) + F32(0.5)) * F32(2.0 / size) - F32(1),
                     indexing="ij")
  one = np.ones_like(s)
  # OpenGL cube map: (rx, ry, rz) for each face from (sc, tc).
  faces = [(one, -t, -s), (-one, -t, s), (s, one, t), (s, -one, -t),
           (s, -t, one), (-s, -t, -one)]
  out = np.empty((6, size, size, 3), F32)
  for f, (rx, ry, rz) in enumerate(faces):
    x, z, y = rx, ry, -rz       # cube (s, t, r) = world (x, z, -y)
    inv = F32(1) / np.sqrt(x * x + y * y + z * z)
    out[f, ..., 0], out[f, ..., 1], out[f, ..., 2] = x * inv, y * inv, z * inv
  return out


def _azimuth(x, y):
  """A monotone, rational pseudo-azimuth in [0, 4) (the "diamond angle")."""
  ax, ay = np.abs(x), np.abs(y)
  s = ax + ay
  r = np.where(s > F32(0), y / np.where(s > F32(0), s, F32(1)), F32(0))
  a = np.where(x >= F32(0), r, F32(2) - r)          # (-1, 3]
  return np.where(a < F32(0), a + F32(4), a)


def _fbm1(az, seed: int, freq: int, octaves: int, gain: float):
  """Periodic 1-D fBm of the pseudo-azimuth (period 4, `freq` cells) in [0, 1]."""
  total = np.zeros_like(az)
  amp, norm = 1.0, 0.0
  for k in range(octaves):
    per = freq * 2**k
    table = _unit(_hash(seed + 31 * k, np.arange(per + 1, dtype=np.int64) % per))
    x = az * F32(per / 4.0)
    xf = np.floor(x)
    t = _smooth(x - xf)
    i0 = xf.astype(np.int64) % per
    n = _lerp(table[i0], table[i0 + 1], t)
    total = total + F32(amp) * n
    norm += amp
    amp *= gain
  return total * F32(1.0 / norm)


_SKIES = {
    # zenith, horizon, haze (colour near the horizon line), cloud colour
    "day": ((0.20, 0.40, 0.80), (0.65, 0.80, 0.95), (0.85, 0.90, 0.95), (1.0, 1.0, 1.0)),
    "deep": ((0.10, 0.25, 0.65), (0.50, 0.70, 0.92), (0.75, 0.85, 0.95), (0.97, 0.97, 1.0)),
    "sunset": ((0.20, 0.25, 0.55), (0.98, 0.60, 0.30), (1.0, 0.75, 0.45), (0.95, 0.55, 0.45)),
    "dawn": ((0.35, 0.45, 0.75), (0.98, 0.78, 0.65), (1.0, 0.88, 0.75), (1.0, 0.85, 0.80)),
    "overcast": ((0.55, 0.58, 0.62), (0.78, 0.80, 0.82), (0.82, 0.83, 0.84), (0.70, 0.72, 0.75)),
    "dusk": ((0.08, 0.08, 0.25), (0.55, 0.35, 0.50), (0.70, 0.45, 0.50), (0.40, 0.30, 0.45)),
    "night": ((0.01, 0.02, 0.07), (0.08, 0.12, 0.25), (0.12, 0.15, 0.28), (0.20, 0.22, 0.30)),
    "haze": ((0.55, 0.62, 0.72), (0.85, 0.82, 0.72), (0.90, 0.86, 0.75), (0.95, 0.93, 0.88)),
}
_GROUNDS = {
    "meadow": ((0.25, 0.40, 0.15), (0.40, 0.50, 0.20)),
    "forest": ((0.10, 0.22, 0.10), (0.18, 0.30, 0.14)),
    "desert": ((0.80, 0.65, 0.45), (0.70, 0.52, 0.35)),
    "savanna": ((0.62, 0.55, 0.30), (0.45, 0.42, 0.22)),
    "snow": ((0.88, 0.90, 0.95), (0.72, 0.78, 0.88)),
    "tundra": ((0.45, 0.45, 0.38), (0.60, 0.58, 0.50)),
    "water": ((0.10, 0.25, 0.35), (0.20, 0.35, 0.45)),
    "rocky": ((0.45, 0.42, 0.40), (0.35, 0.33, 0.32)),
}
_MOUNTAINS = ((0.35, 0.38, 0.45), (0.40, 0.35, 0.30), (0.30, 0.33, 0.28),
              (0.55, 0.50, 0.45), (0.25, 0.28, 0.35))


def _background_from_directions(p: _Params, d: np.ndarray) -> np.ndarray:
  """Evaluates one procedural landscape at unit directions d (..., 3) → RGB.

  The horizon sits 2°–19° below eye level (so cameras that look down still see
  it), the sky above it (gradient, sun, clouds, stars), the ground below it
  (perspective-textured fields, desert, snow or water reflecting the sky) and
  mountain ridges, hills or tree lines on it. Work is done on masked subsets.
  """
  shape = d.shape[:-1]
  d = d.reshape(-1, 3)
  x, y, z = d[:, 0], d[:, 1], d[:, 2]
  sky_name = p.pick(list(_SKIES))
  zen, hor, haze, cloud_c = (p.color(c, 0.05) for c in _SKIES[sky_name])
  ground_name = p.pick(list(_GROUNDS))
  g_scale = {"night": 0.25, "dusk": 0.55, "overcast": 0.75}.get(sky_name, 1.0)
  g1, g2 = (p.color(c, 0.05) * F32(g_scale) for c in _GROUNDS[ground_name])
  v0 = F32(-p.u(0.035, 0.33))
  v = z - v0                        # > 0: sky, < 0: ground
  img = np.empty((d.shape[0], 3), F32)
  S = v >= F32(0)                   # sky texels
  G = ~S

  # --- sun direction (rational pseudo-azimuth, no trigonometry) ---------------
  sun_on = sky_name not in ("overcast", "night") and p.u() < 0.8
  sa = p.u(0.0, 4.0)
  sun_el = p.u(0.05, 0.6) if sky_name not in ("sunset", "dawn", "dusk") else p.u(0.0, 0.15)
  if sa < 1:
    sx, sy = 1 - sa, sa
  elif sa < 2:
    sx, sy = 1 - sa, 2 - sa
  elif sa < 3:
    sx, sy = sa - 3, 2 - sa
  else:
    sx, sy = sa - 3, sa - 4
  sz = float(v0) + sun_el
  sn = float(np.sqrt(F32(sx * sx + sy * sy + sz * sz)))
  s = np.array([sx / sn, sy / sn, sz / sn], F32)
  sun_size = F32(p.u(0.00012, 0.0004))
  glow_amp, glow_k = F32(p.u(0.15, 0.45)), F32(p.u(60, 200))
  sun_c = p.color((1.0, 0.95, 0.80) if sky_name not in ("sunset", "dusk") else
                  (1.0, 0.70, 0.40), 0.03)

  def sky_gradient(up):
    t = up / (up + F32(0.18))
    return _palette(t, [haze, hor, zen], [0.0, 0.25, 1.0])

  # --- sky ---------------------------------------------------------------------
  xs, ys, zs, up = x[S], y[S], z[S], np.minimum(v[S], F32(1))
  sky = sky_gradient(up)
  if sun_on:
    om = np.maximum(F32(1) - (xs * s[0] + ys * s[1] + zs * s[2]), F32(0))
    disc = _smoothstep(float(sun_size) * 1.3, float(sun_size) * 0.7, om)
    sky = sky + (glow_amp / (F32(1) + om * glow_k))[:, None] * sun_c
    sky = _lerp(sky, sun_c * F32(1.2), disc[:, None])
  if sky_name in ("night", "dusk"):
    q = np.floor(d[S] * F32(300)).astype(np.int64)
    star = _unit(_hash(p.seed(), q[:, 0], q[:, 1], q[:, 2])) > F32(0.9975)
    bright = F32(0.85) if sky_name == "night" else F32(0.5)
    sky = np.where((star & (up > F32(0.02)))[:, None], np.maximum(sky, bright), sky)
  cover = {"overcast": p.u(0.55, 0.8), "haze": p.u(0.1, 0.4)}.get(sky_name, p.u(0.0, 0.6))
  if cover > 0.05:
    inv = F32(1) / (up + F32(0.08))
    cs = F32(p.u(0.6, 2.0))
    cx, cy = xs * inv * cs, ys * inv * cs
    warp = fbm(cx * F32(0.5), cy * F32(0.5), p.seed(), 2)
    n = fbm(cx + F32(2) * warp, cy * F32(p.u(1.0, 2.5)) + F32(2) * warp,
            p.seed(), 4, 0.55)
    dens = _smoothstep(1.0 - cover, 1.0 - cover + p.u(0.12, 0.35), n)
    dens = dens * _smoothstep(0.0, 0.12, up) * F32(p.u(0.7, 1.0))
    shade = F32(0.7) + F32(0.6) * (n - warp * F32(0.5))
    sky = _lerp(sky, cloud_c * shade[:, None], dens[:, None])
  img[S] = sky

  # --- ground: perspective texture, haze towards the horizon -------------------
  xg, yg, down = x[G], y[G], np.minimum(-v[G], F32(1))
  ginv = F32(1) / (down + F32(0.01))
  gs = F32(p.u(2.0, 6.0))
  gx, gy = xg * ginv * gs, yg * ginv * gs
  patches = fbm(gx * F32(0.15), gy * F32(0.15), p.seed(), 3, 0.5)
  detail = fbm(gx * F32(2), gy * F32(2), p.seed(), 3, 0.6)
  gn = F32(0.65) * patches + F32(0.35) * detail
  ground = _palette(gn, [g1 * F32(0.7), g1, g2, g2 * F32(1.15)], [0.2, 0.4, 0.6, 0.85])
  if ground_name in ("meadow", "savanna", "tundra") and p.u() < 0.5:
    # farmland: strips of crops with their own colours
    ux, uy = p.u(-1, 1), p.u(-1, 1)
    w = F32(p.u(0.05, 0.2))
    coord = (gx * F32(ux) + gy * F32(uy)) * w
    strip = np.floor(coord).astype(np.int64)
    tint = F32(0.75) + F32(0.5) * _unit(_hash(p.seed(), strip))
    rows = F32(0.85) + F32(0.15) * np.abs(F32(2) * (coord * F32(8) - np.floor(
        coord * F32(8))) - F32(1))
    ground = ground * (tint * rows)[:, None]
  elif ground_name == "desert":
    k = F32(p.u(0.3, 0.8))
    ph = (gx * F32(p.u(-1, 1)) + gy) * k + F32(2) * patches
    ripple = _smooth(np.abs(F32(2) * (ph - np.floor(ph)) - F32(1)))
    ground = ground * (F32(0.8) + F32(0.35) * ripple)[:, None]
  elif ground_name == "forest":
    canopy = fbm(gx * F32(4), gy * F32(4), p.seed(), 2, 0.5, ridged=True)
    ground = ground * (F32(0.6) + F32(0.7) * canopy)[:, None]
  elif ground_name == "water":
    ripple = fbm(gx * F32(1), gy * F32(6), p.seed(), 2)
    refl = sky_gradient(down)
    if sun_on:
      rc = xg * s[0] + yg * s[1] + (F32(2) * v0 - z[G]) * s[2]
      glint = _smoothstep(0.996, 0.9995, rc + F32(0.004) * ripple)
      refl = refl + glint[:, None] * F32(0.8)
    ground = _lerp(ground, refl * F32(0.8), F32(0.65)) * (
        F32(0.85) + F32(0.3) * ripple)[:, None]
  fade = F32(1) / (F32(1) + down * F32(p.u(10, 25)))
  ground = _lerp(ground, haze * F32(g_scale ** 0.5), (fade * F32(0.85))[:, None])
  img[G] = ground

  # --- mountain ridges / hills / tree lines on the horizon ----------------------
  layers = p.i(1, 4) if ground_name != "water" else p.i(0, 3)
  band = np.nonzero((v >= F32(-0.002)) & (v < F32(0.3)))[0]
  if layers and band.size:
    xb, yb, vb = x[band], y[band], v[band]
    az = _azimuth(xb, yb)
    out = img[band]
    for k in range(layers):
      far = (layers - k) / layers                  # far layers first
      height = F32(p.u(0.06, 0.3) * (0.5 + 0.5 * far))
      freq = p.pick([4, 6, 8, 12])
      kind = p.pick(["mountain", "mountain", "mountain", "hills", "trees"])
      if kind == "hills":
        h = _fbm1(az, p.seed(), freq, 3, 0.4) * height * F32(0.6)
      elif kind == "trees":
        h = (F32(0.015) + F32(0.035) * _fbm1(az, p.seed(), 256, 2, 0.6)
             + F32(0.02) * _fbm1(az, p.seed(), 8, 2, 0.5))
      else:
        h = _fbm1(az, p.seed(), freq, 6, 0.55)
        h = np.maximum(h - F32(0.2), F32(0)) * height * F32(1.8)
      inside = vb < h
      if not inside.any():
        continue
      base_c = (p.color((0.12, 0.22, 0.10), 0.04) if kind == "trees" else
                p.color(p.pick(_MOUNTAINS), 0.05)) * F32(g_scale)
      ai, vi, hi = az[inside], vb[inside], h[inside]
      tex = fbm(ai * F32(40), vi * F32(40), p.seed(), 3, 0.55)
      col = base_c * (F32(0.75) + F32(0.5) * tex)[:, None]
      if kind == "mountain" and p.u() < 0.5:
        snow = _smoothstep(0.5, 0.6, vi / np.maximum(hi, F32(1e-3)) + F32(0.15) * tex)
        col = _lerp(col, p.color((0.92, 0.93, 0.96), 0.02) * F32(g_scale), snow[:, None])
      col = _lerp(col, haze * F32(g_scale ** 0.5), F32(0.5 * far ** 1.5))
      out[inside] = col
    img[band] = out

  tint = p.color((1.0, 1.0, 1.0), 0.04)
  return (img * tint * F32(p.u(0.85, 1.1))).reshape(shape + (3,))


_DIRS_CACHE: dict[int, np.ndarray] = {}


def _dirs(size: int) -> np.ndarray:
  if size not in _DIRS_CACHE:
    _DIRS_CACHE[size] = cube_directions(size)
  return _DIRS_CACHE[size]


def procedural_background(index: int, size: int = BACKGROUND_SIZE) -> np.ndarray:
  """Generates procedural skybox `index` as cube faces (deterministic).

  Args:
    index: 0 ≤ index < NUM_BACKGROUNDS.
    size: face resolution (the bank uses BACKGROUND_SIZE).

  Returns:
    uint8 array (6, size, size, 3) in MuJoCo's cube-face order.
  """
  if not 0 <= index < NUM_BACKGROUNDS:
    raise ValueError(
        f"background index must be in [0, {NUM_BACKGROUNDS}), got {index}.")
  p = _Params("background", index)
  return _to_uint8(_background_from_directions(p, _dirs(size)))


def background_name(index: int) -> str:
  return f"sky_{index:03d}"


# ---------------------------------------------------------------------------
# User image folders
# ---------------------------------------------------------------------------


def _list_images(folder) -> list[pathlib.Path]:
  folder = pathlib.Path(folder).expanduser()
  if not folder.is_dir():
    raise ValueError(f"Not a folder: {folder}")
  files = sorted((f for f in folder.iterdir()
                  if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES),
                 key=lambda f: f.name)
  if not files:
    raise ValueError(f"No images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
  return files


def _read_rgb(path) -> np.ndarray:
  import imageio.v3 as iio
  img = np.asarray(iio.imread(path))
  if img.ndim == 2:
    img = np.repeat(img[..., None], 3, axis=-1)
  if img.ndim == 4:          # animated: first frame
    img = img[0]
  img = img[..., :3]
  if img.dtype != np.uint8:
    scale = 255.0 / float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else 255.0
    img = np.clip(img.astype(np.float64) * scale + 0.5, 0, 255).astype(np.uint8)
  return img


def _bilinear(img: np.ndarray, u, v) -> np.ndarray:
  """Samples img (H, W, 3) uint8 at normalised coords u (x), v (y) in [0, 1]."""
  h, w = img.shape[:2]
  fx = np.clip(u * F32(w) - F32(0.5), F32(0), F32(w - 1))
  fy = np.clip(v * F32(h) - F32(0.5), F32(0), F32(h - 1))
  x0, y0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
  x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
  tx, ty = (fx - x0.astype(F32))[..., None], (fy - y0.astype(F32))[..., None]
  im = img.astype(F32) * F32(1.0 / 255)
  top = _lerp(im[y0, x0], im[y0, x1], tx)
  bot = _lerp(im[y1, x0], im[y1, x1], tx)
  return _lerp(top, bot, ty)


def floor_from_image(img: np.ndarray, size: int = FLOOR_SIZE) -> np.ndarray:
  """Resizes a user's floor image to a square texture (centre crop, bilinear)."""
  h, w = img.shape[:2]
  side = min(h, w)
  y0, x0 = (h - side) // 2, (w - side) // 2
  img = img[y0:y0 + side, x0:x0 + side]
  c = (np.arange(size, dtype=F32) + F32(0.5)) * F32(1.0 / size)
  vv, uu = np.meshgrid(c, c, indexing="ij")
  return _to_uint8(_bilinear(img, uu, vv))


def background_from_image(img: np.ndarray, size: int = BACKGROUND_SIZE) -> np.ndarray:
  """Wraps a user's landscape photo around the horizon of a skybox cube.

  The photo covers a quarter turn of azimuth and is mirror-repeated around the
  horizon (no seams); vertically it spans sin(elevation) ∈ [−0.5, 0.5], and
  above/below it its top/bottom rows are extended.
  """
  d = _dirs(size)
  az = _azimuth(d[..., 0], d[..., 1])             # [0, 4)
  seg = np.floor(az)
  frac = az - seg
  u = np.where((seg.astype(np.int64) % 2) == 0, frac, F32(1) - frac)
  v = np.clip(F32(0.5) - d[..., 2], F32(0), F32(1))
  return _to_uint8(_bilinear(img, u, v))


# ---------------------------------------------------------------------------
# The bank, its cache, and the build
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class TextureBank:
  """Floor textures and skybox cube maps for the render model.

  Attributes:
    floors: uint8 (F, S, S, 3) tileable floor textures.
    backgrounds: uint8 (B, 6, W, W, 3) cube faces (+X, −X, +Y, −Y, +Z, −Z).
    floor_names, background_names: a name per texture (kind or file name).
    source: "procedural/<VERSION>" or the user folders it was read from.
  """
  floors: np.ndarray
  backgrounds: np.ndarray
  floor_names: tuple[str, ...]
  background_names: tuple[str, ...]
  source: str

  @property
  def num_floors(self) -> int:
    return int(self.floors.shape[0])

  @property
  def num_backgrounds(self) -> int:
    return int(self.backgrounds.shape[0])

  @property
  def key(self) -> str:
    """A short content key (source and sizes), used to cache render models."""
    return f"{self.source}|{self.floors.shape}|{self.backgrounds.shape}"

  def subset(self, floors: Sequence[int], backgrounds: Sequence[int]) -> "TextureBank":
    """A smaller bank with the given floor and background ids (for tests/tools)."""
    fl, bg = list(floors), list(backgrounds)
    return TextureBank(
        floors=self.floors[fl], backgrounds=self.backgrounds[bg],
        floor_names=tuple(self.floor_names[i] for i in fl),
        background_names=tuple(self.background_names[i] for i in bg),
        source=f"{self.source}[floors={fl},backgrounds={bg}]")


def cache_dir() -> pathlib.Path:
  """The cache folder: $XDG_CACHE_HOME/dmcr_jax, else ~/.cache/dmcr_jax."""
  base = os.environ.get("XDG_CACHE_HOME") or os.path.join(
      os.path.expanduser("~"), ".cache")
  return pathlib.Path(base) / "dmcr_jax"


def _bank_paths() -> tuple[pathlib.Path, pathlib.Path]:
  d = cache_dir() / VERSION
  return d / "floors.npy", d / "backgrounds.npy"


def _jobs(num_floors: int, num_backgrounds: int) -> list[tuple[str, int]]:
  # Backgrounds first (slowest), then floors, so workers finish together.
  return [("background", i) for i in range(num_backgrounds)] + [
      ("floor", i) for i in range(num_floors)]


def _make(kind: str, index: int) -> np.ndarray:
  return procedural_floor(index) if kind == "floor" else procedural_background(index)


def _worker_main(worker: int, workers: int, out_dir: str, num_floors: int,
                 num_backgrounds: int) -> None:
  """Subprocess entry point: generates jobs[worker::workers] into out_dir."""
  import sys
  for kind, i in _jobs(num_floors, num_backgrounds)[worker::workers]:
    np.save(os.path.join(out_dir, f"{kind}_{i}.npy"), _make(kind, i))
    sys.stdout.write("1\n")
    sys.stdout.flush()


def build_procedural(workers: int | None = None, progress: bool = True
                     ) -> tuple[np.ndarray, np.ndarray]:
  """Generates the whole procedural bank (no cache).

  Work is spread over plain `python -c` subprocesses (not multiprocessing, so
  it is safe to call from scripts without a `__main__` guard and from processes
  that run JAX threads).

  Args:
    workers: processes to use (default: the CPU count; 1 runs in-process).
    progress: show a tqdm progress bar (one line instead when stderr is not a
      terminal).

  Returns:
    (floors (NUM_FLOORS, S, S, 3), backgrounds (NUM_BACKGROUNDS, 6, W, W, 3)).
  """
  import subprocess
  import sys
  import threading
  from tqdm.auto import tqdm
  nf, nb = NUM_FLOORS, NUM_BACKGROUNDS
  jobs = _jobs(nf, nb)
  workers = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
  floors = np.empty((nf, FLOOR_SIZE, FLOOR_SIZE, 3), np.uint8)
  bgs = np.empty((nb, 6, BACKGROUND_SIZE, BACKGROUND_SIZE, 3), np.uint8)
  desc = "dmcr_jax: building texture bank (once)"
  bar_on = progress and sys.stderr.isatty()
  if progress and not bar_on:  # to a log file: one line instead of a bar's redraws
    print(f"{desc} …", file=sys.stderr, flush=True)
  bar = tqdm(total=len(jobs), desc=desc, disable=not bar_on, unit="tex")
  try:
    if workers == 1:
      for kind, i in jobs:
        (floors if kind == "floor" else bgs)[i] = _make(kind, i)
        bar.update()
      return floors, bgs
    with tempfile.TemporaryDirectory(prefix="dmcr_textures_") as tmp:
      # Load this file directly (not the package, which imports JAX): fast start.
      code = ("import importlib.util, sys; "
              "spec = importlib.util.spec_from_file_location('_dmcr_textures', sys.argv[6]); "
              "m = sys.modules['_dmcr_textures'] = importlib.util.module_from_spec(spec); "
              "spec.loader.exec_module(m); "
              "m._worker_main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], "
              "int(sys.argv[4]), int(sys.argv[5]))")
      env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
      procs = [subprocess.Popen([sys.executable, "-c", code, str(w), str(workers), tmp,
                                 str(nf), str(nb), os.path.abspath(__file__)],
                                stdout=subprocess.PIPE, env=env)
               for w in range(workers)]
      lock = threading.Lock()

      def pump(proc):
        for _ in proc.stdout:
          with lock:
            bar.update()
      threads = [threading.Thread(target=pump, args=(p,), daemon=True) for p in procs]
      for t in threads:
        t.start()
      codes = [p.wait() for p in procs]
      for t in threads:
        t.join()
      if any(codes):
        raise RuntimeError(f"texture workers failed with exit codes {codes}")
      for kind, i in jobs:
        (floors if kind == "floor" else bgs)[i] = np.load(
            os.path.join(tmp, f"{kind}_{i}.npy"))
  finally:
    bar.close()
  return floors, bgs


_BANK_CACHE: dict[tuple, TextureBank] = {}


def load_bank(floor_dir: str | os.PathLike | None = None,
              background_dir: str | os.PathLike | None = None,
              progress: bool = True) -> TextureBank:
  """The texture bank: procedural (built once, cached on disk) or user folders.

  Args:
    floor_dir: optional folder of floor images (sorted by file name; centre-
      cropped and resized to 256×256). Replaces the procedural floors.
    background_dir: optional folder of landscape images (sorted by file name;
      wrapped around the horizon of a cube map). Replaces the procedural skies.
    progress: show a progress bar while building the procedural bank.

  Returns:
    A `TextureBank` (cached in-process).
  """
  key = (str(floor_dir) if floor_dir else None,
         str(background_dir) if background_dir else None)
  if key in _BANK_CACHE:
    return _BANK_CACHE[key]
  floors = bgs = None
  fnames = tuple(floor_name(i) for i in range(NUM_FLOORS))
  bnames = tuple(background_name(i) for i in range(NUM_BACKGROUNDS))
  source = [f"procedural/{VERSION}"]
  if floor_dir:
    files = _list_images(floor_dir)
    floors = np.stack([floor_from_image(_read_rgb(f)) for f in files])
    fnames = tuple(f.name for f in files)
    source.append(f"floors={pathlib.Path(floor_dir).expanduser().resolve()}")
  if background_dir:
    files = _list_images(background_dir)
    bgs = np.stack([background_from_image(_read_rgb(f)) for f in files])
    bnames = tuple(f.name for f in files)
    source.append(f"backgrounds={pathlib.Path(background_dir).expanduser().resolve()}")
  if floors is None or bgs is None:
    pf, pb = _procedural_cached(progress)
    floors = pf if floors is None else floors
    bgs = pb if bgs is None else bgs
  bank = TextureBank(floors=floors, backgrounds=bgs, floor_names=fnames,
                     background_names=bnames, source=";".join(source))
  _BANK_CACHE[key] = bank
  return bank


def _procedural_cached(progress: bool) -> tuple[np.ndarray, np.ndarray]:
  fpath, bpath = _bank_paths()
  want_f = (NUM_FLOORS, FLOOR_SIZE, FLOOR_SIZE, 3)  # read at call time
  want_b = (NUM_BACKGROUNDS, 6, BACKGROUND_SIZE, BACKGROUND_SIZE, 3)
  try:
    floors = np.load(fpath, mmap_mode="r")
    bgs = np.load(bpath, mmap_mode="r")
    if floors.shape == want_f and bgs.shape == want_b and floors.dtype == np.uint8:
      return np.asarray(floors), np.asarray(bgs)
  except (OSError, ValueError):
    pass
  floors, bgs = build_procedural(progress=progress)
  write_atomic(fpath, lambda f: np.save(f, floors))
  write_atomic(bpath, lambda f: np.save(f, bgs))
  return floors, bgs


def texture_hash(img: np.ndarray) -> str:
  """sha256 (first 16 hex digits) of a texture's bytes and shape."""
  h = hashlib.sha256(repr((img.shape, str(img.dtype))).encode())
  h.update(np.ascontiguousarray(img).tobytes())
  return h.hexdigest()[:16]
