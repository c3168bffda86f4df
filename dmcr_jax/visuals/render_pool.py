"""`RenderPool`: DMCR pixels for a whole batch of envs from CPU-side MuJoCo renderers.

W worker processes (a `WorkerPool`), each with its own GL context and its own
copy of the domain's render model, render fixed slices of the batch. Inputs — the
envs' `qpos`, their looks (`render_model.Looks`, one row per env) and the task's
model variables (targets) — are written once per call into shared memory; each
worker renders its slice with a `TiledRenderer` (many frames per readback) and
writes uint8 pixels straight into a shared output array. A worker's GL context
receives a texture of the bank the first time one of its looks draws it, not
all of them at start.

Pixels equal the single-frame reference (`render_model.FrameRenderer`) bit for
bit, for any number of workers and any batch size: every frame is rendered at
the origin of its context and only copied into a tile (see `tiled`).

Frame stacks (`frame_stack=k`): the workers also build each env's stacked
observation (H, W, 3k), oldest frame first, in a double-buffered output: the new
stack is the previous call's stack shifted by one frame plus the new frame (or
the new frame k times where `restart` is set). Reading only the previous buffer
keeps a re-rendered slice correct after a fault, and the stacking, a copy with
3-byte runs, is spread over the workers instead of the caller.

GL backend: `gl=None` takes `MUJOCO_GL` when it names one of `GL_BACKENDS`, else
EGL (`import dmcr_jax` sets `MUJOCO_GL=egl` on a machine without a display, so
that is the usual default, with or without a GPU: Mesa's EGL renders on the
CPU). `gl="osmesa"` needs the OSMesa library (Debian: libosmesa6); the workers
start with `MUJOCO_GL`/`PYOPENGL_PLATFORM` set to the chosen backend, so no
environment variable is needed in the caller's shell.

EGL devices: by default every worker renders on MuJoCo's EGL device (the one
`MUJOCO_EGL_DEVICE_ID` names, else the first that works). `egl_devices=(d0, d1,
…)` spreads the workers over those EGL device indices, worker w on
`egl_devices[w % len]`: on a machine with several GPUs, frames can be drawn on
GPUs other than the one that trains, or on all of them at once.
"""

from __future__ import annotations

import copy
import ctypes.util
import dataclasses
import os
from typing import TYPE_CHECKING, Any, Mapping

import mujoco
import numpy as np

from dmcr_jax.checks import positive_int
from dmcr_jax.visuals import render_model as rmod
from dmcr_jax.visuals.pool import ArraySpec, OwnsWorkerPool, WorkerPool
from dmcr_jax.visuals.tiled import TiledRenderer, check_quality, prepare_kinematics

if TYPE_CHECKING:  # workers import this module and never JAX (render_model's note)
  from dmcr_jax.visuals.params import VisualParams

GL_BACKENDS = ("egl", "osmesa")


def default_gl() -> str:
  """The GL backend workers use by default (see the module docstring)."""
  env = os.environ.get("MUJOCO_GL", "").lower()
  return env if env in GL_BACKENDS else "egl"


def check_egl_devices(egl_devices, gl: str) -> tuple[int, ...] | None:
  """`egl_devices` as a tuple of EGL device indices (ints ≥ 0, at least one), or
  None; ValueError otherwise, or when `gl` is not "egl"."""
  if egl_devices is None:
    return None
  devices = tuple(egl_devices)
  if not devices or any(isinstance(d, bool) or not isinstance(d, (int, np.integer)) or d < 0
                        for d in devices):
    raise ValueError(f"egl_devices must be EGL device indices (ints >= 0), got {egl_devices!r}")
  if gl != "egl":
    raise ValueError(f"egl_devices apply only to gl='egl', not gl={gl!r}")
  return tuple(int(d) for d in devices)


def check_gl(gl: str) -> str:
  """`gl` if it is one of `GL_BACKENDS` and its library can be loaded, else ValueError."""
  if gl not in GL_BACKENDS:
    raise ValueError(f"Unknown GL backend {gl!r}; valid: {', '.join(GL_BACKENDS)}.")
  if gl == "osmesa" and ctypes.util.find_library("OSMesa") is None:
    raise ValueError("gl='osmesa' needs the OSMesa library, which is not installed "
                     "(Debian/Ubuntu: apt-get install libosmesa6); gl='egl' renders "
                     "without it")
  return gl


def default_workers() -> int:
  """One worker per core, at most 16."""
  return max(1, min(16, os.cpu_count() or 1))


def _variable_specs(model: mujoco.MjModel, keys) -> dict[str, tuple[str, int, tuple]]:
  out = {}
  for key in keys:
    field, i = rmod.variable_index(model, key)
    out[key] = (field, i, tuple(np.shape(getattr(model, field)[i])))
  return out


