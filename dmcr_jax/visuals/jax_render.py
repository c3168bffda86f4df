"""A JAX ray caster for DMCR frames: MuJoCo's picture computed on the accelerator.

`render(scene, poses, look)` draws one env's frame (uint8 H × W × 3) from its body
poses (`jax_render_scene.poses(mjx_data)`) and its look (`DeviceLook`). It is a
pure, jittable function written for one env; batch it with `jax.vmap` (or use
`render_batch`). The scene (`jax_render_scene.build_scene`) holds the geoms and
sites MuJoCo's default camera draws, the lights and the texture bank on device.

What it reproduces of MuJoCo's fixed-function renderer (render_gl3.c, 3.x):
* camera: MuJoCo's fixed / track / trackcom modes from the look's camera fields,
  vertical field of view `fovy`, the image's aspect, pixel centres, znear clip;
* geometry: analytic nearest hits of planes (finite or infinite, front side),
  spheres, ellipsoids, capsules, cylinders (with caps) and boxes;
* shading, per pixel (MuJoCo lights per vertex): the headlight (a directional
  light along the camera's forward axis) and the model's lights (directional or
  spot with cutoff, exponent and attenuation; the light a look moves takes the
  look's diffuse and specular colour), each with ambient, diffuse and specular
  terms (local viewer, Blinn half vector, GL exponent 128 × shininess),
  material emission; colours clamp per pass as in GL;
* shadows (`shadows=True`): the shadow-casting light lights only the points a
  ray towards it reaches without hitting a geom (MuJoCo: shadow map); as in
  MuJoCo, that light reaches opaque surfaces only through the shadow pass;
* floor: the look's texture with the material's texrepeat (texuniform), bilinear
  within a mip level picked from the pixel's footprint, blended between levels
  (trilinear, as GL_LINEAR_MIPMAP_LINEAR);
* reflection (`reflection=True`): the floor adds `reflectance ×` the colour a
  mirrored ray sees (MuJoCo's stencil reflection: reflected geoms' colours are
  scaled by the reflectance, the sky is not reflected);
* transparency: objects with alpha < 0.995 are blended over what is behind
  them in two passes (front to back, then back to front, MuJoCo's order) for the
  two nearest transparent layers of each pixel;
* background: the look's skybox sampled by ray direction (cube map, MuJoCo's
  skybox axis convention), unlit.
Not reproduced: multisample anti-aliasing (`supersample=2` averages 2×2 rays per
pixel instead), per-vertex (Gouraud) shading and the tessellation of curved
geoms, the shadow map's resolution and bias, more than two transparent layers.
The floor texture's origin (the plane's (−x, +y) corner) is matched to
`mujoco.Renderer`'s frames (MuJoCo 3.17), not taken from its source.

Parity with MuJoCo's renderer (mean absolute pixel difference per frame and
per-body silhouette IoU against its segmentation render, per domain) is measured by
`dmcr_jax.benchmarks.jax_render_parity`; its table is benchmarks/results/jax_render_parity_cpu.md.
The frames differ most where MuJoCo's per-vertex lighting and tessellation show:
walker's reflection and shadow edges, reacher's spotlight low over the floor, and
the edge pixels of small spheres and ellipsoids.

How it is built: `pack_env` (per env, a few hundred numbers: object frames, sizes and
colours, camera, lights, floor and sky) and `trace_pixels` (per pixel, reading those
numbers and the texture bank through a reader: `ArrayReader` here, the kernel's
`RefReader` in `jax_render_kernel`). The per-pixel code holds 3-vectors as (x, y, z)
tuples, so it runs both under XLA and inside one fused Pallas kernel.

On a GPU `render_batch` draws every env in one fused kernel (`jax_render_kernel`;
its frames equal this module's XLA path's); `kernel=False` takes the XLA path
(nearest hits as running minima, in chunks of envs). On the CPU the nearest hits are
taken from stacked distances (`running_minima`; both forms give the same frames).
Speeds of both paths: benchmarks/results/jax_render_h100.md.

Used by `dmcr_jax.make(..., renderer="jax")` (`dmcr_jax.jax_env`: physics, this
renderer and frame stacks in one jitted call) and `train --renderer jax`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Mapping, Sequence

import jax
import jax.numpy as jnp

from dmcr_jax.visuals.jax_render_scene import (BOX, CAPSULE, CYLINDER, ELLIPSOID, PLANE,
                                               SPHERE, BodyPoses, DeviceLook, Scene,
                                               build_scene, device_looks, poses)

__all__ = ["render", "render_batch", "render_with_ids", "build_scene", "device_looks",
           "poses", "intersect", "camera_frame", "running_minima", "Layout", "layout",
           "look_layout", "pack_env", "trace_pixels", "image_from_planes", "use_kernel"]

INF = 1e10
_EPS = 1e-6
TRANSPARENT_BELOW = 0.995     # MuJoCo: rgba alpha < 0.995 is drawn as transparent
# Mip selection: a pixel's floor footprint × MIP_SCALE / cos(incidence)^MIP_COS_POWER
# (1, 1: GL's isotropic rule).
MIP_SCALE = 1.0
MIP_COS_POWER = 1.0


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


# Frames of objects, the camera and lights (per env, outside the per-pixel code) are
# written out too: as batched matrix products a GPU may compute them in
# TensorFloat-32 (XLA's default precision for float32 dots), whose 10-bit mantissa
# moves silhouette edges; written out, they are full float32 on every backend.


def _mat_vec_a(m, v):
  """``m @ v`` for 3×3 matrices (..., 3, 3) and 3-vectors (..., 3), as arrays."""
  return m[..., :, 0] * v[..., 0:1] + m[..., :, 1] * v[..., 1:2] + m[..., :, 2] * v[..., 2:3]


def _mat_mat_a(a, b):
  """``a @ b`` for 3×3 matrices (..., 3, 3), in full float32 on every backend."""
  return (a[..., :, 0:1] * b[..., 0:1, :] + a[..., :, 1:2] * b[..., 1:2, :]
          + a[..., :, 2:3] * b[..., 2:3, :])


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


# ---------------------------------------------------------------------------
# Camera, lights and object frames of one env (per env, before the pixels)
# ---------------------------------------------------------------------------


def _quat_to_mat(q: jax.Array) -> jax.Array:
  q = q / jnp.linalg.norm(q)
  w, x, y, z = q[0], q[1], q[2], q[3]
  return jnp.array([
      [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
      [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
      [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])


def camera_frame(scene: Scene, bp: BodyPoses, look: DeviceLook):
  """Camera position and orientation (columns: right, up, backward) in the world.

  MuJoCo's camera modes: fixed (pose in its body frame), track (body position +
  `cam_pos0`, fixed orientation `cam_mat0`), trackcom (subtree centre of mass +
  `cam_poscom0`, `cam_mat0`).
  """
  src = look if scene.cam_looked else scene
  b = scene.cam_body
  if scene.cam_mode == 0:
    rot = _quat_to_mat(src.cam_quat)
    pos = bp.xpos[b] + _mat_vec_a(bp.xmat[b], src.cam_pos)
    return pos, _mat_mat_a(bp.xmat[b], rot)
  mat = src.cam_mat0.reshape(3, 3)
  if scene.cam_mode == 1:
    return bp.xpos[b] + src.cam_pos0, mat
  return bp.subtree_com[b] + src.cam_poscom0, mat


def _lights(scene: Scene, bp: BodyPoses, look: DeviceLook):
  """World position and unit direction of every model light (MuJoCo's modes)."""
  pos, dirs = [], []
  for l, (mode, b) in enumerate(zip(scene.light_modes, scene.light_bodies)):
    looked = l == scene.light_looked
    lp = look.light_pos if looked else scene.light_pos[l]
    ld = look.light_dir if looked else scene.light_dir[l]
    lp0 = look.light_pos0 if looked else scene.light_pos0[l]
    lc0 = look.light_poscom0 if looked else scene.light_poscom0[l]
    ld0 = look.light_dir0 if looked else scene.light_dir0[l]
    if mode == 0:
      p, dvec = bp.xpos[b] + _mat_vec_a(bp.xmat[b], lp), _mat_vec_a(bp.xmat[b], ld)
    elif mode == 1:
      p, dvec = bp.xpos[b] + lp0, ld0
    else:
      p, dvec = bp.subtree_com[b] + lc0, ld0
    pos.append(p)
    dirs.append(dvec / jnp.maximum(jnp.linalg.norm(dvec), 1e-12))
  return pos, dirs


def _objects(scene: Scene, bp: BodyPoses, look: DeviceLook,
             variables: Mapping[str, jax.Array] | None):
  """World frames, sizes and colours of the scene's objects for one env."""
  local_pos, size = scene.local_pos, scene.size
  rgba = jnp.where(scene.mat_slot[:, None] >= 0,
                   look.mat_rgba[jnp.maximum(scene.mat_slot, 0)], scene.rgba)
  if look.floor_rgba is not None and scene.floor_obj >= 0:
    rgba = rgba.at[scene.floor_obj].set(look.floor_rgba)
  for key, field, k in scene.variables:
    if variables is None or key not in variables:
      continue
    value = jnp.asarray(variables[key], jnp.float32)
    if field.endswith("_pos"):
      local_pos = local_pos.at[k].set(value)
    elif field.endswith("_size"):
      size = size.at[k].set(value)
    elif field.endswith("_rgba"):
      default = jnp.array([0.5, 0.5, 0.5, 1.0])
      use_mat = (scene.mat_slot[k] >= 0) & jnp.all(value == default)
      rgba = rgba.at[k].set(jnp.where(use_mat, rgba[k], value))
  xmat = bp.xmat[scene.body]                               # (K, 3, 3)
  pos = bp.xpos[scene.body] + _mat_vec_a(xmat, local_pos)
  mat = _mat_mat_a(xmat, scene.local_mat)
  return pos, mat, size, rgba


# ---------------------------------------------------------------------------
# One env's numbers, packed: what the per-pixel code reads
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Layout:
  """The static part of a scene the per-pixel code needs, and where each env's
  numbers lie in its packed vectors (`pack_env`).

  Floats (one vector per env): per object `OBJ` numbers (world position 3, frame 9
  row-major, size 3, rgba 4, specular, shininess, emission, casts-shadow flag,
  type); the camera (position 3, frame 9); per light `LIGHT` numbers (position 3,
  unit direction 3, ambient 3, diffuse 3, specular 3, attenuation 3, cutoff,
  exponent); the headlight (ambient, diffuse, specular: 9); the floor's
  reflectance and texrepeat (2). Ints: the floor's mip level count, the sky, and
  the floor texture's per-level texel offset, width and height. With `sky_blend`
  (a look whose background moves) one more float, the second sky's weight, and one
  more int, the second sky.
  """
  types: tuple
  floor_obj: int
  light_types: tuple
  light_shadow: tuple
  fovy: float
  znear: float
  levels: int
  sky_size: int
  sky_blend: bool = False

  OBJ = 24
  # offsets of an object's numbers within its OBJ floats
  POS, MAT, SIZE, RGBA, SPECULAR, SHININESS, EMISSION, CASTER, TYPE = (
      0, 3, 12, 15, 19, 20, 21, 22, 23)
  LIGHT = 20

  @property
  def num_objects(self) -> int:
    return len(self.types)

  @property
  def num_lights(self) -> int:
    return len(self.light_types)

  @property
  def cam(self) -> int:
    return self.OBJ * self.num_objects

  def light(self, l: int) -> int:
    return self.cam + 12 + self.LIGHT * l

  @property
  def head(self) -> int:
    return self.light(self.num_lights)

  @property
  def floor(self) -> int:
    return self.head + 9

  @property
  def num_floats(self) -> int:
    return self.floor + 3 + self.sky_blend

  # ints: 0 floor levels, 1 sky, then offsets, widths, heights per level
  def level_field(self, which: int) -> int:
    return 2 + which * self.levels

  @property
  def num_ints(self) -> int:
    return 2 + 3 * self.levels + self.sky_blend


def layout(scene: Scene, sky_blend: bool = False) -> Layout:
  """The scene's `Layout` (static; hashable); `sky_blend`: for looks that blend a
  second sky (`DeviceLook.sky2`)."""
  return Layout(types=tuple(scene.types), floor_obj=scene.floor_obj,
                light_types=tuple(scene.light_types),
                light_shadow=tuple(scene.light_shadow), fovy=scene.fovy, znear=scene.znear,
                levels=int(scene.floor_offset.shape[1]), sky_size=int(scene.skies.shape[2]),
                sky_blend=bool(sky_blend))


def look_layout(scene: Scene, look: DeviceLook) -> Layout:
  """The `Layout` of `scene` for looks shaped like `look` (static)."""
  return layout(scene, look.sky2 is not None)


def pack_env(scene: Scene, bp: BodyPoses, look: DeviceLook,
             variables: Mapping[str, jax.Array] | None = None):
  """One env's numbers for the per-pixel code: float32 (`num_floats`,) and int32
  (`num_ints`,) vectors in `layout(scene)`'s order (vmap it for a batch)."""
  pos, mat, size, rgba = _objects(scene, bp, look, variables)
  k = scene.num_objects
  caster = (~scene.decor & (jnp.asarray(scene.types) != PLANE)).astype(jnp.float32)
  objs = jnp.concatenate([pos, mat.reshape(k, 9), size, rgba, scene.specular[:, None],
                          scene.shininess[:, None], scene.emission[:, None],
                          caster[:, None],
                          jnp.asarray(scene.types, jnp.float32)[:, None]], axis=1)
  cam_pos, cam_mat = camera_frame(scene, bp, look)
  lpos, ldir = _lights(scene, bp, look)
  looked = lambda l, own, field: own if l == scene.light_looked else field[l]
  lights = [jnp.concatenate([lpos[l], ldir[l], scene.light_ambient[l],
                             looked(l, look.light_diffuse, scene.light_diffuse),
                             looked(l, look.light_specular, scene.light_specular),
                             scene.light_attenuation[l], scene.light_cutoff[l][None],
                             scene.light_exponent[l][None]]) for l in range(len(lpos))]
  f = look.floor
  blend = look.sky2 is not None
  floats = jnp.concatenate([objs.reshape(-1), cam_pos, cam_mat.reshape(9), *lights,
                            look.headlight.reshape(9),
                            jnp.reshape(look.floor_reflectance, (1,)),
                            scene.floor_repeat[f],
                            *([jnp.reshape(look.sky_mix, (1,))] if blend else [])
                            ]).astype(jnp.float32)
  ints = jnp.concatenate([scene.floor_levels[f][None], jnp.reshape(look.sky, (1,)),
                          scene.floor_offset[f], scene.floor_width[f],
                          scene.floor_height[f],
                          *([jnp.reshape(look.sky2, (1,))] if blend else [])
                          ]).astype(jnp.int32)
  L = layout(scene, blend)
  assert floats.shape == (L.num_floats,) and ints.shape == (L.num_ints,), "Layout drift"
  return floats, ints


class ArrayReader:
  """Reads one env's packed numbers and the scene's textures from arrays (XLA).

  The per-pixel code reads through this interface only; `jax_render_kernel` has
  the same methods over a GPU kernel's memory references.
  """

  def __init__(self, floats, ints, texels, skies):
    self.floats, self.ints, self.texels, self.skies = floats, ints, texels, skies

  def f(self, i: int):
    """Float `i` of the env (a scalar)."""
    return self.floats[i]

  def f_at(self, i: int, index):
    """Floats `i + index` (index: per-pixel int array)."""
    return self.floats[i + index]

  def i(self, i: int):
    """Int `i` of the env (a scalar)."""
    return self.ints[i]

  def i_at(self, i: int, index):
    """Ints `i + index`."""
    return self.ints[i + index]

  def texel(self, index):
    """Floor texel bytes at flat `index` (the scene's `floor_texels`, flattened)."""
    return self.texels[index]

  def sky(self, index):
    """Sky texel bytes at flat `index` (the scene's `skies`, flattened)."""
    return self.skies[index]


def _obj_numbers(read):
  """An object's position, frame, size, rgba, specular, shininess and emission, from
  `read(i)`, its i-th packed float (`Layout` offsets): scalars for one object, or
  per pixel for per-pixel object ids."""
  v = lambda i, n: tuple(read(i + j) for j in range(n))
  return (v(Layout.POS, 3), v(Layout.MAT, 9), v(Layout.SIZE, 3), v(Layout.RGBA, 4),
          read(Layout.SPECULAR), read(Layout.SHININESS), read(Layout.EMISSION))


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
      vis.append((tmin >= maxd).astype(jnp.float32))
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
      t_r, k_r = _nearest(L, R, ro, rd, running=running, skip=floor_obj)
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

  color = when(jnp.min(t_o) < INF, opaque)
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


def _render(scene: Scene, bp: BodyPoses, look: DeviceLook, variables, *, height, width,
            shadows, reflection, supersample, running=None):
  """Colour planes (3, P) in [0, 1] and nearest object (P,) of one env (−1: none),
  under XLA; `running`: the nearest-hit form (None: `running_minima()`)."""
  running = running_minima() if running is None else running
  floats, ints = pack_env(scene, bp, look, variables)
  reader = ArrayReader(floats, ints, scene.floor_texels.reshape(-1), scene.skies.reshape(-1))
  pix = jnp.arange(height * supersample * width * supersample, dtype=jnp.int32)
  color, seg = trace_pixels(look_layout(scene, look), reader, pix, height=height, width=width,
                            shadows=shadows, reflection=reflection,
                            supersample=supersample, running=running)
  return jnp.stack(color), seg


@functools.partial(jax.jit, static_argnames=("height", "width", "shadows", "reflection",
                                             "supersample"))
def render(scene: Scene, bp: BodyPoses, look: DeviceLook,
           variables: Mapping[str, jax.Array] | None = None, *, height: int = 84,
           width: int = 84, shadows: bool = True, reflection: bool = True,
           supersample: int = 1) -> jax.Array:
  """Renders one env's frame (under XLA; `render_batch` renders many).

  Args:
    scene: the domain's `Scene` (`build_scene`).
    bp: the env's `BodyPoses` (`poses(mjx_data)`; positions must be current).
    look: the env's `DeviceLook` (one row of `device_looks`).
    variables: task model variables (`State.info`, "geom_pos:target" → value).
    height, width: image size (static).
    shadows: shadow rays towards shadow-casting lights (static).
    reflection: the floor's reflection (static).
    supersample: rays per pixel along each axis, averaged (static; 1 = none).

  Returns:
    uint8 (height, width, 3), top row first (as `mujoco.Renderer`).
  """
  color, _ = _render(scene, bp, look, variables, height=height, width=width,
                     shadows=shadows, reflection=reflection, supersample=supersample)
  return image_from_planes(color, height, width, supersample)


@functools.partial(jax.jit, static_argnames=("height", "width"))
def render_with_ids(scene: Scene, bp: BodyPoses, look: DeviceLook,
                    variables: Mapping[str, jax.Array] | None = None, *,
                    height: int = 84, width: int = 84):
  """`render` plus the body id seen at each pixel (−1: background), as
  MuJoCo's segmentation rendering (nearest geom or site, transparency ignored).

  Returns:
    (uint8 (H, W, 3), int32 (H, W)).
  """
  color, seg = _render(scene, bp, look, variables, height=height, width=width,
                       shadows=True, reflection=True, supersample=1)
  body = jnp.where(seg >= 0, scene.seg_body[jnp.maximum(seg, 0)], -1)
  return image_from_planes(color, height, width, 1), body.reshape(height, width)


def use_kernel(kernel: bool | None) -> bool:
  """Whether to render in the fused GPU kernel: None (the default) on a GPU only;
  True insists (ValueError unless JAX's default backend is a GPU); False never."""
  gpu = jax.default_backend() == "gpu"
  if kernel and not gpu:
    raise ValueError(f"the fused render kernel needs a GPU (Pallas on Triton); JAX's "
                     f"backend here is {jax.default_backend()!r}: render without it "
                     f"(kernel=False / render_kernel=False, or None: the kernel on a "
                     f"GPU only)")
  return gpu if kernel is None else bool(kernel)


def render_batch(scene: Scene, bp: BodyPoses, look: DeviceLook,
                 variables: Mapping[str, jax.Array] | None = None, *,
                 chunk: int | None = None, kernel: bool | None = None,
                 **kwargs) -> jax.Array:
  """`render` over a leading env axis of `bp`, `look` and `variables`.

  Args:
    scene, bp, look, variables: as for `render`, batched (the scene is shared).
    chunk: without the kernel, envs are rendered `chunk` at a time (`lax.map`
      over vmapped chunks; a remainder is one more, smaller chunk), which bounds
      memory and, on a GPU, keeps a chunk's arrays in cache. The kernel ignores it.
    kernel: render every env's pixels in one fused GPU kernel
      (`jax_render_kernel`: the same per-pixel code and the same frames, faster).
      None (default): on a GPU; see `use_kernel`.
    **kwargs: `render`'s static options (height, width, shadows, …).

  Returns:
    uint8 (N, H, W, 3).
  """
  if use_kernel(kernel):
    from dmcr_jax.visuals import jax_render_kernel
    return jax_render_kernel.render_batch(scene, bp, look, variables, **kwargs)
  fn = functools.partial(render, **kwargs)
  if chunk is None:
    return jax.vmap(fn, in_axes=(None, 0, 0, 0 if variables else None))(
        scene, bp, look, variables)
  one = lambda args: fn(scene, *args)
  return jax.lax.map(one, (bp, look, variables), batch_size=chunk)
