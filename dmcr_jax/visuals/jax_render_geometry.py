"""Geometry of the JAX ray caster: 3-vectors and ray–primitive intersections.

The per-pixel code's vector helpers on (x, y, z) tuples, the analytic nearest
front-side hit of a ray with each MuJoCo primitive (plane, sphere, ellipsoid,
capsule, cylinder, box) in the primitive's own frame, and the outward normal at a
point on it. Distances are in units of |d|; `INF` marks a miss.
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp

from dmcr_jax.visuals.jax_render_scene import BOX, CAPSULE, CYLINDER, ELLIPSOID, PLANE, SPHERE

INF = 1e10
_EPS = 1e-6


# ---------------------------------------------------------------------------
# 3-vectors as (x, y, z) tuples
# ---------------------------------------------------------------------------
# The per-pixel code holds a 3-vector as three arrays (or three scalars), never as
# an array with a length-3 axis: the same code then runs inside the fused GPU kernel
# (`jax_render_kernel`, where a block's arrays must have power-of-two shapes) and
# under XLA, where a sum over a length-3 axis would be a reduction that ends a GPU
# fusion (measured rows: benchmarks/results/jax_render_h100.jsonl).
# A 3×3 matrix is a 9-tuple, row-major.


def _v(a) -> tuple:
  """An (..., 3) array as an (x, y, z) tuple."""
  return (a[..., 0], a[..., 1], a[..., 2])


def _add(a, b):
  return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _sub(a, b):
  return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _scale(a, s):
  return (a[0] * s, a[1] * s, a[2] * s)


def _dot(a, b):
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _norm(a):
  return jnp.sqrt(_dot(a, a))


def _unit(a):
  n = jnp.maximum(_norm(a), 1e-12)
  return (a[0] / n, a[1] / n, a[2] / n)


def _where(c, a, b):
  return (jnp.where(c, a[0], b[0]), jnp.where(c, a[1], b[1]), jnp.where(c, a[2], b[2]))


def _vec_mat(v, m):
  """``v @ m`` (a world vector into the frame whose axes are m's columns)."""
  return (v[0] * m[0] + v[1] * m[3] + v[2] * m[6], v[0] * m[1] + v[1] * m[4] + v[2] * m[7],
          v[0] * m[2] + v[1] * m[5] + v[2] * m[8])


def _mat_vec(m, v):
  """``m @ v``."""
  return (m[0] * v[0] + m[1] * v[1] + m[2] * v[2], m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
          m[6] * v[0] + m[7] * v[1] + m[8] * v[2])


# ---------------------------------------------------------------------------
# Ray–primitive intersections (object frame)
# ---------------------------------------------------------------------------


def _sphere_t(o, d, r, unit: bool = False):
  """Entry distance of rays o + t·d into a sphere of radius r at the origin
  (`unit`: the directions are unit vectors, |d|² = 1 is not recomputed)."""
  b = _dot(o, d)
  c = _dot(o, o) - r * r
  if unit:
    disc = b * b - c
    t = -b - jnp.sqrt(jnp.maximum(disc, 0.0))
  else:
    a = _dot(d, d)
    disc = b * b - a * c
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / a
  return jnp.where((disc >= 0) & (t > _EPS), t, INF)


def _side_hit(o, d, r, h):
  """Where rays enter the side of a z-axis cylinder of radius r, |z| ≤ h: the
  entry distance t into the infinite cylinder, its height z there, whether that
  is a hit on the side, and whether the ray is slanted (not along the axis)."""
  a = d[0] * d[0] + d[1] * d[1]
  b = o[0] * d[0] + o[1] * d[1]
  c = o[0] * o[0] + o[1] * o[1] - r * r
  disc = b * b - a * c
  slanted = a > 1e-12
  t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.where(slanted, a, 1.0)
  z = o[2] + t * d[2]
  return t, z, slanted & (disc >= 0) & (t > _EPS) & (jnp.abs(z) <= h), slanted


def _capsule_t(o, d, r, h, unit: bool = False):
  """Entry distance into a z-axis capsule (radius r, segment |z| ≤ h).

  One end sphere is tested, not both: a ray that enters the capsule's infinite
  cylinder beyond one end of the segment can only enter the capsule through that
  end's hemisphere (rays along the axis: the end facing the ray's origin)."""
  t, z, side, slanted = _side_hit(o, d, r, h)
  end = jnp.where(jnp.where(slanted, z > 0, d[2] < 0), h, -h)
  return jnp.where(side, t, _sphere_t((o[0], o[1], o[2] - end), d, r, unit))


def _intersect(typ: int, o, d, size, unit: bool = False):
  """`intersect` on (x, y, z) tuples; `size` a tuple of three scalars."""
  if typ == PLANE:
    down = d[2] < -1e-12
    t = -o[2] / jnp.where(down, d[2], -1.0)
    x = o[0] + t * d[0]
    y = o[1] + t * d[1]
    ok = down & (o[2] > 0) & (t > _EPS)
    ok &= (size[0] <= 0) | (jnp.abs(x) <= size[0])
    ok &= (size[1] <= 0) | (jnp.abs(y) <= size[1])
    return jnp.where(ok, t, INF)
  if typ == SPHERE:
    return _sphere_t(o, d, size[0], unit)
  if typ == ELLIPSOID:
    return _sphere_t((o[0] / size[0], o[1] / size[1], o[2] / size[2]),
                     (d[0] / size[0], d[1] / size[1], d[2] / size[2]), 1.0)
  if typ == CAPSULE:
    return _capsule_t(o, d, size[0], size[1], unit)
  if typ == CYLINDER:
    r, h = size[0], size[1]
    dz = d[2]
    axial = jnp.abs(dz) > 1e-12
    tc = (jnp.where(dz < 0, h, -h) - o[2]) / jnp.where(axial, dz, 1.0)
    x = o[0] + tc * d[0]
    y = o[1] + tc * d[1]
    okc = axial & (tc > _EPS) & (x * x + y * y <= r * r)
    okc &= jnp.abs(o[2]) > h          # entering through the cap from outside
    t, _, side, _ = _side_hit(o, d, r, h)
    return jnp.minimum(jnp.where(side, t, INF), jnp.where(okc, tc, INF))
  if typ == BOX:
    lo, hi = [], []
    for i in range(3):
      inv = 1.0 / jnp.where(jnp.abs(d[i]) > 1e-12, d[i], 1e-12)
      t1, t2 = (-size[i] - o[i]) * inv, (size[i] - o[i]) * inv
      lo.append(jnp.minimum(t1, t2))
      hi.append(jnp.maximum(t1, t2))
    tn = jnp.maximum(jnp.maximum(lo[0], lo[1]), lo[2])
    tf = jnp.minimum(jnp.minimum(hi[0], hi[1]), hi[2])
    return jnp.where((tn <= tf) & (tn > _EPS), tn, INF)
  raise NotImplementedError(f"geom type {typ}")


def intersect(typ: int, o: jax.Array, d: jax.Array, size: jax.Array,
              unit: bool = False) -> jax.Array:
  """Nearest front-side hit distance of rays with one primitive, in its frame.

  Args:
    typ: static geom type (`PLANE`, `SPHERE`, `CAPSULE`, `ELLIPSOID`,
      `CYLINDER`, `BOX`).
    o, d: (..., 3) ray origins and directions in the object frame (d need not
      be unit; t is in units of |d|).
    size: (3,) MuJoCo size (`geom_size` layout: sphere r; capsule/cylinder r,
      half-length; ellipsoid/box half-axes; plane half-extents, 0 = infinite).
    unit: (static) the directions are unit vectors, which spares spheres and
      capsules one dot product per ray.

  Returns:
    (...,) distance t > 0 of the entry point, `INF` where the ray misses (or
    starts inside: MuJoCo culls back faces, so the inside is not drawn).
  """
  return _intersect(typ, _v(o), _v(d), (size[0], size[1], size[2]), unit)


def _normal_local(typ, p, size, present: Sequence[int]):
  """Outward unit normal at object-frame points p on primitives of per-point type
  `typ` (int array) and per-point `size`; `present`: the types that can occur."""
  zero = jnp.zeros_like(p[0])
  one = jnp.ones_like(p[0])
  n = (zero, zero, one)                                     # plane
  if SPHERE in present:
    n = _where(typ == SPHERE, p, n)
  if ELLIPSOID in present:
    e = tuple(p[i] / jnp.maximum(size[i] * size[i], 1e-12) for i in range(3))
    n = _where(typ == ELLIPSOID, e, n)
  if CAPSULE in present:
    c = (p[0], p[1], p[2] - jnp.clip(p[2], -size[1], size[1]))
    n = _where(typ == CAPSULE, c, n)
  if CYLINDER in present:
    radial = jnp.sqrt(p[0] * p[0] + p[1] * p[1])
    on_cap = jnp.abs(jnp.abs(p[2]) - size[1]) < jnp.abs(radial - size[0])
    c = _where(on_cap, (zero, zero, jnp.sign(p[2])), (p[0], p[1], zero))
    n = _where(typ == CYLINDER, c, n)
  if BOX in present:
    q = tuple(jnp.abs(p[i]) / jnp.maximum(size[i], 1e-12) for i in range(3))
    x_axis = (q[0] >= q[1]) & (q[0] >= q[2])              # argmax's choice: first of ties
    y_axis = ~x_axis & (q[1] >= q[2])
    z_axis = ~x_axis & ~y_axis
    b = tuple(jnp.where(a, jnp.sign(p[i]), 0.0) for i, a in enumerate((x_axis, y_axis,
                                                                      z_axis)))
    n = _where(typ == BOX, b, n)
  return _unit(n)
