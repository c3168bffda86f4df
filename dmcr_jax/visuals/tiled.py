"""Render many MuJoCo frames per GL context: tiles of one offscreen buffer, one readback.

`TiledRenderer` owns a GL context, an `MjrContext` and an `MjvScene` for one
`mujoco.MjModel`. For a batch, every frame is rendered (`mjv_updateScene` +
`mjr_render`) at the origin of MuJoCo's offscreen buffer, exactly as
`mujoco.Renderer` renders it, and then copied (and multisample-resolved) with
`glBlitFramebuffer` into its tile of one large tile buffer; the tile buffer is
read back once per batch instead of once per frame. Before each frame a
caller-supplied `prepare(i)` writes env i's state (and look) into the model and
data.

Why not render straight into each tile's viewport: rasterising at a viewport
offset changes floating-point rounding, and on Mesa that moved about one pixel
per frame by one level. Rendering at the origin and blitting keeps every tile
bit-identical to a single-frame `mujoco.Renderer` (tests check this), whatever the
frame's position in the batch, so pixels do not depend on batch size or on the
number of workers.

`QUALITY` names the render presets: `"exact"` keeps dm_control's settings (what
the seed-0 parity test uses); the fast presets shrink or drop the shadow map and
drop reflections, trading look for speed (see benchmarks/results).
"""

from __future__ import annotations

import contextlib
import math
from typing import Callable, Iterable

import mujoco
import numpy as np

from dmcr_jax.models.names import find_id

# preset -> (shadow map size or None to keep the model's, shadows on, reflections on)
QUALITY: dict[str, tuple[int | None, bool, bool]] = {
    "exact": (None, True, True),
    "fast": (256, True, False),
    "fastest": (None, False, False),
}


def check_quality(quality: str) -> str:
  """`quality` if it names a render preset of `QUALITY`, else a ValueError naming them."""
  if quality not in QUALITY:
    raise ValueError(f"Unknown render quality {quality!r}; valid: {', '.join(QUALITY)}.")
  return quality


def apply_quality(model: mujoco.MjModel, quality: str) -> None:
  """Sets the model's shadow map size for a preset (before the MjrContext exists)."""
  size, _, _ = QUALITY[check_quality(quality)]
  if size is not None:
    model.vis.quality.shadowsize = size


def prepare_kinematics(model: mujoco.MjModel, data: mujoco.MjData) -> None:
  """Computes what the renderer reads from `qpos`: poses, tracking cameras and
  lights, tendon paths (cheaper than `mj_forward`: no dynamics, no collision)."""
  mujoco.mj_kinematics(model, data)
  mujoco.mj_comPos(model, data)
  mujoco.mj_camlight(model, data)
  mujoco.mj_tendon(model, data)


@contextlib.contextmanager
def _textures_shrunk(model: mujoco.MjModel, textures: Iterable[int]):
  """Within the block, `textures` read as 1×1 (2-D) or 1×1 per face (cube), so a
  GL context made here holds a placeholder for each; their data and the other
  textures are untouched, and the sizes are restored on exit."""
  ids = np.asarray(list(textures), np.int64)
  width, height = model.tex_width[ids].copy(), model.tex_height[ids].copy()
  separate_faces = (model.tex_type[ids] != int(mujoco.mjtTexture.mjTEXTURE_2D)) & (height != width)
  try:
    model.tex_width[ids] = 1
    model.tex_height[ids] = np.where(separate_faces, 6, 1)
    yield
  finally:
    model.tex_width[ids], model.tex_height[ids] = width, height


