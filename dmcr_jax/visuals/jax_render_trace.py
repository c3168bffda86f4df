"""The JAX ray caster's per-pixel tracer: nearest hits and one env's pixels.

`trace_pixels` computes the colour and the nearest object of some rays of one env
from its packed numbers (`jax_render_pack`), read through a reader, so the same
code runs under XLA (`jax_render.render`) and inside the fused GPU kernel
(`jax_render_kernel`); `image_from_planes` turns its colour planes into a uint8
image. Nearest hits come in two equal forms, chosen by `running_minima`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from dmcr_jax.visuals.jax_render_geometry import (INF, _add, _dot, _intersect, _mat_vec,
                                                  _norm, _normal_local, _scale, _sub, _unit,
                                                  _vec_mat)
from dmcr_jax.visuals.jax_render_pack import Layout, _obj_numbers
from dmcr_jax.visuals.jax_render_shade import _floor_color, _shade, _sky_color

TRANSPARENT_BELOW = 0.995     # MuJoCo: rgba alpha < 0.995 is drawn as transparent
# Mip selection: a pixel's floor footprint × MIP_SCALE / cos(incidence)^MIP_COS_POWER
# (1, 1: GL's isotropic rule).
MIP_SCALE = 1.0
MIP_COS_POWER = 1.0


# ---------------------------------------------------------------------------
# Tracing
# ---------------------------------------------------------------------------


# Nearest hits come in two forms, chosen by backend (`running_minima`), with the
# same result (ties go to the lower object index in both; tested): on a GPU, a
# running minimum folded in object by object, which keeps each trace in registers
# instead of writing a (K, P) array of distances and reducing it; on XLA's CPU
# backend, which runs the long select chains several times slower, the stacked
# distances and argmin (measured rows: jax_render_h100.jsonl, jax_render_cpu.jsonl in
# benchmarks/results/).
# The fused GPU kernel always folds.


def running_minima() -> bool:
  """Whether renders traced now use the running-minimum form (default backend
  is not the CPU)."""
  return jax.default_backend() != "cpu"


def _local_t(L: Layout, R, k: int, o, d, casters: bool = False):
  """Distances of unit world rays to object k (`INF` where missed, where the object
  is invisible, and with `casters` where it casts no shadow)."""
  read = lambda i: R.f(L.OBJ * k + i)
  pos, mat, size, rgba = _obj_numbers(read)[:4]
  t = _intersect(L.types[k], _vec_mat(_sub(o, pos), mat), _vec_mat(d, mat), size,
                 unit=True)
  keep = rgba[3] > 0
  if casters:
    keep &= read(Layout.CASTER) > 0
  return jnp.where(keep, t, INF)


def _fold(t, k: int, t_best, k_best):
  """One step of a running minimum: (t, k) where t is nearer than t_best (ties
  keep the earlier object, as argmin does)."""
  closer = t < t_best
  return jnp.where(closer, t, t_best), jnp.where(closer, k, k_best)


def _nearest(L: Layout, R, o, d, *, running: bool, casters: bool = False, skip=None):
  """Nearest hit (t, k) of rays over the objects (`INF`, 0 where none); `casters`:
  shadow casters only; `skip` leaves one object out."""
  shape = jnp.shape(d[0])
  objs = [k for k in range(L.num_objects) if k != skip]
  ts = {k: _local_t(L, R, k, o, d, casters) for k in objs}
  if not running:
    ts = jnp.stack([ts.get(k, jnp.full(shape, INF)) for k in range(L.num_objects)])
    return jnp.min(ts, 0), jnp.argmin(ts, 0).astype(jnp.int32)
  t_best = jnp.full(shape, INF)
  k_best = jnp.zeros(shape, jnp.int32)
  for k, t in ts.items():
    t_best, k_best = _fold(t, k, t_best, k_best)
  return t_best, k_best


def _primary(L: Layout, R, o, d, dz, *, running: bool):
  """What primary rays see: the nearest opaque hit (t, k), the nearest object of
  any kind (segmentation, −1 where none) and the two nearest transparent hits
  (t, k) in front of the opaque one (`INF` where none)."""
  shape = jnp.shape(d[0])
  ts, opaque = [], []
  for k in range(L.num_objects):
    t = _local_t(L, R, k, o, d)
    ts.append(jnp.where(t * -dz < L.znear, INF, t))               # near clip plane
    opaque.append(R.f(L.OBJ * k + Layout.RGBA + 3) >= TRANSPARENT_BELOW)
  if not running:
    ts = jnp.stack(ts)                                            # (K, P)
    op = jnp.stack([jnp.broadcast_to(a, shape) for a in opaque])
    t_op = jnp.where(op, ts, INF)
    k_o, t_o = jnp.argmin(t_op, axis=0), jnp.min(t_op, axis=0)
    seg = jnp.where(jnp.min(ts, 0) < INF, jnp.argmin(ts, axis=0), -1)
    t_tr = jnp.where(~op & (ts < t_o[None]), ts, INF)
    k_1, t_1 = jnp.argmin(t_tr, axis=0), jnp.min(t_tr, axis=0)
    t_tr2 = jnp.where(jnp.arange(L.num_objects)[:, None] == k_1[None], INF, t_tr)
    k_2, t_2 = jnp.argmin(t_tr2, axis=0), jnp.min(t_tr2, axis=0)
    i32 = lambda a: a.astype(jnp.int32)
    return (t_o, i32(k_o)), i32(seg), (t_1, i32(k_1)), (t_2, i32(k_2))
  inf = jnp.full(shape, INF)
  zero = jnp.zeros(shape, jnp.int32)
  t_o, k_o, t_a, k_a, t_1, k_1, t_2, k_2 = inf, zero, inf, zero, inf, zero, inf, zero
  for k, (t, op) in enumerate(zip(ts, opaque)):
    t_a, k_a = _fold(t, k, t_a, k_a)
    t_o, k_o = _fold(jnp.where(op, t, INF), k, t_o, k_o)
    tk = jnp.where(op, INF, t)
    first, second = tk < t_1, (tk >= t_1) & (tk < t_2)
    t_2 = jnp.where(first, t_1, jnp.where(second, tk, t_2))
    k_2 = jnp.where(first, k_1, jnp.where(second, k, k_2))
    t_1, k_1 = jnp.where(first, tk, t_1), jnp.where(first, k, k_1)
  # the two nearest transparent hits overall, kept only in front of the opaque one
  t_1, t_2 = jnp.where(t_1 < t_o, t_1, INF), jnp.where(t_2 < t_o, t_2, INF)
  return (t_o, k_o), jnp.where(t_a < INF, k_a, -1), (t_1, k_1), (t_2, k_2)


def _camera_rays(L: Layout, R, pix, height: int, width: int, supersample: int):
  """Unit world directions of the rays of flat pixel indices `pix` (row-major from
  the top of an (H·s, W·s) grid) and their camera-frame z."""
  hs, ws = height * supersample, width * supersample
  tan = math.tan(math.radians(L.fovy) / 2)
  row = (pix // ws).astype(jnp.float32)
  col = (pix % ws).astype(jnp.float32)
  ys = (1 - 2 * (row + 0.5) / hs) * tan
  xs = (2 * (col + 0.5) / ws - 1) * (tan * width / height)
  dc = _unit((xs, ys, -jnp.ones_like(xs)))
  cam = tuple(R.f(L.cam + 3 + i) for i in range(9))
  return _mat_vec(cam, dc), dc[2]


def trace_pixels(L: Layout, R, pix, *, height: int, width: int, shadows: bool,
                 reflection: bool, supersample: int = 1, running: bool = True,
                 skip_empty: bool = False):
  """Colour and nearest object of some pixels of one env.

  The per-pixel part of the renderer, written once for XLA (`render`) and the
  fused GPU kernel (`jax_render_kernel`).

  Args:
    L: the scene's `Layout` (static).
    R: a reader of the env's packed numbers and the scene's textures
      (`ArrayReader`, or the kernel's).
    pix: int32 flat indices of the rays (row-major over H·s × W·s).
    height, width, shadows, reflection, supersample: as `render`.
    running: the nearest-hit form (`running_minima`).
    skip_empty: skip, for the whole of `pix`, work none of its rays needs (the
      opaque shading when none hits a surface, the sky when all do, the
      reflection when none sees the floor, the transparent layers when none meets
      a transparent object; `lax.cond`, which under vmap computes both sides):
      for the GPU kernel, where `pix` is one program's block; same result.

  Returns:
    ((r, g, b) in [0, 1], object id or −1), each shaped as `pix`.
  """
  d, dz = _camera_rays(L, R, pix, height, width, supersample)
  o = tuple(R.f(L.cam + i) for i in range(3))
  (t_o, k_op), seg, (t_1, k_t1), (t_2, k_t2) = _primary(L, R, o, d, dz, running=running)
  # Fences (`R.fence`) after the primary hits, each shadow ray, the reflection ray
  # and the opaque colour cut the per-pixel graph into the pieces XLA fuses.
  (t_o, k_op, seg, t_1, k_t1, t_2, k_t2, d, dz) = R.fence((t_o, k_op, seg, t_1, k_t1,
                                                           t_2, k_t2, d, dz))
  present = sorted(set(L.types))
  floor_obj = L.floor_obj
  nl = L.num_lights

  def light(l: int, on):
    b = L.light(l)
    v3 = lambda i: (R.f(b + i), R.f(b + i + 1), R.f(b + i + 2))
    kind = "dir" if L.light_types[l] == 1 else "spot"
    return (kind, v3(0), v3(3), v3(6), v3(9), v3(12), v3(15), R.f(b + 18), R.f(b + 19), on)

  cam_mat = tuple(R.f(L.cam + 3 + i) for i in range(9))
  head_v = lambda i: (R.f(L.head + i), R.f(L.head + i + 1), R.f(L.head + i + 2))
  head = ("dir", o, (-cam_mat[2], -cam_mat[5], -cam_mat[8]), head_v(0), head_v(3),
          head_v(6), None, None, None, None)

  def surface(k, t, origin, dirs):
    """World point, object-frame point, world normal and numbers of object k."""
    base = k * L.OBJ
    read = lambda i: R.f_at(i, base)
    obj = _obj_numbers(read)
    pos, mat, size = obj[:3]
    typ = read(Layout.TYPE).astype(jnp.int32)
    p = _add(origin, _scale(dirs, t))
    pl = _vec_mat(_sub(p, pos), mat)
    n = _mat_vec(mat, _normal_local(typ, pl, size, present))
    return p, pl, n, obj

  def lit(obj, p, n, v, scale, on_shadowed, tex):
    """Colour of surface points: pass 1 (headlight + lights without shadows)
    plus pass 2 (shadow lights × visibility), each clamped, times the texture."""
    rgba, sp, sh, em = obj[3], obj[4], obj[5], obj[6]
    pass1, pass2 = [head], []
    for l in range(nl):
      if L.light_shadow[l] and on_shadowed is not None:
        pass2.append(light(l, on_shadowed[l]))
      else:
        pass1.append(light(l, None))
    c = _shade(n, p, v, scale, rgba, sp, sh, em, pass1)
    if pass2:
      c2 = _shade(n, p, v, scale, rgba, sp, sh, 0.0, pass2)
      c = tuple(a + b for a, b in zip(c, c2))
    if tex is not None:
      c = tuple(a * b for a, b in zip(c, tex))
    return tuple(jnp.clip(a, 0.0, 1.0) for a in c)

  def shadow_vis(p, n):
    """Per light, 1/0 per pixel: the point sees light l (rays against casters)."""
    vis = []
    for l in range(nl):
      if not (L.light_shadow[l] and shadows):
        vis.append(None)
        continue
      b = L.light(l)
      if L.light_types[l] == 1:
        to = (-R.f(b + 3), -R.f(b + 4), -R.f(b + 5))
        to = tuple(jnp.broadcast_to(x, jnp.shape(p[0])) for x in to)
        maxd = INF
      else:
        to = _sub((R.f(b), R.f(b + 1), R.f(b + 2)), p)
        maxd = _norm(to)
        safe = jnp.maximum(maxd, 1e-12)
        to = (to[0] / safe, to[1] / safe, to[2] / safe)
      origin = _add(p, _scale(n, 1e-4))
      tmin, _ = _nearest(L, R, origin, to, running=running, casters=True)
      vis.append(R.fence((tmin >= maxd).astype(jnp.float32)))
    return vis

  def when(pred, fn, *args):
    """fn(*args), or with `skip_empty` and `pred` false, args (or zeros) unchanged."""
    if not skip_empty:
      return fn(*args)
    keep = (lambda *a: a[0] if len(a) == 1 else a) if args else (
        lambda: tuple(jnp.zeros_like(t_o) for _ in range(3)))
    return jax.lax.cond(pred, fn, keep, *args)

  hit = t_o < INF
  v = (-d[0], -d[1], -d[2])

  # ---- opaque surface (its colour counts only where `hit`)
  def opaque():
    t_hit = jnp.where(hit, t_o, 0.0)
    p, pl, n, obj = surface(k_op, t_hit, o, d)
    if floor_obj >= 0:
      floor_px = (k_op == floor_obj) & hit
      pix_angle = 2 * math.tan(math.radians(L.fovy) / 2) / (height * supersample)
      cos_in = jnp.maximum(jnp.abs(_dot(d, n)), 1e-3)
      footprint = t_hit * pix_angle * (-dz) * MIP_SCALE / cos_in ** MIP_COS_POWER
      size_at = L.OBJ * floor_obj + Layout.SIZE
      half = (R.f(size_at), R.f(size_at + 1))
      fc = _floor_color(L, R, pl, footprint, half)
      tex = tuple(jnp.where(floor_px, c, 1.0) for c in fc)
    else:
      tex = None
    color = lit(obj, p, n, v, 1.0, shadow_vis(p, n), tex)
    if not (reflection and floor_obj >= 0):
      return color

    def reflect(color):
      rd = _sub(d, _scale(n, 2 * _dot(d, n)))
      ro = _add(p, _scale(n, 1e-4))
      t_r, k_r = R.fence(_nearest(L, R, ro, rd, running=running, skip=floor_obj))
      rhit = (t_r < INF) & floor_px
      rp, _, rn, robj = surface(k_r, jnp.where(rhit, t_r, 0.0), ro, rd)
      refl = R.f(L.floor)
      # transparent geoms are blended twice over the (black) reflection buffer
      a_r = robj[3][3]
      a_r = jnp.where(a_r >= TRANSPARENT_BELOW, 1.0, 1 - (1 - a_r) ** 2)
      rc = lit(robj, rp, rn, (-rd[0], -rd[1], -rd[2]), refl, None, None)
      keep = rhit & (refl > 0)
      return tuple(jnp.where(keep, jnp.clip(c + a_r * r, 0, 1), c)
                   for c, r in zip(color, rc))
    return when(jnp.max(floor_px.astype(jnp.float32)) > 0, reflect, color)

  color = R.fence(when(jnp.min(t_o) < INF, opaque))
  sky = when(jnp.max(t_o) >= INF, lambda: _sky_color(L, R, d))
  color = tuple(jnp.where(hit, c, s) for c, s in zip(color, sky))

  # ---- transparent layers (two passes: front to back, then back to front)
  def layer(k, t):
    ok = t < INF
    lp, _, ln, lobj = surface(k, jnp.where(ok, t, 0.0), o, d)
    c = lit(lobj, lp, ln, v, 1.0, None, None)
    return c, jnp.where(ok, lobj[3][3], 0.0)

  def layers(color):
    c1, a1 = layer(k_t1, t_1)
    c2, a2 = layer(k_t2, t_2)
    blend = lambda dst, c, a: tuple(a * ci + (1 - a) * di for ci, di in zip(c, dst))
    color = blend(blend(color, c1, a1), c2, a2)      # front to back
    return blend(blend(color, c2, a2), c1, a1)       # back to front

  color = when(jnp.min(t_1) < INF, layers, color)
  return color, seg


def image_from_planes(rgb, height: int, width: int, supersample: int = 1) -> jax.Array:
  """uint8 (..., H, W, 3) image from colour planes (..., 3, ≥ H·s·W·s) in [0, 1]
  (averaging s × s rays per pixel)."""
  s = supersample
  lead = rgb.shape[:-2]
  c = rgb[..., :height * s * width * s].reshape(lead + (3, height, s, width, s))
  img = c.mean((-3, -1)) if s > 1 else c.reshape(lead + (3, height, width))
  img = jnp.moveaxis(img, -3, -1)
  return jnp.clip(jnp.round(img * 255.0), 0, 255).astype(jnp.uint8)
