"""The procedural backgrounds: skybox cube maps of landscapes.

`cube_directions` gives the world direction of every texel of MuJoCo's cube map;
`procedural_background(i)` evaluates one landscape (sky gradient, sun, clouds,
stars, mountain ridges, tree lines, fields, dunes, snow or water) at them.
"""

from __future__ import annotations

import numpy as np

from dmcr_jax.visuals.texture_noise import (F32, _hash, _lerp, _palette, _Params, _smooth,
                                            _smoothstep, _to_uint8, _unit, fbm)
from dmcr_jax.visuals.texture_spec import BACKGROUND_SIZE, NUM_BACKGROUNDS


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
  """The skybox texture's name in a MuJoCo model for background `index` ("sky_007")."""
  return f"sky_{index:03d}"
