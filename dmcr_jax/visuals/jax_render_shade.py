"""Shading and texturing for the JAX ray caster, per pixel.

GL's fixed-function lighting of surface points (`_shade`), the floor texture's
trilinear lookup with MuJoCo's texture origin and texrepeat (`_floor_color`) and
the skybox's cube-map lookup, optionally blended with a second sky (`_sky_color`).
Colours are (r, g, b) tuples in [0, 1]; texels are read through a reader
(`ArrayReader` or the kernel's `RefReader`).
"""

from __future__ import annotations

import jax.numpy as jnp

from dmcr_jax.visuals.jax_render_geometry import _add, _dot, _norm, _scale, _sub, _unit
from dmcr_jax.visuals.jax_render_pack import Layout


def _shade(n, p, v, rgb_scale, rgba, spec, shin, emis, lights):
  """GL fixed-function lighting of surface points (sum over lights, clamped).

  Args:
    n, p, v: unit normals, points and unit directions to the viewer (tuples).
    rgb_scale: scalar or per-pixel factor on the material colour (reflections).
    rgba: the material colour (4-tuple).
    spec, shin, emis: specular, shininess (MuJoCo scale), emission.
    lights: list of (kind, pos, dir, ambient, diffuse, specular, attenuation,
      cutoff, exponent, on) with kind 'dir' or 'spot', 3-tuples of scalars, and
      `on` a per-pixel factor or None (1).

  Returns:
    (r, g, b) in [0, 1].
  """
  rgb = _scale(rgba[:3], rgb_scale)
  out = _scale(rgb, emis)
  expo = 128.0 * shin
  for kind, lpos, ldir, amb, dif, spc, att, cut, ex, on in lights:
    if kind == "dir":
      to_light = (-ldir[0], -ldir[1], -ldir[2])
      factor = None
    else:
      to = _sub(lpos, p)
      dist = _norm(to)
      safe = jnp.maximum(dist, 1e-12)
      to_light = (to[0] / safe, to[1] / safe, to[2] / safe)
      cos = -_dot(to_light, ldir)
      spot = jnp.where(cos >= jnp.cos(jnp.deg2rad(cut)), jnp.maximum(cos, 0.0) ** ex, 0.0)
      factor = spot / (att[0] + att[1] * dist + att[2] * dist * dist)
    if on is not None:
      factor = on if factor is None else factor * on
    ndl = _dot(n, to_light)
    ndh = jnp.maximum(_dot(n, _unit(_add(to_light, v))), 0.0)
    lit_spec = jnp.where(ndl > 0, ndh ** expo, 0.0)
    dif_w = jnp.maximum(ndl, 0.0)
    term = tuple(amb[c] * rgb[c] + dif_w * dif[c] * rgb[c] + lit_spec * spc[c] * spec
                 for c in range(3))
    out = tuple(out[c] + (term[c] if factor is None else factor * term[c])
                for c in range(3))
  return tuple(jnp.clip(c, 0.0, 1.0) for c in out)


def _bilinear(fetch, u, v):
  """Bilinear filtering of texels `fetch(u0, v0)` (3-tuples) around (u, v)."""
  u0, v0 = jnp.floor(u), jnp.floor(v)
  fu, fv = u - u0, v - v0
  u0, v0 = u0.astype(jnp.int32), v0.astype(jnp.int32)
  a, b = fetch(u0, v0), fetch(u0 + 1, v0)
  c, d = fetch(u0, v0 + 1), fetch(u0 + 1, v0 + 1)
  return tuple((1 - fu) * (1 - fv) * a[i] + fu * (1 - fv) * b[i] + (1 - fu) * fv * c[i]
               + fu * fv * d[i] for i in range(3))


def _floor_color(L: Layout, R, p_local, footprint, half):
  """Trilinear floor-texture lookup at plane-frame points (MuJoCo's texgen).

  `footprint` is a pixel's extent on the floor in metres along its longer axis,
  which picks the mip level (GL's isotropic selection)."""
  rep0, rep1 = R.f(L.floor + 1), R.f(L.floor + 2)
  # MuJoCo 3.x: texture origin at the plane's (−x, +y) corner, 2 / texrepeat
  # metres per repeat (texuniform); matched to mujoco.Renderer's frames.
  s = 0.5 * rep0 * (p_local[0] + half[0])
  t = 0.5 * rep1 * (half[1] - p_local[1])
  off, wid, hei = L.level_field(0), L.level_field(1), L.level_field(2)
  w0 = R.i(wid).astype(jnp.float32)
  lam = jnp.log2(jnp.maximum(footprint * 0.5 * rep0 * w0, 1e-6))
  nlev = R.i(0)
  lam = jnp.clip(lam, 0.0, (nlev - 1).astype(jnp.float32))
  l0 = jnp.floor(lam).astype(jnp.int32)
  l1 = jnp.minimum(l0 + 1, nlev - 1)
  frac = lam - l0.astype(jnp.float32)

  def level_color(level):
    base, w, h = R.i_at(off, level), R.i_at(wid, level), R.i_at(hei, level)

    def fetch(uu, vv):
      i = (base + jnp.mod(vv, h) * w + jnp.mod(uu, w)) * 3
      return tuple(R.texel(i + c).astype(jnp.float32) for c in range(3))
    return _bilinear(fetch, s * w.astype(jnp.float32) - 0.5, t * h.astype(jnp.float32) - 0.5)

  c0, c1 = level_color(l0), level_color(l1)
  return tuple(((1 - frac) * c0[i] + frac * c1[i]) / 255.0 for i in range(3))


def _sky_color(L: Layout, R, d):
  """Skybox colour along world directions d: the look's sky, or with
  `L.sky_blend` its blend with the second sky (weight: the last float)."""
  c = _one_sky_color(L, R, d, R.i(1))
  if not L.sky_blend:
    return c
  w = R.f(L.num_floats - 1)
  c2 = _one_sky_color(L, R, d, R.i(L.num_ints - 1))
  return tuple((1 - w) * a + w * b for a, b in zip(c, c2))


def _one_sky_color(L: Layout, R, d, sky):
  """Skybox `sky`'s colour along world directions d (MuJoCo maps (x, y, z) to the
  cube map's (x, z, −y); GL cube-face selection, bilinear, clamped to the face)."""
  rx, ry, rz = d[0], d[2], -d[1]
  ax, ay, az = jnp.abs(rx), jnp.abs(ry), jnp.abs(rz)
  xm = (ax >= ay) & (ax >= az)
  ym = ~xm & (ay >= az)
  face = jnp.where(xm, jnp.where(rx > 0, 0, 1),
                   jnp.where(ym, jnp.where(ry > 0, 2, 3), jnp.where(rz > 0, 4, 5)))
  ma = jnp.where(xm, ax, jnp.where(ym, ay, az))
  sc = jnp.where(xm, jnp.where(rx > 0, -rz, rz),
                 jnp.where(ym, rx, jnp.where(rz > 0, rx, -rx)))
  tc = jnp.where(xm, -ry, jnp.where(ym, jnp.where(ry > 0, rz, -rz), -ry))
  size = L.sky_size
  base = (sky * 6 + face) * size

  def fetch(uu, vv):
    i = ((base + jnp.clip(vv, 0, size - 1)) * size + jnp.clip(uu, 0, size - 1)) * 3
    return tuple(R.sky(i + c).astype(jnp.float32) for c in range(3))
  c = _bilinear(fetch, (sc / ma + 1) * 0.5 * size - 0.5, (tc / ma + 1) * 0.5 * size - 0.5)
  return tuple(x / 255.0 for x in c)