def _look_specs(rm: rmod.RenderModel) -> dict[str, ArraySpec]:
  looks = rmod.prepare(rm, rm.sample([0], vary="none"))
  return {f.name: ArraySpec(tuple(getattr(looks, f.name).shape[1:]),
                            str(getattr(looks, f.name).dtype))
          for f in dataclasses.fields(rmod.Looks)}


def shift_stacks(out: np.ndarray, prev: np.ndarray) -> None:
  """``out[..., :-3] = prev[..., 3:]`` (every stack one frame on) as one contiguous copy.

  Flat, each byte of `prev` goes 3 places back: every pixel's later frames land
  where its earlier ones were, and its newest frame's 3 channels receive the next
  pixel's oldest frame, which the caller then overwrites with the new frame. A
  strided copy would touch 6 bytes of every 9; contiguous, it is a memmove
  (benchmarks/results/env_h100.md compares the two).

  Args:
    out, prev: C-contiguous uint8 (n, H, W, 3·k) stacks, distinct buffers.

  Raises:
    AttributeError: a buffer that is not contiguous (no flat view of it exists).
  """
  flat_out, flat_prev = out.view(), prev.view()
  flat_out.shape = flat_prev.shape = (-1,)  # fails rather than copy
  flat_out[:-3] = flat_prev[3:]


class _WorkerRenderer:
  """Built inside each worker: the render model, a tiled renderer, MjData."""

  def __init__(self, domain: str, variables: tuple[str, ...], height: int, width: int,
               camera, quality: str, tiles: int | None, frame_stack: int = 1):
    self.rm = copy.copy(rmod.build_render_model(domain))
    self.model = self.rm.model
    self.data = mujoco.MjData(self.model)
    self.variables = _variable_specs(self.model, variables)
    self.renderer = TiledRenderer(self.model, height, width, camera=camera,
                                  tiles=tiles, quality=quality,
                                  lazy_textures=self.rm.bank_textures)
    self.frame_stack = frame_stack
    self.frames = None

  def __call__(self, inputs: Mapping[str, np.ndarray], out: np.ndarray,
               prev: np.ndarray | None = None) -> None:
    looks = rmod.Looks(**{f.name: inputs["look." + f.name]
                          for f in dataclasses.fields(rmod.Looks)})
    qpos = inputs["qpos"]
    m, d = self.model, self.data

    def prepare(i: int) -> None:
      rmod.apply(self.rm, looks, i, context=self.renderer.context)
      self.renderer.upload(rmod.look_textures(self.rm, looks, i))
      for key, (field, j, _) in self.variables.items():
        getattr(m, field)[j] = inputs["var." + key][i]
      d.qpos[:] = qpos[i]
      prepare_kinematics(m, d)

    n = len(out)
    if self.frame_stack == 1:
      self.renderer.render(d, n, prepare, out)
      self._blend_skies(looks, prepare, out)
      return
    if self.frames is None or len(self.frames) < n:
      self.frames = np.empty((n,) + out.shape[1:3] + (3,), np.uint8)
    frames = self.frames[:n]
    self.renderer.render(d, n, prepare, frames)
    self._blend_skies(looks, prepare, frames)
    shift_stacks(out, prev)
    out[..., -3:] = frames
    restart = np.flatnonzero(inputs["restart"])
    if len(restart):
      out[restart] = np.concatenate([frames[restart]] * self.frame_stack, axis=-1)


  def _blend_skies(self, looks: rmod.Looks, prepare, frames: np.ndarray) -> None:
    """Cross-fades the skies of the frames whose look blends in a second skybox
    (`Looks.sky_mix` > 0): those rows are drawn again under `skybox_tex2` and the
    two frames mixed, which blends only the sky (all else is the same in both)."""
    rows = np.flatnonzero(looks.sky_mix[:len(frames)] > 0)
    if not len(rows):
      return

    def prepare2(j: int) -> None:
      i = int(rows[j])
      prepare(i)
      rmod.set_skybox(self.rm, self.renderer.context, int(looks.skybox_tex2[i]))

    second = np.empty((len(rows),) + frames.shape[1:], np.uint8)
    self.renderer.render(self.data, len(rows), prepare2, second)
    w = looks.sky_mix[rows].astype(np.float32)[:, None, None, None]
    frames[rows] = np.rint((1 - w) * frames[rows] + w * second).astype(np.uint8)