class TiledRenderer:
  """Renders batches of `height`×`width` frames of one model, many per readback.

  Args:
    model: the render model (its fields may be changed per frame by `prepare`;
      its offscreen buffer size is set to one frame).
    height, width: frame size in pixels.
    camera: fixed camera id or name.
    tiles: frames per readback (default: as many as fit in a 2048² buffer).
    quality: a key of `QUALITY`.
    lazy_textures: texture ids the GL context gets only when `upload` asks for
      them (a 1×1 placeholder until then): a context of a large texture bank is
      made in a fraction of the time and holds only the textures drawn.
  """

  def __init__(self, model: mujoco.MjModel, height: int, width: int, camera=0,
               tiles: int | None = None, quality: str = "exact",
               lazy_textures: Iterable[int] = ()):
    self.model = model
    self.height, self.width = int(height), int(width)
    if self.height < 1 or self.width < 1:
      raise ValueError(f"frame size must be positive, got {height}x{width}")
    if isinstance(camera, str):
      cam_id = find_id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    else:
      cam_id = int(camera)
    if not 0 <= cam_id < model.ncam:
      raise ValueError(f"camera {camera!r} not in the model ({model.ncam} cameras)")
    self.camera_id = cam_id
    if tiles is None:
      tiles = max(1, (2048 // self.width) * (2048 // self.height))
    self.cols = max(1, min(int(tiles), 2048 // self.width or 1))
    self.rows = max(1, math.ceil(int(tiles) / self.cols))
    self.tiles = self.cols * self.rows
    bw, bh = self.cols * self.width, self.rows * self.height
    self.buffer_size = (bw, bh)
    apply_quality(model, quality)
    _, shadows, reflections = QUALITY[quality]
    # MuJoCo's (multisampled) offscreen buffer only ever holds one frame, so it is
    # sized to the frame, not to the tile buffer, which renders faster
    # (benchmarks/results/render_variants_h100.md).
    model.vis.global_.offwidth, model.vis.global_.offheight = self.width, self.height
    self._gl = mujoco.GLContext(max(bw, 1), max(bh, 1))
    self._gl.make_current()
    self._not_uploaded = set(int(t) for t in lazy_textures)
    with _textures_shrunk(model, self._not_uploaded):
      self.context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)
    self.scene = mujoco.MjvScene(model, maxgeom=10000)
    self.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = shadows
    self.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = reflections
    self.option = mujoco.MjvOption()
    self.perturb = mujoco.MjvPerturb()
    self.cam = mujoco.MjvCamera()
    self.cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
    self.cam.fixedcamid = cam_id
    self._buf = np.empty((bh, bw, 3), np.uint8)
    self._make_tile_buffer(bw, bh)

  def _make_tile_buffer(self, bw: int, bh: int) -> None:
    from OpenGL import GL  # after the context exists (PyOpenGL picks its platform)
    self._GL = GL
    self._tile_fbo = GL.glGenFramebuffers(1)
    self._tile_rbo = GL.glGenRenderbuffers(1)
    GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._tile_rbo)
    GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, bw, bh)
    GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._tile_fbo)
    GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0,
                                 GL.GL_RENDERBUFFER, self._tile_rbo)
    status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
    if status != GL.GL_FRAMEBUFFER_COMPLETE:
      raise RuntimeError(f"tile framebuffer incomplete (status {status})")
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)

  def upload(self, textures: Iterable[int]) -> None:
    """Uploads those of `textures` (ids of `lazy_textures`) that the GL context
    does not hold yet; others are ignored. Call it from `prepare`, before the
    frame that draws them (the context is current there)."""
    for t in textures:
      if t in self._not_uploaded:
        mujoco.mjr_uploadTexture(self.model, self.context, int(t))
        self._not_uploaded.discard(t)

  def render(self, data: mujoco.MjData, n: int, prepare: Callable[[int], None],
             out: np.ndarray) -> None:
    """Renders frames 0..n-1 into `out[:n]` (uint8, (n, H, W, 3)).

    `prepare(i)` must leave `self.model` and `data` describing frame i
    (typically: write the look, write qpos, `prepare_kinematics`).
    """
    self._gl.make_current()
    GL = self._GL
    H, W = self.height, self.width
    origin = mujoco.MjrRect(0, 0, W, H)
    for start in range(0, n, self.tiles):
      count = min(self.tiles, n - start)
      used_rows = math.ceil(count / self.cols)
      for k in range(count):
        prepare(start + k)
        mujoco.mjv_updateScene(self.model, data, self.option, self.perturb, self.cam,
                               mujoco.mjtCatBit.mjCAT_ALL, self.scene)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)
        mujoco.mjr_render(origin, self.scene, self.context)
        r, c = divmod(k, self.cols)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self.context.offFBO)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._tile_fbo)
        GL.glBlitFramebuffer(0, 0, W, H, c * W, r * H, (c + 1) * W, (r + 1) * H,
                             GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST)
      GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._tile_fbo)
      GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
      GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
      buf = self._buf[:used_rows * H]
      GL.glReadPixels(0, 0, self.cols * W, used_rows * H, GL.GL_RGB, GL.GL_UNSIGNED_BYTE,
                      buf)
      for k in range(count):
        r, c = divmod(k, self.cols)
        # GL rows run bottom-up: tile row r sits r*H rows above the bottom.
        out[start + k] = buf[r * H:(r + 1) * H, c * W:(c + 1) * W][::-1]
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)

  def close(self) -> None:
    """Frees the GL resources."""
    if getattr(self, "_gl", None) is not None:
      self._gl.make_current()
      self._GL.glDeleteFramebuffers(1, [self._tile_fbo])
      self._GL.glDeleteRenderbuffers(1, [self._tile_rbo])
      self.context.free()
      self._gl.free()
      self._gl = None
