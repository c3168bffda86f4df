"""The render model (dm_control's model + the texture bank) and applying one look.

`build_render_model(domain)` compiles dm_control's own suite MJCF for a domain
with MuJoCo's `MjSpec` and appends visual-only assets: one 2-D texture and one
material per floor of the bank (tiling like dm_control's grid) and one cube
texture per skybox of the bank. Nothing else changes: no body, joint, geom or
option is added, so the qpos/qvel layout and the dynamics are dm_control's
(tests step both models and compare bit for bit), and with seed 0 the render
model draws exactly dm_control's pixels (the bank is there but unused).

Switching looks is cheap: a GL context holds each texture once, and a look only
selects among them. (`mujoco.Renderer`, as in `FrameRenderer`, uploads the whole
bank when its context is made; the render pool's workers upload a bank texture
the first time a look draws it: `look_textures`, `TiledRenderer.upload`.)

* floor: the floor geom's `geom_matid` selects one of the bank's materials
  (materials keep their texture and tiling in the GL context);
* colours, reflectance, headlight, light and camera: plain writes into
  `mat_rgba`, `mat_reflectance`, `vis.headlight`, `light_pos/dir(+0)`,
  `light_diffuse/specular` and
  `cam_pos/quat` and their derived `cam_pos0/cam_poscom0/cam_mat0` (which
  MuJoCo's tracking cameras and lights read; we compute them as `mj_setConst`
  would, from the body poses at qpos0);
* background: MuJoCo draws the first texture of type skybox in the GL
  context's texture table (`mjrContext.textureType`; MuJoCo 3.17, render_gl3.c)
  and all cube and skybox textures are uploaded as GL cube maps. So every
  skybox of the bank is uploaded once as a cube texture, and selecting one is
  two integer writes into the context's `textureType` (the default skybox
  becomes "cube", the chosen one "skybox"). We also write the chosen texture
  into the context's skybox material slot, which newer MuJoCo versions read
  instead. This needs the `mujoco.MjrContext` that renders, hence `context=`.
  A visual-only backdrop geom was the alternative; it would be lit, shadowed
  and reflected like any geom and cost a draw per frame, where the skybox is
  unlit, at infinity and free.

`prepare(render_model, params)` turns a batch of `VisualParams` into host
arrays (float64 NumPy, nonlinear parts such as Euler → quaternion done here,
deterministically); `apply(render_model, looks, i, context)` writes env i's
look into the model; `FrameRenderer` renders one frame with `mujoco.Renderer`,
the reference that batched render pools must match.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any, Mapping

import mujoco
import numpy as np

from dmcr_jax.models.names import (FIELD_OBJECTS, find_id, obj_id, suite_compile_quiet,
                                    suite_model, suite_xml)
from dmcr_jax.visuals import ranges as R
from dmcr_jax.visuals.factors import FACTOR_INDEX, check_domain
from dmcr_jax.visuals.textures import TextureBank, load_bank

# `params` (JAX and flax) is imported only where params are sampled: render workers
# only `apply` prepared `Looks`, and start without importing JAX.
if TYPE_CHECKING:
  from dmcr_jax.visuals.params import VisualParams

_O = mujoco.mjtObj
_SKYBOX = int(mujoco.mjtTexture.mjTEXTURE_SKYBOX)
_CUBE = int(mujoco.mjtTexture.mjTEXTURE_CUBE)
_NTEXROLE = int(mujoco.mjtTextureRole.mjNTEXROLE)
_ROLE_RGB = int(mujoco.mjtTextureRole.mjTEXROLE_RGB)
MAX_TEXTURES = 1000      # mjMAXTEXTURE
MAX_MATERIALS = 997      # mjMAXMATERIAL − 3 (one slot is the skybox's)


@dataclasses.dataclass(eq=False)
class RenderModel:
  """A domain's render model and the indices `apply` writes to.

  Attributes:
    domain: the DMCR domain.
    model: the `mujoco.MjModel` (dm_control's model + bank textures/materials).
      `apply` mutates it; give each renderer (thread/process) its own copy
      (`copy.copy(render_model)` copies the MjModel too).
    bank: the `TextureBank` it holds.
    cam_id, light_id, floor_geom: ids of camera 0, the light and the floor geom.
    floor_mat0: material id of bank floor 0 (floor k is floor_mat0 + k).
    bg_tex0: texture id of bank skybox 0 (skybox k is bg_tex0 + k).
    sky_tex: texture id of dm_control's skybox.
  """
  domain: str
  model: mujoco.MjModel
  bank: TextureBank
  cam_id: int
  light_id: int
  floor_geom: int
  floor_mat0: int
  bg_tex0: int
  sky_tex: int
  body_mats: np.ndarray
  effector_mats: np.ndarray
  target_mats: np.ndarray
  dflt: dict[str, np.ndarray]          # exact model defaults (float64/float32)
  cam_frame: tuple[np.ndarray, np.ndarray, np.ndarray]    # xpos, xquat, com at qpos0
  light_frame: tuple[np.ndarray, np.ndarray, np.ndarray]

  def __copy__(self) -> "RenderModel":
    out = dataclasses.replace(self)
    out.model = _copy_model(self.model)
    return out

  @property
  def bank_textures(self) -> range:
    """Texture ids of the bank (its floors, then its skies), after dm_control's own."""
    return range(self.bg_tex0 - self.bank.num_floors, self.bg_tex0 + self.bank.num_backgrounds)

  def sample(self, seeds, vary="all") -> VisualParams:
    """`params.sample` for this domain with this model's bank sizes."""
    from dmcr_jax.visuals.params import sample
    return sample(self.domain, seeds, vary, num_floors=self.bank.num_floors,
                  num_backgrounds=self.bank.num_backgrounds)


def with_default_look(rm: RenderModel) -> RenderModel:
  """A copy of `rm` whose model shows dm_control's look, whatever look `apply`
  wrote into `rm.model` last: every field `apply` writes is set back to `rm.dflt`
  (the skybox lives in a GL context, not in the model)."""
  out = rm.__copy__()
  m, d, c, l = out.model, rm.dflt, rm.cam_id, rm.light_id
  m.mat_rgba[:] = d["mat_rgba"]
  m.mat_reflectance[:] = d["mat_reflectance"]
  m.geom_matid[rm.floor_geom] = d["floor_matid"]
  hl = m.vis.headlight
  hl.ambient[:], hl.diffuse[:], hl.specular[:] = d["headlight"]
  for name in ("cam_pos", "cam_quat", "cam_pos0", "cam_poscom0", "cam_mat0"):
    getattr(m, name)[c] = d[name]
  for name in ("light_pos", "light_dir", "light_pos0", "light_poscom0", "light_dir0",
               "light_diffuse", "light_specular"):
    getattr(m, name)[l] = d[name]
  return out


def _copy_model(m: mujoco.MjModel) -> mujoco.MjModel:
  import copy
  return copy.copy(m)


def _compile(domain: str, bank: TextureBank) -> mujoco.MjModel:
  r = R.DOMAIN_RANGES[domain]
  base = suite_model(domain)
  n_tex = base.ntex + bank.num_floors + bank.num_backgrounds
  n_mat = base.nmat + bank.num_floors
  if n_tex > MAX_TEXTURES or n_mat > MAX_MATERIALS:
    raise ValueError(
        f"Bank too large for MuJoCo's renderer: {n_tex} textures (max "
        f"{MAX_TEXTURES}) and {n_mat} materials (max {MAX_MATERIALS}).")
  xml, assets = suite_xml(domain)
  spec = mujoco.MjSpec.from_string(xml, include=assets)
  floor_mat = base.geom_matid[obj_id(base, _O.mjOBJ_GEOM, r.floor)]
  rep = 2.0 / r.floor_tile          # texuniform: one repeat per 2/texrepeat metres
  S = bank.floors.shape[1]
  W = bank.backgrounds.shape[2]
  flat = dict(builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT, rgb1=[0, 0, 0], rgb2=[0, 0, 0],
              colorspace=mujoco.mjtColorSpace.mjCOLORSPACE_LINEAR, nchannel=3)
  for k in range(bank.num_floors):
    spec.add_texture(name=f"dmcr_floor_{k}", type=mujoco.mjtTexture.mjTEXTURE_2D,
                     width=S, height=S, **flat)
    mat = spec.add_material(name=f"dmcr_floor_{k}")
    mat.textures[_ROLE_RGB] = f"dmcr_floor_{k}"
    mat.texrepeat = [rep, rep]
    mat.texuniform = True
    mat.rgba = [1, 1, 1, 1]
    mat.reflectance = float(base.mat_reflectance[floor_mat])
    mat.specular = float(base.mat_specular[floor_mat])
    mat.shininess = float(base.mat_shininess[floor_mat])
    mat.emission = float(base.mat_emission[floor_mat])
  for k in range(bank.num_backgrounds):
    spec.add_texture(name=f"dmcr_sky_{k}", type=mujoco.mjtTexture.mjTEXTURE_CUBE,
                     width=W, height=6 * W, **flat)
  with suite_compile_quiet():
    m = spec.compile()
  # Fill the texture data in one pass per texture (faster than passing bytes).
  t0 = base.ntex
  for k in range(bank.num_floors):
    adr = m.tex_adr[t0 + k]
    m.tex_data[adr:adr + S * S * 3] = bank.floors[k].reshape(-1)
  t0 += bank.num_floors
  for k in range(bank.num_backgrounds):
    adr = m.tex_adr[t0 + k]
    m.tex_data[adr:adr + 6 * W * W * 3] = bank.backgrounds[k].reshape(-1)
  return m


def _check_same_physics(domain: str, m: mujoco.MjModel) -> None:
  base = suite_model(domain)
  for f in ("nq", "nv", "nu", "na", "nbody", "njnt", "ngeom", "nsite", "ncam",
            "nlight", "ntendon", "nsensor", "neq"):
    if getattr(base, f) != getattr(m, f):
      raise AssertionError(f"render model differs from dm_control's in {f}")
  for f in ("jnt_qposadr", "jnt_dofadr", "jnt_type", "qpos0", "body_mass",
            "geom_size", "geom_pos", "geom_contype", "geom_conaffinity",
            "geom_matid", "cam_pos", "cam_quat", "cam_poscom0", "cam_mat0",
            "light_pos", "light_dir", "light_poscom0"):
    if not np.array_equal(getattr(base, f), getattr(m, f)):
      raise AssertionError(f"render model differs from dm_control's in {f}")


def _frame_at_qpos0(m: mujoco.MjModel, body: int, target: int):
  d = mujoco.MjData(m)
  mujoco.mj_kinematics(m, d)
  mujoco.mj_comPos(m, d)
  com_body = target if target >= 0 else body
  return (d.xpos[body].copy(), d.xquat[body].copy(), d.subtree_com[com_body].copy())


_MODELS: dict[tuple[str, str], RenderModel] = {}


def build_render_model(domain: str, bank: TextureBank | None = None) -> RenderModel:
  """Builds (once per process and bank, cached) the render model of a domain.

  Args:
    domain: a DMCR domain (or task name such as "walker-walk").
    bank: the texture bank; default `textures.load_bank()` (the procedural
      bank, built and cached on disk the first time).

  Returns:
    The cached `RenderModel`. `apply` mutates its `model`; use `copy.copy` for
    an independent one.
  """
  domain = check_domain(domain)
  bank = load_bank() if bank is None else bank
  key = (domain, bank.key)
  if key in _MODELS:
    return _MODELS[key]
  r = R.DOMAIN_RANGES[domain]
  base = suite_model(domain)
  m = _compile(domain, bank)
  _check_same_physics(domain, m)
  cam = obj_id(m, _O.mjOBJ_CAMERA, r.camera)
  light = obj_id(m, _O.mjOBJ_LIGHT, r.light)
  floor = obj_id(m, _O.mjOBJ_GEOM, r.floor)
  skies = [i for i in range(base.ntex) if base.tex_type[i] == _SKYBOX]
  mats = lambda names: np.array([obj_id(m, _O.mjOBJ_MATERIAL, n) for n in names])
  dflt = {
      "mat_rgba": m.mat_rgba.copy(), "mat_reflectance": m.mat_reflectance.copy(),
      "floor_matid": int(m.geom_matid[floor]),
      "headlight": np.stack([np.array(m.vis.headlight.ambient),
                             np.array(m.vis.headlight.diffuse),
                             np.array(m.vis.headlight.specular)]).astype(np.float32),
      "cam_pos": m.cam_pos[cam].copy(), "cam_quat": m.cam_quat[cam].copy(),
      "cam_pos0": m.cam_pos0[cam].copy(), "cam_poscom0": m.cam_poscom0[cam].copy(),
      "cam_mat0": m.cam_mat0[cam].copy(),
      "light_pos": m.light_pos[light].copy(), "light_dir": m.light_dir[light].copy(),
      "light_pos0": m.light_pos0[light].copy(),
      "light_poscom0": m.light_poscom0[light].copy(),
      "light_dir0": m.light_dir0[light].copy(),
      "light_diffuse": m.light_diffuse[light].copy(),
      "light_specular": m.light_specular[light].copy(),
  }
  rm = RenderModel(
      domain=domain, model=m, bank=bank, cam_id=cam, light_id=light,
      floor_geom=floor, floor_mat0=base.nmat, bg_tex0=base.ntex + bank.num_floors,
      sky_tex=skies[0] if skies else -1,
      body_mats=mats(r.body), effector_mats=mats(r.effector), target_mats=mats(r.target),
      dflt=dflt,
      cam_frame=_frame_at_qpos0(m, int(m.cam_bodyid[cam]), int(m.cam_targetbodyid[cam])),
      light_frame=_frame_at_qpos0(m, int(m.light_bodyid[light]),
                                  int(m.light_targetbodyid[light])))
  _MODELS[key] = rm
  return rm


# ---------------------------------------------------------------------------
# Host-side looks (float64) and applying one env's look
# ---------------------------------------------------------------------------


def _qmul(a: np.ndarray, b: np.ndarray, xp=np) -> np.ndarray:
  """Quaternion product (w, x, y, z) over leading axes (plain + − ×, exact order);
  `xp`: the array module (NumPy here, `jax.numpy` for looks made on the device)."""
  aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
  bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
  return xp.stack([aw * bw - ax * bx - ay * by - az * bz,
                   aw * bx + ax * bw + ay * bz - az * by,
                   aw * by - ax * bz + ay * bw + az * bx,
                   aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def _qmat(q: np.ndarray, xp=np) -> np.ndarray:
  """Unit quaternion → row-major 3×3 rotation matrix (flattened to 9)."""
  w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
  return xp.stack([
      w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y),
      2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x),
      2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
      axis=-1)


def _rotate(q: np.ndarray, v: np.ndarray, xp=np) -> np.ndarray:
  """`v` rotated by the unit quaternion `q` (over leading axes)."""
  mat = _qmat(q, xp).reshape(q.shape[:-1] + (3, 3))
  return (mat[..., 0] * v[..., :1] + mat[..., 1] * v[..., 1:2] + mat[..., 2] * v[..., 2:3])


def _axis_quat(deg: np.ndarray, axis: int) -> np.ndarray:
  """Quaternions of rotations by `deg` degrees about x/y/z (libm sin/cos)."""
  out = np.zeros(deg.shape + (4,))
  flat_deg = deg.reshape(-1)
  half = [math.radians(float(a)) / 2 for a in flat_deg]
  out.reshape(-1, 4)[:, 0] = [math.cos(h) for h in half]
  out.reshape(-1, 4)[:, 1 + axis] = [math.sin(h) for h in half]
  return out


@dataclasses.dataclass
class Looks:
  """Host arrays of a batch of looks, ready to write into a render model.

  Every field has a leading batch axis N. Values for factors that are not
  varied are the model's exact defaults.
  """
  body_rgba: np.ndarray         # float32 (N, 4)
  effector_rgba: np.ndarray     # float32 (N, 4)
  target_rgba: np.ndarray       # float32 (N, 4)
  floor_matid: np.ndarray       # int (N,)
  floor_reflectance: np.ndarray  # float32 (N,)
  headlight: np.ndarray         # float32 (N, 3, 3): ambient, diffuse, specular
  cam_pos: np.ndarray           # float64 (N, 3)
  cam_quat: np.ndarray          # float64 (N, 4)
  cam_pos0: np.ndarray          # float64 (N, 3)
  cam_poscom0: np.ndarray       # float64 (N, 3)
  cam_mat0: np.ndarray          # float64 (N, 9)
  light_pos: np.ndarray         # float64 (N, 3)
  light_dir: np.ndarray         # float64 (N, 3)
  light_pos0: np.ndarray        # float64 (N, 3)
  light_poscom0: np.ndarray     # float64 (N, 3)
  light_dir0: np.ndarray        # float64 (N, 3)
  light_diffuse: np.ndarray     # float32 (N, 3): the light's diffuse RGB
  light_specular: np.ndarray    # float32 (N, 3): the light's specular RGB
  skybox_tex: np.ndarray        # int (N,): texture id to draw as the skybox
  floor_rgba: np.ndarray        # float32 (N, 4): colour of the floor's material
  skybox_tex2: np.ndarray       # int (N,): the skybox blended in with weight sky_mix
  sky_mix: np.ndarray           # float32 (N,): that weight (0: skybox_tex alone)

  def __len__(self) -> int:
    return int(self.floor_matid.shape[0])


def prepare(rm: RenderModel, params: VisualParams) -> Looks:
  """Converts a batch of `VisualParams` into host arrays for `apply`.

  Deterministic: float64 NumPy with + − × ÷ √ and libm sin/cos (for Euler
  offsets); factors that are not varied get the model's exact default values.

  Args:
    rm: the domain's `RenderModel`.
    params: `VisualParams` of that domain (any batch size).

  Returns:
    `Looks` with the same batch size.

  Raises:
    ValueError: if the params belong to another domain or index textures
      outside the render model's bank.
  """
  if params.domain and params.domain != rm.domain:
    raise ValueError(f"VisualParams of domain {params.domain!r} cannot be applied "
                     f"to the {rm.domain!r} render model.")
  P = {f.name: np.asarray(getattr(params, f.name)) for f in dataclasses.fields(params)
       if f.name != "domain" and getattr(params, f.name) is not None}
  n = P["seed"].shape[0]
  varied = P["varied"].astype(bool)
  on = lambda f: varied[:, FACTOR_INDEX[f]]
  d = rm.dflt
  fid, bid = P["floor_id"].astype(np.int64), P["background_id"].astype(np.int64)
  if (fid >= rm.bank.num_floors).any() or (bid >= rm.bank.num_backgrounds).any():
    raise ValueError(
        f"Texture ids exceed the render model's bank ({rm.bank.num_floors} floors, "
        f"{rm.bank.num_backgrounds} skies); sample with num_floors/num_backgrounds "
        f"of this bank (RenderModel.sample).")
  sel = lambda f, x, dv: np.where(on(f).reshape((n,) + (1,) * (np.ndim(x) - 1)), x, dv)

  body = sel("body", P["body_rgba"], d["mat_rgba"][rm.body_mats[0]])
  eff = sel("body", P["effector_rgba"], d["mat_rgba"][rm.effector_mats[0]])
  tgt = sel("target", P["target_rgba"], d["mat_rgba"][rm.target_mats[0]])
  floor_matid = np.where(on("floor") & (fid >= 0), rm.floor_mat0 + fid, d["floor_matid"])
  refl = np.where(on("reflectance"), P["floor_reflectance"],
                  d["mat_reflectance"][floor_matid]).astype(np.float32)
  head = np.stack([P["headlight_ambient"], P["headlight_diffuse"],
                   P["headlight_specular"]], axis=1).astype(np.float32)
  head = sel("light", head, d["headlight"])

  # Camera: Euler offsets (intrinsic x-y-z) on top of the default orientation.
  rot = P["cam_rot"].astype(np.float64)
  q = np.broadcast_to(d["cam_quat"], (n, 4)).copy()
  for axis in range(3):
    if np.any(rot[:, axis] != 0):
      q = _qmul(q, _axis_quat(rot[:, axis], axis))
  q = q / np.sqrt(np.sum(q * q, axis=-1, keepdims=True))
  cpos = P["cam_pos"].astype(np.float64)
  xpos, xquat, com = rm.cam_frame
  cxpos = xpos + _rotate(np.broadcast_to(xquat, (n, 4)), cpos)
  cmat = _qmat(_qmul(np.broadcast_to(xquat, (n, 4)), q))
  cam = on("camera")[:, None]
  cam_pos = np.where(cam, cpos, d["cam_pos"])
  cam_quat = np.where(cam, q, d["cam_quat"])
  cam_pos0 = np.where(cam, cxpos - xpos, d["cam_pos0"])
  cam_poscom0 = np.where(cam, cxpos - com, d["cam_poscom0"])
  cam_mat0 = np.where(cam, cmat, d["cam_mat0"])

  # Light: position and (normalised) direction, and their tracking offsets.
  lmoves = on("light") & (R.DOMAIN_RANGES[rm.domain].light_pos is not None)
  lpos = P["light_pos"].astype(np.float64)
  ldir = P["light_dir"].astype(np.float64)
  norm = np.sqrt(np.sum(ldir * ldir, axis=-1, keepdims=True))
  ldir = np.where(norm > 1e-9, ldir / np.where(norm > 1e-9, norm, 1.0), d["light_dir"])
  xpos, xquat, com = rm.light_frame
  lxpos = xpos + _rotate(np.broadcast_to(xquat, (n, 4)), lpos)
  lxdir = _rotate(np.broadcast_to(xquat, (n, 4)), ldir)
  lm = lmoves[:, None]
  # Light colour (finger): the drawn values as they are (float32, as MuJoCo stores).
  lcol = (on("light") & (R.DOMAIN_RANGES[rm.domain].light_diffuse is not None))[:, None]
  sky = np.where(on("background") & (bid >= 0), rm.bg_tex0 + bid, rm.sky_tex)
  # A moving look (`moving.look_at`): the floor material's colour and a second sky.
  floor_rgba = d["mat_rgba"][floor_matid].astype(np.float32)
  if "floor_delta" in P:
    floor_rgba[:, :3] = np.clip(floor_rgba[:, :3] + P["floor_delta"], 0.0, 1.0)
  sky2, mix = sky.copy(), np.zeros(n, np.float32)
  if "background_mix" in P:
    sky2 = rm.bg_tex0 + P["background2_id"].astype(np.int64)
    mix = P["background_mix"].astype(np.float32)
  return Looks(
      body_rgba=body.astype(np.float32), effector_rgba=eff.astype(np.float32),
      target_rgba=tgt.astype(np.float32), floor_matid=floor_matid,
      floor_reflectance=refl, headlight=head,
      cam_pos=cam_pos, cam_quat=cam_quat, cam_pos0=cam_pos0,
      cam_poscom0=cam_poscom0, cam_mat0=cam_mat0,
      light_pos=np.where(lm, lpos, d["light_pos"]),
      light_dir=np.where(lm, ldir, d["light_dir"]),
      light_pos0=np.where(lm, lxpos - xpos, d["light_pos0"]),
      light_poscom0=np.where(lm, lxpos - com, d["light_poscom0"]),
      light_dir0=np.where(lm, lxdir, d["light_dir0"]),
      light_diffuse=np.where(lcol, P["light_diffuse"], d["light_diffuse"]).astype(np.float32),
      light_specular=np.where(lcol, P["light_specular"],
                              d["light_specular"]).astype(np.float32),
      skybox_tex=sky, floor_rgba=floor_rgba, skybox_tex2=sky2, sky_mix=mix)


def look_textures(rm: RenderModel, looks: Looks, index: int) -> tuple[int, ...]:
  """Texture ids env `index`'s look draws from the bank or dm_control: its floor
  material's texture (-1 for none), its skybox, and the skybox it blends in."""
  floor = int(rm.model.mat_texid[int(looks.floor_matid[index]), _ROLE_RGB])
  return floor, int(looks.skybox_tex[index]), int(looks.skybox_tex2[index])


def set_skybox(rm: RenderModel, context: mujoco.MjrContext, tex: int) -> None:
  """Makes texture `tex` (dm_control's skybox or a bank cube) the drawn skybox.

  Args:
    rm: the render model the context was made from.
    context: its `mujoco.MjrContext`.
    tex: texture id (`Looks.skybox_tex`).
  """
  tt = context.textureType
  if rm.sky_tex >= 0:
    tt[rm.sky_tex] = _SKYBOX if tex == rm.sky_tex else _CUBE
  nb = rm.bank.num_backgrounds
  tt[rm.bg_tex0:rm.bg_tex0 + nb] = _CUBE
  if tex != rm.sky_tex:
    tt[tex] = _SKYBOX
  slot = (context.mat_texid.shape[0] // _NTEXROLE - 1) * _NTEXROLE + _ROLE_RGB
  context.mat_texid[slot] = tex


def apply(rm: RenderModel, looks: Looks | VisualParams, index: int = 0,
          context: mujoco.MjrContext | None = None) -> None:
  """Writes env `index`'s look into `rm.model` (and the skybox into `context`).

  Every field a look can change is written, so looks can follow each other in
  any order on one model. Cost: a few small array writes (no texture upload).

  Args:
    rm: the domain's `RenderModel`.
    looks: `Looks` from `prepare` (or `VisualParams`, converted here).
    index: which env of the batch.
    context: the `mujoco.MjrContext` that will render (created from `rm.model`);
      needed when the look has a bank skybox.

  Raises:
    ValueError: if the look needs a skybox switch and no context is given.
  """
  if not isinstance(looks, Looks):  # VisualParams
    looks = prepare(rm, looks.take(index))
    index = 0
  m, i = rm.model, index
  d = rm.dflt
  m.mat_rgba[:] = d["mat_rgba"]
  m.mat_rgba[rm.body_mats] = looks.body_rgba[i]
  m.mat_rgba[rm.effector_mats] = looks.effector_rgba[i]
  m.mat_rgba[rm.target_mats] = looks.target_rgba[i]
  mid = int(looks.floor_matid[i])
  m.geom_matid[rm.floor_geom] = mid
  m.mat_rgba[mid] = looks.floor_rgba[i]
  m.mat_reflectance[mid] = looks.floor_reflectance[i]
  hl = m.vis.headlight
  hl.ambient[:], hl.diffuse[:], hl.specular[:] = looks.headlight[i]
  c, l = rm.cam_id, rm.light_id
  m.cam_pos[c] = looks.cam_pos[i]
  m.cam_quat[c] = looks.cam_quat[i]
  m.cam_pos0[c] = looks.cam_pos0[i]
  m.cam_poscom0[c] = looks.cam_poscom0[i]
  m.cam_mat0[c] = looks.cam_mat0[i]
  m.light_pos[l] = looks.light_pos[i]
  m.light_dir[l] = looks.light_dir[i]
  m.light_pos0[l] = looks.light_pos0[i]
  m.light_poscom0[l] = looks.light_poscom0[i]
  m.light_dir0[l] = looks.light_dir0[i]
  m.light_diffuse[l] = looks.light_diffuse[i]
  m.light_specular[l] = looks.light_specular[i]
  tex = int(looks.skybox_tex[i])
  if context is not None:
    set_skybox(rm, context, tex)
  elif tex != rm.sky_tex:
    raise ValueError("This look has a bank skybox: pass the mujoco.MjrContext "
                     "that renders as context= (MuJoCo picks the skybox there).")


# ---------------------------------------------------------------------------
# The reference renderer
# ---------------------------------------------------------------------------



def variable_index(m: mujoco.MjModel, key: str) -> tuple[str, int]:
  """A task model variable's place in `m`: "<field>:<element name>" (e.g.
  "geom_pos:target") → (the MjModel field, the element's id); ValueError for a
  field that is not a per-element geom/site/body/... field or a name `m` lacks."""
  field, name = key.split(":", 1)
  obj = FIELD_OBJECTS.get(field.split("_")[0])
  if obj is None or not hasattr(m, field):
    raise ValueError(f"Unsupported model variable {key!r}.")
  i = find_id(m, obj, name)
  if i < 0:
    raise ValueError(f"Model variable {key!r}: no {field.split('_')[0]} named {name!r}.")
  return field, i


def _write_variables(m: mujoco.MjModel, variables: Mapping[str, Any] | None
                     ) -> dict[tuple[str, int], np.ndarray]:
  """Writes task model variables ("geom_pos:target" → value; keys without a colon
  are ignored) into `m`; returns the values they replaced, by (field, element id)."""
  saved = {}
  for key, value in (variables or {}).items():
    if ":" not in key:
      continue
    field, i = variable_index(m, key)
    arr = getattr(m, field)
    saved.setdefault((field, i), np.array(arr[i]))
    arr[i] = np.asarray(value)
  return saved


class FrameRenderer:
  """Renders single frames of one domain's looks with `mujoco.Renderer`.

  This is the reference: `render(looks, qpos, index=i)` applies env i's look,
  sets the state and draws camera 0 (by default). With seed 0 it reproduces
  dm_control's `physics.render` of the same state and camera.

  Args:
    rm: the domain's `RenderModel` (`apply` writes each frame's look into its
      model; a frame's task variables are written for that frame only and the
      defaults restored after it, so renderers sharing `rm` never see each
      other's; the renderer's GL context holds the whole bank, uploaded once at
      creation).
    height, width: frame size in pixels (at most the model's offscreen size,
      640×480 for the DMC domains).
  """

  def __init__(self, rm: RenderModel, height: int = 84, width: int = 84):
    self.rm = rm
    self.height, self.width = height, width
    self.renderer = mujoco.Renderer(rm.model, height, width)
    self.data = mujoco.MjData(rm.model)

  @property
  def context(self) -> mujoco.MjrContext:
    return self.renderer._mjr_context  # pylint: disable=protected-access

  def render(self, looks: Looks | VisualParams, qpos, *, index: int = 0,
             model_variables: Mapping[str, Any] | None = None,
             camera: int | str = 0) -> np.ndarray:
    """Renders env `index`'s look at the state `qpos`.

    Args:
      looks: `Looks` or `VisualParams` (batch).
      qpos: generalised positions (dm_control's layout).
      index: which env of the batch.
      model_variables: task variables kept in the model (`State.info`).
      camera: camera id or name (the looks move camera 0).

    Returns:
      uint8 array (height, width, 3).
    """
    apply(self.rm, looks, index, context=self.context)
    m, d = self.rm.model, self.data
    saved = _write_variables(m, model_variables)
    try:
      d.qpos[:] = np.asarray(qpos, np.float64)
      d.qvel[:] = 0
      mujoco.mj_fwdPosition(m, d)
      self.renderer.update_scene(d, camera=camera)
      return self.renderer.render().copy()
    finally:
      for (field, i), value in saved.items():
        getattr(m, field)[i] = value

  def close(self) -> None:
    self.renderer.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()


_FRAME_RENDERERS: dict[tuple[int, int, int], FrameRenderer] = {}


def render_frame(rm: RenderModel, looks: Looks | VisualParams, qpos, *,
                 index: int = 0, model_variables: Mapping[str, Any] | None = None,
                 camera: int | str = 0, height: int = 84, width: int = 84) -> np.ndarray:
  """Applies env `index`'s look to the render model and renders one frame.

  Uses a `FrameRenderer` cached per (render model, size) in this process.

  Args:
    rm: the domain's `RenderModel` (`build_render_model`).
    looks: `VisualParams` (or prepared `Looks`).
    qpos: generalised positions of the state to draw.
    index: which env of the batch.
    model_variables: task variables that live in the model (`State.info`,
      e.g. {"geom_pos:target": ...}).
    camera: camera id or name.
    height, width: frame size.

  Returns:
    uint8 array (height, width, 3).
  """
  key = (id(rm), height, width)
  fr = _FRAME_RENDERERS.get(key)
  if fr is None:
    fr = _FRAME_RENDERERS[key] = FrameRenderer(rm, height, width)
  return fr.render(looks, qpos, index=index, model_variables=model_variables,
                   camera=camera)


def close_renderers() -> None:
  """Frees the GL contexts cached by `render_frame`."""
  for fr in _FRAME_RENDERERS.values():
    fr.close()
  _FRAME_RENDERERS.clear()