class RenderPool(OwnsWorkerPool):
  """Renders batches of DMCR frames in W worker processes.

  Args:
    task: a task name ("walker-walk") or a domain ("walker"); a task also fixes
      which model variables (targets) `render` takes.
    max_batch: the largest batch `render` accepts.
    height, width: frame size (default 84×84).
    camera: camera id or name (the looks move camera 0).
    workers: number of processes (default: `default_workers()`).
    quality: render preset, a key of `tiled.QUALITY` ("exact" = dm_control's).
    gl: "egl" or "osmesa" (default: `default_gl()`; see the module docstring).
    tiles: frames per readback in each worker (default: fill a 2048² buffer).
    timeout: seconds a busy worker may send no heartbeat before it is announced
      and replaced (None: `pool.default_timeout()`, `DMCR_WORKER_TIMEOUT`).
    frame_stack: k > 1 makes `render` return stacked observations
      (N, H, W, 3k), built in the workers (see the module docstring).
    egl_devices: EGL device indices the workers are spread over (see the module
      docstring; None: MuJoCo's default device).
    wait_start: False returns once the workers are launched; the first `submit`
      waits for them to have started (`WorkerPool`'s `wait_start`).

  Use as a context manager, or call `close()`.
  """

  def __init__(self, task: str, max_batch: int, height: int = 84, width: int = 84,
               camera: int | str = 0, workers: int | None = None,
               quality: str = "exact", gl: str | None = None,
               tiles: int | None = None, timeout: float | None = None,
               frame_stack: int = 1,
               egl_devices=None, wait_start: bool = True):
    from dmcr_jax import models
    if "-" in task:
      domain, _ = models.split_name(task)
      variables = tuple(f"{f}:{n}" for f, n in models.spec(task).model_variables)
    else:
      domain = rmod.check_domain(task)
      variables = ()
    gl = check_gl(default_gl() if gl is None else gl)
    self.egl_devices = check_egl_devices(egl_devices, gl)
    check_quality(quality)
    if int(height) < 1 or int(width) < 1:
      raise ValueError(f"frame size must be positive, got {height}x{width}")
    self.frame_stack = positive_int("frame_stack", frame_stack)
    workers = default_workers() if workers is None else int(workers)
    self.task, self.domain, self.variables = task, domain, variables
    self.height, self.width, self.gl, self.quality = int(height), int(width), gl, quality
    self.rm = rmod.build_render_model(domain)
    self.nq = int(self.rm.model.nq)
    self._var_specs = _variable_specs(self.rm.model, variables)
    inputs = {"qpos": ArraySpec((self.nq,), "float64")}
    inputs.update({"look." + k: v for k, v in _look_specs(self.rm).items()})
    inputs.update({"var." + k: ArraySpec(shape, "float64")
                   for k, (_, _, shape) in self._var_specs.items()})
    if self.frame_stack > 1:
      inputs["restart"] = ArraySpec((), "bool")
    self._pool = WorkerPool(
        _WorkerRenderer, (domain, variables, self.height, self.width, camera, quality, tiles,
                          self.frame_stack),
        inputs, ArraySpec((self.height, self.width, 3 * self.frame_stack), "uint8"),
        max_batch=max_batch, workers=workers, timeout=timeout,
        buffers=2 if self.frame_stack > 1 else 1,
        # Workers never compute with JAX: keep it off the GPU (it would reserve
        # most of the GPU's memory in every worker).
        env={"MUJOCO_GL": gl, "PYOPENGL_PLATFORM": gl, "JAX_PLATFORMS": "cpu"},
        worker_env=[{"MUJOCO_EGL_DEVICE_ID": str(d)} for d in self.egl_devices or ()],
        wait_start=wait_start)
    self.max_batch = self._pool.max_batch
    self.num_workers = self._pool.num_workers

  def render(self, qpos, looks: VisualParams | rmod.Looks,
             model_variables: Mapping[str, Any] | None = None, *,
             restart=None, copy_out: bool = True) -> np.ndarray:
    """Renders N envs: `submit` with these arguments, then `collect(copy_out)`.

    Args:
      qpos: (N, nq) generalised positions (dm_control's layout).
      looks: the N envs' `VisualParams` (or `Looks` already prepared).
      model_variables: the task's model variables, each (N, …), e.g.
        `State.info`; extra keys are ignored.
      restart: with `frame_stack` > 1, bool (N,): envs whose stack starts
        afresh (the new frame repeated); None = all. A stack continues the
        previous call's stack of the same env index.
      copy_out: return a copy (True) or a view of shared memory that a later
        call overwrites (False).

    Returns:
      uint8 array (N, height, width, 3 · frame_stack).
    """
    self.submit(qpos, looks, model_variables, restart=restart)
    return self.collect(copy_out)

  @property
  def busy(self) -> bool:
    """Whether a `submit` awaits its `collect`."""
    return self._pool.busy

  def rows(self, start: int, stop: int) -> RenderRows:
    """Envs [start, stop) of this pool's batch as a pool of their own
    (`RenderRows`), drawn by this pool's workers."""
    return RenderRows(self, start, stop)

  def submit(self, qpos, looks: VisualParams | rmod.Looks,
             model_variables: Mapping[str, Any] | None = None, *, restart=None) -> None:
    """Hands N envs' frames to the workers and returns without waiting for them
    (arguments as for `render`); `collect` waits. One call of the pool's rows may
    be in flight; row views (`rows`) each have one of their own."""
    self._submit(qpos, looks, model_variables, restart, 0)

  def _submit(self, qpos, looks, model_variables, restart, start: int) -> None:
    """`submit` of envs [start, start + N) of the batch, queued behind the calls
    in flight (which hold other rows)."""
    qpos = np.asarray(qpos)
    if qpos.ndim != 2 or qpos.shape[1] != self.nq:
      raise ValueError(f"qpos must have shape (N, {self.nq}), got {qpos.shape}")
    n = qpos.shape[0]
    if not 1 <= n <= self.max_batch - start:
      raise ValueError(f"batch size must be in [1, {self.max_batch - start}], got {n}")
    self._pool.check_free(n, start)   # before the inputs of a call in flight change
    if not isinstance(looks, rmod.Looks):  # VisualParams
      if looks.domain and looks.domain != self.domain:
        raise ValueError(f"looks are for {looks.domain!r}, the pool renders {self.domain!r}")
      looks = rmod.prepare(self.rm, looks)
    if len(looks) != n:
      raise ValueError(f"got {len(looks)} looks for {n} envs")
    missing = [k for k in self._var_specs if model_variables is None or k not in model_variables]
    if missing:
      raise ValueError(f"{self.task} needs model variables {missing} (from State.info)")
    shm = {k: v[start:start + n] for k, v in self._pool.inputs.items()}
    shm["qpos"][:] = qpos
    for f in dataclasses.fields(rmod.Looks):
      shm["look." + f.name][:] = getattr(looks, f.name)
    for k, (_, _, shape) in self._var_specs.items():
      v = np.asarray(model_variables[k], np.float64)
      if v.shape != (n,) + shape:
        raise ValueError(f"model variable {k!r} must have shape {(n,) + shape}, got {v.shape}")
      shm["var." + k][:] = v
    if self.frame_stack > 1:
      shm["restart"][:] = True if restart is None else np.broadcast_to(
          np.asarray(restart, bool), (n,))
    self._pool.submit(n, start)

  def collect(self, copy_out: bool = True) -> np.ndarray:
    """Waits for the frames `submit` handed out: uint8 (N, height, width,
    3 · frame_stack), the same pixels `render` returns (`copy_out` as there)."""
    return self._collect(copy_out, 0)

  def _collect(self, copy_out: bool, start: int) -> np.ndarray:
    """`collect` of the call of envs from `start` (and of every call before it)."""
    out = self._pool.wait(start)
    return out.copy() if copy_out else out



