"""Host side of the JAX ray caster: a domain's scene, its texture bank and looks on device.

`build_scene(render_model)` reads, once per domain, everything about the picture
that does not change per env or per step: which geoms and sites MuJoCo's default
render draws (taken from `mjv_updateScene` itself, so groups ≥ 3, visual flags and
the like are skipped exactly as dm_control's camera skips them), their types,
sizes, body frames, materials and lighting constants, the camera and the lights
(mode, body, type, colours, cone), and the floor and skybox textures of the
render model's bank, prepared for sampling on the device:

* floors: every texture (index 0 = the model's default floor texture, k + 1 =
  bank floor k) with its mip chain (box-filtered halvings, like
  `glGenerateMipmap`), all packed into one flat texel array with per-level
  offsets, so a trilinear lookup is eight gathers whatever the level;
* skies: every skybox (index 0 = the model's, k + 1 = bank sky k) as six cube
  faces resampled to one size (`SKY_SIZE`, about one texel per pixel at 84×84,
  which is the mip level MuJoCo's minified lookups read).

`Scene` is a frozen pytree (arrays on device, layout static), built for one
camera. `device_looks(scene, looks)` turns the host `render_model.Looks` of a
batch (what `prepare` computes from `VisualParams`, in float64) into the
`DeviceLook` pytree the renderer reads: the material colour table, floor and
sky indices, floor reflectance, headlight, the moved light's colour, and the
camera and light poses in
the form MuJoCo's camera/light modes use (`cam_pos`, `cam_quat`, `cam_pos0`,
`cam_poscom0`, `cam_mat0`, …).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from dmcr_jax.models.names import find_id
from dmcr_jax.visuals import render_model as rmod

# Geom types the ray caster intersects (mjtGeom values).
PLANE, SPHERE, CAPSULE, ELLIPSOID, CYLINDER, BOX = (
    int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_SPHERE),
    int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_ELLIPSOID),
    int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_BOX))
SUPPORTED = (PLANE, SPHERE, CAPSULE, ELLIPSOID, CYLINDER, BOX)
SKY_SIZE = 128            # cube-face size of the skies on device
_GEOM = int(mujoco.mjtObj.mjOBJ_GEOM)
_SITE = int(mujoco.mjtObj.mjOBJ_SITE)
_SPOT = int(mujoco.mjtLightType.mjLIGHT_SPOT)
_DIRECTIONAL = int(mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
_TEX2D = int(mujoco.mjtTexture.mjTEXTURE_2D)
_ROLE_RGB = int(mujoco.mjtTextureRole.mjTEXROLE_RGB)
# Variables the renderer applies (State.info keys "<field>:<name>").
VARIABLE_FIELDS = ("geom_pos", "geom_size", "geom_rgba", "site_pos", "site_size",
                   "site_rgba")


@struct.dataclass
class Scene:
  """One domain's drawable objects, lights, camera and textures (built by `build_scene`).

  K objects (geoms and sites MuJoCo draws), M material slots, L model lights.

  Attributes:
    types: static tuple of K geom types (`PLANE` … `BOX`).
    obj_ids: static tuple of K (objtype, objid) pairs (MuJoCo ids).
    body: int32 (K,) body each object is attached to.
    local_pos, local_mat: (K, 3), (K, 3, 3) the object's frame in its body frame.
    size: (K, 3) model size (`geom_size` / `site_size` layout).
    decor: bool (K,) sites (drawn, cast no shadow).
    mat_slot: int32 (K,) row of `DeviceLook.mat_rgba` colouring the object, −1
      when its own `rgba` is used.
    rgba: (K, 4) the object's own colour.
    specular, shininess, emission: (K,) material constants (shininess in
      MuJoCo's [0, 1] scale; GL's exponent is 128 × it).
    seg_body: int32 (K,) body id (for silhouettes).
    floor_obj: static index of the floor object (−1: none).
    variables: static tuple of (key, field, object index).
    cam_mode, cam_body: static camera mode (0 fixed, 1 track, 2 trackcom) and body.
    cam_looked: static, whether the look moves this camera.
    fovy: static vertical field of view (degrees).
    znear, zfar: static clip distances (metres).
    cam_pos, cam_quat, cam_pos0, cam_poscom0, cam_mat0: the model's camera values
      (used when the look does not move this camera).
    light_types, light_modes, light_bodies, light_shadow: static per-light tuples.
    light_looked: static index of the light the look moves (−1: none).
    light_ambient, light_diffuse, light_specular, light_attenuation: (L, 3).
    light_cutoff, light_exponent: (L,).
    light_pos, light_dir, light_pos0, light_poscom0, light_dir0: (L, 3) model values.
    floor_texels: uint8 (T, 3) every floor texture and mip level, packed.
    floor_offset, floor_width, floor_height: int32 (F, LEVELS) per level.
    floor_levels: int32 (F,) number of levels of each floor texture.
    floor_repeat: (F, 2) texrepeat of each floor (texuniform).
    skies: uint8 (B, 6, SKY_SIZE, SKY_SIZE, 3) cube faces (+x −x +y −y +z −z).
    domain: static domain name.
  """
  body: jax.Array
  local_pos: jax.Array
  local_mat: jax.Array
  size: jax.Array
  decor: jax.Array
  mat_slot: jax.Array
  rgba: jax.Array
  specular: jax.Array
  shininess: jax.Array
  emission: jax.Array
  seg_body: jax.Array
  cam_pos: jax.Array
  cam_quat: jax.Array
  cam_pos0: jax.Array
  cam_poscom0: jax.Array
  cam_mat0: jax.Array
  light_ambient: jax.Array
  light_diffuse: jax.Array
  light_specular: jax.Array
  light_attenuation: jax.Array
  light_cutoff: jax.Array
  light_exponent: jax.Array
  light_pos: jax.Array
  light_dir: jax.Array
  light_pos0: jax.Array
  light_poscom0: jax.Array
  light_dir0: jax.Array
  floor_texels: jax.Array
  floor_offset: jax.Array
  floor_width: jax.Array
  floor_height: jax.Array
  floor_levels: jax.Array
  floor_repeat: jax.Array
  skies: jax.Array
  types: tuple = struct.field(pytree_node=False, default=())
  obj_ids: tuple = struct.field(pytree_node=False, default=())
  floor_obj: int = struct.field(pytree_node=False, default=-1)
  variables: tuple = struct.field(pytree_node=False, default=())
  cam_mode: int = struct.field(pytree_node=False, default=0)
  cam_body: int = struct.field(pytree_node=False, default=0)
  cam_looked: bool = struct.field(pytree_node=False, default=True)
  fovy: float = struct.field(pytree_node=False, default=45.0)
  znear: float = struct.field(pytree_node=False, default=0.01)
  zfar: float = struct.field(pytree_node=False, default=50.0)
  light_types: tuple = struct.field(pytree_node=False, default=())
  light_modes: tuple = struct.field(pytree_node=False, default=())
  light_bodies: tuple = struct.field(pytree_node=False, default=())
  light_shadow: tuple = struct.field(pytree_node=False, default=())
  light_looked: int = struct.field(pytree_node=False, default=-1)
  domain: str = struct.field(pytree_node=False, default="")

  @property
  def num_objects(self) -> int:
    return len(self.types)


@struct.dataclass
class DeviceLook:
  """One env's look as the ray caster reads it (batch it with a leading axis).

  Attributes:
    mat_rgba: (M, 4) colour of every material slot of the scene.
    floor: int32 floor texture (0: the model's default, k + 1: bank floor k).
    floor_reflectance: float32.
    sky: int32 skybox (0: the model's, k + 1: bank sky k).
    headlight: (3, 3) ambient, diffuse, specular.
    cam_pos, cam_quat, cam_pos0, cam_poscom0, cam_mat0: camera 0 (MuJoCo's
      fields; `cam_mat0` is 9 numbers, row-major).
    light_pos, light_dir, light_pos0, light_poscom0, light_dir0: the moved light.
    light_diffuse, light_specular: (3,) its diffuse and specular RGB (used in
      place of the scene's `light_diffuse/specular` row of that light).
    floor_rgba: (4,) the floor material's colour, or None: the scene's (a look
      that moves the floor, `moving.look_at`).
    sky2: int32 a second skybox (as `sky`) blended in with weight `sky_mix`
      (float32), or both None: `sky` alone (a look that moves the background).
  """
  mat_rgba: jax.Array
  floor: jax.Array
  floor_reflectance: jax.Array
  sky: jax.Array
  headlight: jax.Array
  cam_pos: jax.Array
  cam_quat: jax.Array
  cam_pos0: jax.Array
  cam_poscom0: jax.Array
  cam_mat0: jax.Array
  light_pos: jax.Array
  light_dir: jax.Array
  light_pos0: jax.Array
  light_poscom0: jax.Array
  light_dir0: jax.Array
  light_diffuse: jax.Array
  light_specular: jax.Array
  floor_rgba: jax.Array | None = None
  sky2: jax.Array | None = None
  sky_mix: jax.Array | None = None

  def take(self, index) -> "DeviceLook":
    """The looks at `index` of a batched `DeviceLook`."""
    return jax.tree.map(lambda x: x[index], self)


# ---------------------------------------------------------------------------
# Textures
# ---------------------------------------------------------------------------


def _halve(img: np.ndarray) -> np.ndarray:
  """One mip level down: 2×2 box filter (odd sizes drop their last row/column,
  as `glGenerateMipmap`'s floor(size / 2) level sizes)."""
  h, w = max(1, img.shape[0] // 2), max(1, img.shape[1] // 2)
  if img.shape[0] == 1:
    return img[:, :2 * w].reshape(1, w, 2, -1).mean(2)
  if img.shape[1] == 1:
    return img[:2 * h].reshape(h, 2, 1, -1).mean(1)
  return img[:2 * h, :2 * w].reshape(h, 2, w, 2, -1).mean((1, 3))


def mip_chain(img: np.ndarray) -> list[np.ndarray]:
  """Every mip level of an (H, W, 3) uint8 texture, finest first (float32)."""
  levels = [img.astype(np.float32)]
  while levels[-1].shape[0] > 1 or levels[-1].shape[1] > 1:
    levels.append(_halve(levels[-1]))
  return levels


def _resample(img: np.ndarray, size: int) -> np.ndarray:
  """Area resampling of a square (S, S, C) image to (size, size, C)."""
  s = img.shape[0]
  img = img.astype(np.float32)
  edges = np.linspace(0, s, size + 1)
  # weights matrix (size, s): overlap of output cell i with input texel j
  lo, hi = edges[:-1, None], edges[1:, None]
  j = np.arange(s)[None, :]
  wgt = np.clip(np.minimum(hi, j + 1) - np.maximum(lo, j), 0, None)
  wgt /= wgt.sum(1, keepdims=True)
  rows = np.tensordot(wgt, img, axes=(1, 0))                 # (size, s, C)
  return np.tensordot(rows, wgt, axes=(1, 1)).transpose(0, 2, 1)


def _texture(m: mujoco.MjModel, tex: int) -> np.ndarray:
  """Texture `tex` of the model as uint8 (H, W, 3)."""
  w, h, c = int(m.tex_width[tex]), int(m.tex_height[tex]), int(m.tex_nchannel[tex])
  adr = int(m.tex_adr[tex])
  return np.asarray(m.tex_data[adr:adr + w * h * c]).reshape(h, w, c)[..., :3]


def _pack_floors(textures: list[np.ndarray]):
  """Packs mip chains of floor textures into one flat texel array."""
  chains = [mip_chain(t) for t in textures]
  nlev = max(len(c) for c in chains)
  off = np.zeros((len(chains), nlev), np.int32)
  wid = np.ones((len(chains), nlev), np.int32)
  hei = np.ones((len(chains), nlev), np.int32)
  parts, pos = [], 0
  for f, chain in enumerate(chains):
    for l in range(nlev):
      lev = chain[min(l, len(chain) - 1)]
      off[f, l], hei[f, l], wid[f, l] = pos, lev.shape[0], lev.shape[1]
      if l < len(chain):
        parts.append(np.clip(np.round(lev), 0, 255).astype(np.uint8).reshape(-1, 3))
        pos += lev.shape[0] * lev.shape[1]
      else:
        off[f, l] = off[f, len(chain) - 1]
  levels = np.array([len(c) for c in chains], np.int32)
  return np.concatenate(parts), off, wid, hei, levels


@functools.lru_cache(maxsize=8)
def _bank_textures(rm_key: tuple, rm: rmod.RenderModel):
  """Device-ready floor and sky arrays of a render model's bank (cached)."""
  m = rm.model
  floor_mat = rm.dflt["floor_matid"]
  grid = int(m.mat_texid[floor_mat][_ROLE_RGB])
  floors = [_texture(m, grid)] + [np.asarray(f) for f in rm.bank.floors]
  texels, off, wid, hei, levels = _pack_floors(floors)
  repeat = np.concatenate([m.mat_texrepeat[floor_mat][None],
                           np.repeat(m.mat_texrepeat[rm.floor_mat0][None],
                                     rm.bank.num_floors, 0)]).astype(np.float32)
  skies = []
  if rm.sky_tex >= 0:
    sky = _texture(m, rm.sky_tex)
    w = sky.shape[1]
    skies.append(sky.reshape(6, w, w, 3))
  else:
    skies.append(np.zeros((6, SKY_SIZE, SKY_SIZE, 3), np.uint8))
  skies += [np.asarray(b) for b in rm.bank.backgrounds]
  out = np.empty((len(skies), 6, SKY_SIZE, SKY_SIZE, 3), np.uint8)
  for i, sky in enumerate(skies):
    for f in range(6):
      face = sky[f]
      if face.shape[0] != SKY_SIZE:
        face = np.clip(np.round(_resample(face, SKY_SIZE)), 0, 255).astype(np.uint8)
      out[i, f] = face
  return texels, off, wid, hei, levels, repeat, out


# ---------------------------------------------------------------------------
# Scene
# ---------------------------------------------------------------------------


def _drawn_objects(m: mujoco.MjModel, cam: int) -> list[tuple[int, int]]:
  """(objtype, objid) of every geom/site MuJoCo's default render draws."""
  d = mujoco.MjData(m)
  mujoco.mj_forward(m, d)
  opt = mujoco.MjvOption()
  scn = mujoco.MjvScene(m, maxgeom=10000)
  camera = mujoco.MjvCamera()
  camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
  camera.fixedcamid = cam
  mujoco.mjv_updateScene(m, d, opt, mujoco.MjvPerturb(), camera,
                         int(mujoco.mjtCatBit.mjCAT_ALL), scn)
  out = []
  for i in range(scn.ngeom):
    g = scn.geoms[i]
    if int(g.objtype) in (_GEOM, _SITE):
      out.append((int(g.objtype), int(g.objid)))
  return out


def _quat_mat(q) -> np.ndarray:
  mat = np.zeros(9)
  mujoco.mju_quat2Mat(mat, np.asarray(q, np.float64))
  return mat.reshape(3, 3)


def build_scene(rm: rmod.RenderModel, camera: int | str = 0) -> Scene:
  """Builds a domain's `Scene` for one camera (host work, once per domain).

  Args:
    rm: the domain's `RenderModel` (its bank becomes the device texture bank).
    camera: camera id or name (camera 0 is the one looks move).

  Returns:
    The `Scene` (device arrays).

  Raises:
    NotImplementedError: a drawn object of a type the ray caster does not
      intersect, a textured object other than the floor, or a camera mode
      other than fixed / track / trackcom.
  """
  m = rmod.with_default_look(rm).model   # not the look a MuJoCo render applied last
  cam = camera if isinstance(camera, (int, np.integer)) else find_id(
      m, mujoco.mjtObj.mjOBJ_CAMERA, camera)
  if not 0 <= cam < m.ncam:
    raise ValueError(f"No camera {camera!r} in the {rm.domain} model.")
  objs = _drawn_objects(m, cam)
  mats_used = sorted({int((m.geom_matid if t == _GEOM else m.site_matid)[i])
                      for t, i in objs} - {-1, rm.dflt["floor_matid"]})
  slot_of = {mat: s for s, mat in enumerate(mats_used)}
  f32 = lambda x: np.asarray(x, np.float32)
  rows = []
  floor_obj = -1
  default_rgba = np.array([0.5, 0.5, 0.5, 1.0], np.float32)
  for k, (t, i) in enumerate(objs):
    geom = t == _GEOM
    typ = int((m.geom_type if geom else m.site_type)[i])
    if typ not in SUPPORTED:
      raise NotImplementedError(f"{rm.domain}: drawn object {k} has geom type {typ}.")
    matid = int((m.geom_matid if geom else m.site_matid)[i])
    rgba = f32((m.geom_rgba if geom else m.site_rgba)[i])
    is_floor = geom and i == rm.floor_geom
    if is_floor:
      floor_obj = k
    elif matid >= 0 and m.mat_texid[matid][_ROLE_RGB] >= 0:
      raise NotImplementedError(f"{rm.domain}: textured object {k} other than the floor.")
    # MuJoCo colours an object by its material when its own rgba is the default.
    use_mat = matid >= 0 and np.array_equal(rgba, default_rgba)
    rows.append(dict(
        type=typ, body=int((m.geom_bodyid if geom else m.site_bodyid)[i]),
        pos=(m.geom_pos if geom else m.site_pos)[i],
        mat=_quat_mat((m.geom_quat if geom else m.site_quat)[i]),
        size=(m.geom_size if geom else m.site_size)[i], decor=not geom,
        slot=slot_of[matid] if use_mat and not is_floor else -1,
        rgba=m.mat_rgba[matid] if (use_mat and is_floor) else rgba,
        specular=m.mat_specular[matid] if matid >= 0 else 0.5,
        shininess=m.mat_shininess[matid] if matid >= 0 else 0.5,
        emission=m.mat_emission[matid] if matid >= 0 else 0.0))
  variables = []
  for key in rm_variables(rm):
    field, name = key.split(":", 1)
    kind = _GEOM if field.startswith("geom") else _SITE
    i = find_id(m, kind, name)
    if (kind, i) in objs:
      variables.append((key, field, objs.index((kind, i))))
  # lights
  L = m.nlight
  for l in range(L):
    if int(m.light_type[l]) not in (_SPOT, _DIRECTIONAL):
      raise NotImplementedError(f"{rm.domain}: light {l} of type {m.light_type[l]}.")
    if int(m.light_mode[l]) not in (0, 1, 2):
      raise NotImplementedError(f"{rm.domain}: light {l} in mode {m.light_mode[l]}.")
  if int(m.cam_mode[cam]) not in (0, 1, 2):
    raise NotImplementedError(f"{rm.domain}: camera {cam} in mode {m.cam_mode[cam]}.")
  texels, off, wid, hei, levels, repeat, skies = _bank_textures(
      (rm.domain, rm.bank.key), rm)
  col = lambda name: np.stack([np.asarray(r[name], np.float64) for r in rows])
  extent = float(m.stat.extent)
  j = jnp.asarray
  return Scene(
      body=j(col("body").astype(np.int32)), local_pos=j(f32(col("pos"))),
      local_mat=j(f32(col("mat"))), size=j(f32(col("size"))),
      decor=j(col("decor").astype(bool)), mat_slot=j(col("slot").astype(np.int32)),
      rgba=j(f32(col("rgba"))), specular=j(f32(col("specular"))),
      shininess=j(f32(col("shininess"))), emission=j(f32(col("emission"))),
      seg_body=j(col("body").astype(np.int32)),
      cam_pos=j(f32(m.cam_pos[cam])), cam_quat=j(f32(m.cam_quat[cam])),
      cam_pos0=j(f32(m.cam_pos0[cam])), cam_poscom0=j(f32(m.cam_poscom0[cam])),
      cam_mat0=j(f32(m.cam_mat0[cam])),
      light_ambient=j(f32(m.light_ambient)), light_diffuse=j(f32(m.light_diffuse)),
      light_specular=j(f32(m.light_specular)),
      light_attenuation=j(f32(m.light_attenuation)),
      light_cutoff=j(f32(m.light_cutoff)), light_exponent=j(f32(m.light_exponent)),
      light_pos=j(f32(m.light_pos)), light_dir=j(f32(m.light_dir)),
      light_pos0=j(f32(m.light_pos0)), light_poscom0=j(f32(m.light_poscom0)),
      light_dir0=j(f32(m.light_dir0)),
      floor_texels=j(texels), floor_offset=j(off), floor_width=j(wid),
      floor_height=j(hei), floor_levels=j(levels), floor_repeat=j(repeat),
      skies=j(skies),
      types=tuple(r["type"] for r in rows), obj_ids=tuple(objs), floor_obj=floor_obj,
      variables=tuple(variables), cam_mode=int(m.cam_mode[cam]),
      cam_body=int(m.cam_bodyid[cam]), cam_looked=bool(cam == rm.cam_id),
      fovy=float(m.cam_fovy[cam]), znear=float(m.vis.map.znear) * extent,
      zfar=float(m.vis.map.zfar) * extent,
      light_types=tuple(int(t) for t in m.light_type),
      light_modes=tuple(int(t) for t in m.light_mode),
      light_bodies=tuple(int(b) for b in m.light_bodyid),
      light_shadow=tuple(bool(s) for s in m.light_castshadow),
      light_looked=int(rm.light_id), domain=rm.domain)


def rm_variables(rm: rmod.RenderModel) -> tuple[str, ...]:
  """The model-variable keys the domain's tasks use (every task of the domain)."""
  from dmcr_jax import models
  keys = []
  for name in models.ALL_TASKS:
    if models.split_name(name)[0] == rm.domain:
      for field, obj in models.spec(name).model_variables:
        if field in VARIABLE_FIELDS and f"{field}:{obj}" not in keys:
          keys.append(f"{field}:{obj}")
  return tuple(keys)


def material_slots(scene: Scene, rm: rmod.RenderModel) -> np.ndarray:
  """Material id of every slot of `DeviceLook.mat_rgba` (in slot order)."""
  m = rm.model
  geom_matid = m.geom_matid.copy()   # the floor's as built, not an applied look's
  geom_matid[rm.floor_geom] = rm.dflt["floor_matid"]
  mats = sorted({int((geom_matid if t == _GEOM else m.site_matid)[i])
                 for t, i in scene.obj_ids} - {-1, rm.dflt["floor_matid"]})
  return np.asarray(mats, np.int64)


def device_looks(scene: Scene, rm: rmod.RenderModel, looks: rmod.Looks,
                 moving: tuple[str, ...] = ()) -> DeviceLook:
  """A batch of host `Looks` (from `render_model.prepare`) as a `DeviceLook`.

  Args:
    scene: the domain's scene.
    rm: its render model.
    looks: `Looks` with batch size N.
    moving: the moving factors (`moving.check_moving`): "floor" fills
      `floor_rgba`, "background" `sky2` and `sky_mix`.

  Returns:
    `DeviceLook` with leading axis N (float32 / int32 device arrays).
  """
  n = len(looks)
  mats = material_slots(scene, rm)
  table = np.broadcast_to(rm.dflt["mat_rgba"][mats], (n, len(mats), 4)).copy()
  for group, rgba in ((rm.body_mats, looks.body_rgba),
                      (rm.effector_mats, looks.effector_rgba),
                      (rm.target_mats, looks.target_rgba)):
    for s, mat in enumerate(mats):
      if mat in group:
        table[:, s] = rgba
  floor = np.where(looks.floor_matid == rm.dflt["floor_matid"], 0,
                   looks.floor_matid - rm.floor_mat0 + 1)
  sky_id = lambda tex: np.where(tex == rm.sky_tex, 0, tex - rm.bg_tex0 + 1).astype(np.int32)
  sky = sky_id(looks.skybox_tex)
  f32 = lambda x: jnp.asarray(np.asarray(x, np.float32))
  extra = {}
  if "floor" in moving:
    extra["floor_rgba"] = f32(looks.floor_rgba)
  if "background" in moving:
    extra.update(sky2=jnp.asarray(sky_id(looks.skybox_tex2)), sky_mix=f32(looks.sky_mix))
  return DeviceLook(
      mat_rgba=f32(table), floor=jnp.asarray(floor.astype(np.int32)),
      floor_reflectance=f32(looks.floor_reflectance), sky=jnp.asarray(sky.astype(np.int32)),
      headlight=f32(looks.headlight), cam_pos=f32(looks.cam_pos),
      cam_quat=f32(looks.cam_quat), cam_pos0=f32(looks.cam_pos0),
      cam_poscom0=f32(looks.cam_poscom0), cam_mat0=f32(looks.cam_mat0),
      light_pos=f32(looks.light_pos), light_dir=f32(looks.light_dir),
      light_pos0=f32(looks.light_pos0), light_poscom0=f32(looks.light_poscom0),
      light_dir0=f32(looks.light_dir0), light_diffuse=f32(looks.light_diffuse),
      light_specular=f32(looks.light_specular), **extra)


@struct.dataclass
class LookMaker:
  """What turns visual seeds into `DeviceLook`s on the device (build with `look_maker`).

  `maker(seeds)` is `device_looks(scene, rm, prepare(rm, rm.sample(seeds, vary)))`
  computed in float32 inside `jit` (`params.sample_masked`, then `prepare`'s
  selections, Euler offsets, normalisations and frame offsets with `jax.numpy`):
  a look is a function of its seed alone, costs no host work and no table, so a
  range of any size can be drawn from on the device. Integer fields equal the
  host's; float fields agree with the host's float64 path to float32 rounding.

  Attributes:
    mask: bool (7,) the factors the seeds change (`params.factor_mask`).
    consts: the render model's defaults and frames as float32 / int32 arrays.
    domain, num_floors, num_backgrounds: static; the domain and its bank sizes.
    light_moves: static; whether the domain's look moves a light.
    light_coloured: static; whether it also changes that light's colour.
    moving, intensity: static; the factors that move within an episode and how far
      (`moving.look_at`; () = static looks).
  """
  mask: jax.Array
  consts: dict
  domain: str = struct.field(pytree_node=False, default="")
  num_floors: int = struct.field(pytree_node=False, default=1)
  num_backgrounds: int = struct.field(pytree_node=False, default=1)
  light_moves: bool = struct.field(pytree_node=False, default=False)
  light_coloured: bool = struct.field(pytree_node=False, default=False)
  moving: tuple = struct.field(pytree_node=False, default=())
  intensity: float = struct.field(pytree_node=False, default=0.0)

  @property
  def moves(self) -> bool:
    """Whether looks change within an episode (static)."""
    return bool(self.moving) and self.intensity > 0

  def params(self, seeds: jax.Array, step: jax.Array | None = None):
    """The `VisualParams` of int32 (N,) seeds at episode steps `step` (int (N,);
    None or static looks: the static look), as the host's `look_at` gives them."""
    from dmcr_jax.visuals.moving import look_at
    from dmcr_jax.visuals.params import sample_masked
    p = sample_masked(self.domain, jnp.asarray(seeds, jnp.int32), self.mask,
                      self.num_floors, self.num_backgrounds)
    if not self.moves or step is None:
      return p
    return look_at(p, step, self.moving, self.intensity,
                   num_backgrounds=self.num_backgrounds)

  def __call__(self, seeds: jax.Array, step: jax.Array | None = None) -> DeviceLook:
    """The `DeviceLook`s of int32 (N,) visual seeds (jittable; leading axis N) at
    episode steps `step` (int (N,); used when the looks move, None: step 0)."""
    if self.moves and step is None:
      step = jnp.zeros(jnp.shape(seeds), jnp.int32)
    return self.device_look(self.params(seeds, step))

  def device_look(self, p) -> DeviceLook:
    """The `DeviceLook`s of N envs' `VisualParams` (from `params`, or moved by
    `moving.look_at_each`; jittable): the floor's colour where `p` has a
    `floor_delta`, a second sky where it has a `background2_id`."""
    from dmcr_jax.visuals.params import FACTOR_INDEX
    c, n = self.consts, p.seed.shape[0]
    on = lambda f: p.varied[:, FACTOR_INDEX[f]]
    sel = lambda f, x, d: jnp.where(on(f).reshape((n,) + (1,) * (x.ndim - 1)), x, d)
    colour = {1: sel("body", p.body_rgba, c["body_rgba"]),
              2: sel("body", p.effector_rgba, c["effector_rgba"]),
              3: sel("target", p.target_rgba, c["target_rgba"])}
    mat_rgba = jnp.broadcast_to(c["mat_rgba"], (n,) + c["mat_rgba"].shape)
    for group, rgba in colour.items():
      mat_rgba = jnp.where((c["slot_group"] == group)[None, :, None], rgba[:, None], mat_rgba)
    floor = jnp.where(on("floor") & (p.floor_id >= 0), p.floor_id + 1, 0)
    sky = jnp.where(on("background") & (p.background_id >= 0), p.background_id + 1, 0)
    refl = jnp.where(on("reflectance"), p.floor_reflectance, c["floor_reflectance"][floor])
    head = jnp.stack([p.headlight_ambient, p.headlight_diffuse, p.headlight_specular], 1)

    # Camera: Euler offsets (intrinsic x-y-z) on top of the default orientation.
    q = jnp.broadcast_to(c["cam_quat"], (n, 4))
    half = jnp.deg2rad(p.cam_rot) / 2
    for axis in range(3):
      turn = jnp.zeros((n, 4)).at[:, 0].set(jnp.cos(half[:, axis]))
      q = rmod._qmul(q, turn.at[:, 1 + axis].set(jnp.sin(half[:, axis])), jnp)
    q = q / jnp.sqrt(jnp.sum(q * q, axis=-1, keepdims=True))
    xpos, xquat, com = c["cam_frame"]
    xquat = jnp.broadcast_to(xquat, (n, 4))
    cxpos = xpos + rmod._rotate(xquat, p.cam_pos, jnp)
    cmat = rmod._qmat(rmod._qmul(xquat, q, jnp), jnp)
    cam = lambda x, d: sel("camera", x, d)

    # Light: position and (normalised) direction, and their tracking offsets.
    norm = jnp.sqrt(jnp.sum(p.light_dir * p.light_dir, axis=-1, keepdims=True))
    ldir = jnp.where(norm > 1e-9, p.light_dir / jnp.where(norm > 1e-9, norm, 1.0),
                     c["light_dir"])
    lxpos_b, lquat, lcom = c["light_frame"]
    lquat = jnp.broadcast_to(lquat, (n, 4))
    lxpos = lxpos_b + rmod._rotate(lquat, p.light_pos, jnp)
    lxdir = rmod._rotate(lquat, ldir, jnp)
    lm = (on("light") & self.light_moves)[:, None]
    light = lambda x, d: jnp.where(lm, x, d)
    lc = (on("light") & self.light_coloured)[:, None]
    extra = {}
    if p.floor_delta is not None:
      base = c["floor_rgba"][floor]
      extra["floor_rgba"] = base.at[:, :3].set(
          jnp.clip(base[:, :3] + p.floor_delta, 0.0, 1.0))
    if p.background2_id is not None:
      extra.update(sky2=(p.background2_id + 1).astype(jnp.int32), sky_mix=p.background_mix)
    return DeviceLook(
        mat_rgba=mat_rgba, floor=floor.astype(jnp.int32), floor_reflectance=refl,
        sky=sky.astype(jnp.int32), headlight=sel("light", head, c["headlight"]),
        cam_pos=cam(p.cam_pos, c["cam_pos"]), cam_quat=cam(q, c["cam_quat"]),
        cam_pos0=cam(cxpos - xpos, c["cam_pos0"]),
        cam_poscom0=cam(cxpos - com, c["cam_poscom0"]), cam_mat0=cam(cmat, c["cam_mat0"]),
        light_pos=light(p.light_pos, c["light_pos"]), light_dir=light(ldir, c["light_dir"]),
        light_pos0=light(lxpos - lxpos_b, c["light_pos0"]),
        light_poscom0=light(lxpos - lcom, c["light_poscom0"]),
        light_dir0=light(lxdir, c["light_dir0"]),
        light_diffuse=jnp.where(lc, p.light_diffuse, c["light_diffuse"]),
        light_specular=jnp.where(lc, p.light_specular, c["light_specular"]), **extra)


def look_maker(scene: Scene, rm: rmod.RenderModel, vary, moving: tuple[str, ...] = (),
               intensity: float = 0.0) -> LookMaker:
  """The `LookMaker` of a domain's scene and render model for the factors `vary`.

  Args:
    scene: the domain's scene.
    rm: its render model.
    vary: the factors the visual seeds change (as for `params.sample`).
    moving, intensity: the factors that move within an episode and how far
      (checked, as `moving.check_moving` returns them).
  """
  from dmcr_jax.visuals import ranges as R
  from dmcr_jax.visuals.params import factor_mask
  d = rm.dflt
  mats = material_slots(scene, rm)
  group = np.zeros(len(mats), np.int32)       # later groups win, as in `device_looks`
  for code, members in ((1, rm.body_mats), (2, rm.effector_mats), (3, rm.target_mats)):
    group[np.isin(mats, members)] = code
  floors = np.concatenate([[d["floor_matid"]], rm.floor_mat0 + np.arange(rm.bank.num_floors)])
  f32 = lambda x: jnp.asarray(np.asarray(x, np.float32))
  consts = {k: f32(d[k]) for k in ("headlight", "cam_pos", "cam_quat", "cam_pos0",
                                   "cam_poscom0", "cam_mat0", "light_pos", "light_dir",
                                   "light_pos0", "light_poscom0", "light_dir0",
                                   "light_diffuse", "light_specular")}
  consts.update(
      mat_rgba=f32(d["mat_rgba"][mats]), slot_group=jnp.asarray(group),
      body_rgba=f32(d["mat_rgba"][rm.body_mats[0]]),
      effector_rgba=f32(d["mat_rgba"][rm.effector_mats[0]]),
      target_rgba=f32(d["mat_rgba"][rm.target_mats[0]]),
      floor_reflectance=f32(d["mat_reflectance"][floors]),
      floor_rgba=f32(d["mat_rgba"][floors]),
      cam_frame=tuple(f32(x) for x in rm.cam_frame),
      light_frame=tuple(f32(x) for x in rm.light_frame))
  return LookMaker(mask=jnp.asarray(factor_mask(rm.domain, vary)), consts=consts,
                   domain=rm.domain, num_floors=int(rm.bank.num_floors),
                   num_backgrounds=int(rm.bank.num_backgrounds),
                   light_moves=R.DOMAIN_RANGES[rm.domain].light_pos is not None,
                   light_coloured=R.DOMAIN_RANGES[rm.domain].light_diffuse is not None,
                   moving=tuple(moving), intensity=float(intensity))


@struct.dataclass
class BodyPoses:
  """What the renderer reads from a physics state: body frames and subtree centres.

  Attributes:
    xpos: (nbody, 3) body positions.
    xmat: (nbody, 3, 3) body orientations.
    subtree_com: (nbody, 3) subtree centres of mass (tracking cameras/lights).
  """
  xpos: jax.Array
  xmat: jax.Array
  subtree_com: jax.Array


def poses(data) -> BodyPoses:
  """`BodyPoses` of an MJX `Data`, a `mujoco.MjData` or anything with `xpos`,
  `xmat` and `subtree_com` (positions must be current: after forward/kinematics)."""
  xpos = jnp.asarray(np.asarray(data.xpos) if isinstance(data, mujoco.MjData)
                     else data.xpos, jnp.float32)
  xmat = jnp.asarray(np.asarray(data.xmat) if isinstance(data, mujoco.MjData)
                     else data.xmat, jnp.float32)
  com = jnp.asarray(np.asarray(data.subtree_com) if isinstance(data, mujoco.MjData)
                    else data.subtree_com, jnp.float32)
  return BodyPoses(xpos=xpos, xmat=xmat.reshape(xmat.shape[:-1] + (3, 3))
                   if xmat.shape[-1] == 9 else xmat, subtree_com=com)

