"""One env's numbers for the JAX ray caster: frames, the packed `Layout`, readers.

Per env, before the pixels: the camera frame (MuJoCo's camera modes), the lights'
world positions and directions, the objects' world frames, sizes and colours; then
`pack_env` writes them (with the look's floor and sky) into one float32 and one
int32 vector in the order a `Layout` names, and `ArrayReader` reads them (and the
texture bank) for the per-pixel code under XLA.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import jax
import jax.numpy as jnp

from dmcr_jax.visuals.jax_render_scene import PLANE, BodyPoses, DeviceLook, Scene


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


def fences_by_default() -> bool:
  """Whether renders traced now fence their per-pixel graph (`ArrayReader.fence`):
  where the default backend is not the CPU. XLA:CPU compiles the unfenced graph as
  fast, and unfenced its rounding does not depend on the batch shape the render is
  compiled for, which exact comparisons between batchings on the CPU rely on."""
  return jax.default_backend() != "cpu"


class ArrayReader:
  """Reads one env's packed numbers and the scene's textures from arrays (XLA).

  The per-pixel code reads through this interface only; `jax_render_kernel` has
  the same methods over a GPU kernel's memory references.
  """

  def __init__(self, floats, ints, texels, skies):
    self.floats, self.ints, self.texels, self.skies = floats, ints, texels, skies
    self.fences = fences_by_default()

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

  def fence(self, values):
    """`values` (a pytree) unchanged; with `fences`, behind
    `lax.optimization_barrier`: XLA then fuses the per-pixel graph on either side
    of a fence separately, which keeps its GPU fusion pass's graphs small (the
    same function; a compile-time and speed matter only)."""
    return jax.lax.optimization_barrier(values) if self.fences else values


def _obj_numbers(read):
  """An object's position, frame, size, rgba, specular, shininess and emission, from
  `read(i)`, its i-th packed float (`Layout` offsets): scalars for one object, or
  per pixel for per-pixel object ids."""
  v = lambda i, n: tuple(read(i + j) for j in range(n))
  return (v(Layout.POS, 3), v(Layout.MAT, 9), v(Layout.SIZE, 3), v(Layout.RGBA, 4),
          read(Layout.SPECULAR), read(Layout.SHININESS), read(Layout.EMISSION))
