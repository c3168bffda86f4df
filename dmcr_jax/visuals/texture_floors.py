"""The procedural floors: tileable FLOOR_SIZE² textures in 16 kinds.

One generator per kind (grass, soil, sand, gravel, rock, ice, concrete, brick,
tiles, moss, leaves, lichen, snow, mud, cobblestone, frozen ground), each drawing
its parameters from the texture's `_Params` stream; `procedural_floor(i)` picks
the kind `i % 16` and `floor_name(i)` names it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from dmcr_jax.visuals.texture_noise import (F32, U32, _hash, _lerp, _mix, _palette,
                                            _Params, _shade, _smooth, _smoothstep, _to_uint8,
                                            _unit, fbm, worley)
from dmcr_jax.visuals.texture_spec import FLOOR_KINDS, FLOOR_SIZE, NUM_FLOORS


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