class RenderRows:
  """Envs [start, stop) of a `RenderPool`'s batch, drawn by its workers
  (`RenderPool.rows`): `render`, `submit` and `collect` as the pool's, on those
  rows, each view's frame stacks its own. Envs that share one pool's workers
  (`dmcr_jax.make(..., render_pool=view)`) each take a view of their own rows;
  each view may have a call in flight while the others have theirs: the workers
  draw them in the order submitted. `close` does nothing (the pool's owner closes
  the pool).

  Attributes:
    pool: the `RenderPool`.
    start: the first row.
    max_batch: stop − start.
    task, domain, rm, height, width, frame_stack, quality, num_workers: the pool's.
  """

  def __init__(self, pool: RenderPool, start: int, stop: int):
    if not 0 <= start < stop <= pool.max_batch:
      raise ValueError(f"rows [{start}, {stop}) must be a non-empty range inside the "
                       f"pool's batch [0, {pool.max_batch})")
    self.pool, self.start, self.max_batch = pool, int(start), int(stop - start)
    for name in ("task", "domain", "rm", "height", "width", "frame_stack", "quality",
                 "num_workers"):
      setattr(self, name, getattr(pool, name))
    self._submitted = False

  @property
  def busy(self) -> bool:
    """Whether this view's `submit` awaits its `collect`."""
    return self._submitted

  def render(self, qpos, looks, model_variables=None, *, restart=None,
             copy_out: bool = True) -> np.ndarray:
    """`RenderPool.render` of these rows."""
    self.submit(qpos, looks, model_variables, restart=restart)
    return self.collect(copy_out)

  def submit(self, qpos, looks, model_variables=None, *, restart=None) -> None:
    """`RenderPool.submit` of these rows."""
    self.pool._submit(qpos, looks, model_variables, restart, self.start)
    self._submitted = True

  def collect(self, copy_out: bool = True) -> np.ndarray:
    """`RenderPool.collect` of this view's `submit`."""
    if not self._submitted:
      raise RuntimeError("collect() without a submit() of these rows")
    self._submitted = False
    return self.pool._collect(copy_out, self.start)

  def close(self) -> None:
    """Nothing: the pool's owner closes it."""
