"""`RenderPool`: DMCR pixels for a whole batch of envs from CPU-side MuJoCo renderers.

W worker processes (a `WorkerPool`), each with its own GL context and its own
copy of the domain's render model, render fixed slices of the batch. Inputs — the
envs' `qpos`, their looks (`render_model.Looks`, one row per env) and the task's
model variables (targets) — are written once per call into shared memory; each
worker renders its slice with a `TiledRenderer` (many frames per readback) and
writes uint8 pixels straight into a shared output array.

Pixels equal the single-frame reference (`render_model.FrameRenderer`) bit for
bit, for any number of workers and any batch size: every frame is rendered at
the origin of its context and only copied into a tile (see `tiled`).

GL backend: `gl=None` takes `MUJOCO_GL` when set, else EGL when an NVIDIA device
is present and OSMesa otherwise; pass "egl" or "osmesa" to choose.
"""

from __future__ import annotations

import copy
import dataclasses
import glob
import os
from typing import Any, Mapping

import mujoco
import numpy as np

from dmcr_jax.visuals import render_model as rmod
from dmcr_jax.visuals.params import VisualParams
from dmcr_jax.visuals.pool import ArraySpec, WorkerPool
from dmcr_jax.visuals.tiled import TiledRenderer, check_quality, prepare_kinematics

GL_BACKENDS = ("egl", "osmesa")
_OBJ = {"geom": mujoco.mjtObj.mjOBJ_GEOM, "site": mujoco.mjtObj.mjOBJ_SITE,
        "body": mujoco.mjtObj.mjOBJ_BODY, "mat": mujoco.mjtObj.mjOBJ_MATERIAL,
        "cam": mujoco.mjtObj.mjOBJ_CAMERA, "light": mujoco.mjtObj.mjOBJ_LIGHT}


def default_gl() -> str:
  """The GL backend workers use by default (see the module docstring)."""
  env = os.environ.get("MUJOCO_GL")
  if env:
    return env
  return "egl" if glob.glob("/dev/nvidia[0-9]*") else "osmesa"


def default_workers() -> int:
  """One worker per core, at most 16."""
  return max(1, min(16, os.cpu_count() or 1))


def _variable_specs(model: mujoco.MjModel, keys) -> dict[str, tuple[str, int, tuple]]:
  out = {}
  for key in keys:
    field, name = key.split(":", 1)
    obj = _OBJ.get(field.split("_")[0])
    if obj is None or not hasattr(model, field):
      raise ValueError(f"Unsupported model variable {key!r}.")
    i = mujoco.mj_name2id(model, obj, name)
    if i < 0:
      raise ValueError(f"Model variable {key!r}: no {field.split('_')[0]} named {name!r}.")
    out[key] = (field, i, tuple(np.shape(getattr(model, field)[i])))
  return out


def _look_specs(rm: rmod.RenderModel) -> dict[str, ArraySpec]:
  looks = rmod.prepare(rm, rm.sample([0], vary="none"))
  return {f.name: ArraySpec(tuple(getattr(looks, f.name).shape[1:]),
                            str(getattr(looks, f.name).dtype))
          for f in dataclasses.fields(rmod.Looks)}


class _WorkerRenderer:
  """Built inside each worker: the render model, a tiled renderer, MjData."""

  def __init__(self, domain: str, variables: tuple[str, ...], height: int, width: int,
               camera, quality: str, tiles: int | None):
    self.rm = copy.copy(rmod.build_render_model(domain))
    self.model = self.rm.model
    self.data = mujoco.MjData(self.model)
    self.variables = _variable_specs(self.model, variables)
    self.renderer = TiledRenderer(self.model, height, width, camera=camera,
                                  tiles=tiles, quality=quality)

  def __call__(self, inputs: Mapping[str, np.ndarray], out: np.ndarray) -> None:
    looks = rmod.Looks(**{f.name: inputs["look." + f.name]
                          for f in dataclasses.fields(rmod.Looks)})
    qpos = inputs["qpos"]
    m, d = self.model, self.data

    def prepare(i: int) -> None:
      rmod.apply(self.rm, looks, i, context=self.renderer.context)
      for key, (field, j, _) in self.variables.items():
        getattr(m, field)[j] = inputs["var." + key][i]
      d.qpos[:] = qpos[i]
      prepare_kinematics(m, d)

    self.renderer.render(d, len(out), prepare, out)


class RenderPool:
  """Renders batches of DMCR frames in W worker processes.

  Args:
    task: a task name ("walker-walk") or a domain ("walker"); a task also fixes
      which model variables (targets) `render` takes.
    max_batch: the largest batch `render` accepts.
    height, width: frame size (default 84×84).
    camera: camera id or name (the looks move camera 0).
    workers: number of processes (default: `default_workers()`).
    quality: render preset, a key of `tiled.QUALITY` ("exact" = dm_control's).
    gl: "egl" or "osmesa" (default: `default_gl()`).
    tiles: frames per readback in each worker (default: fill a 2048² buffer).
    timeout: seconds a worker may take for its slice before it is replaced.

  Use as a context manager, or call `close()`.
  """

  def __init__(self, task: str, max_batch: int, height: int = 84, width: int = 84,
               camera: int | str = 0, workers: int | None = None,
               quality: str = "exact", gl: str | None = None,
               tiles: int | None = None, timeout: float = 120.0):
    from dmcr_jax import models
    if "-" in task:
      domain, _ = models.split_name(task)
      variables = tuple(f"{f}:{n}" for f, n in models.spec(task).model_variables)
    else:
      domain = rmod.check_domain(task)
      variables = ()
    gl = default_gl() if gl is None else gl
    if gl not in GL_BACKENDS:
      raise ValueError(f"Unknown GL backend {gl!r}; valid: {', '.join(GL_BACKENDS)}.")
    check_quality(quality)
    if int(height) < 1 or int(width) < 1:
      raise ValueError(f"frame size must be positive, got {height}x{width}")
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
    self._pool = WorkerPool(
        _WorkerRenderer, (domain, variables, self.height, self.width, camera, quality, tiles),
        inputs, ArraySpec((self.height, self.width, 3), "uint8"), max_batch=max_batch,
        workers=workers, timeout=timeout,
        env={"MUJOCO_GL": gl, "PYOPENGL_PLATFORM": gl})
    self.max_batch = self._pool.max_batch
    self.num_workers = self._pool.num_workers

  @property
  def restarts(self) -> int:
    """Workers replaced so far (killed or hung)."""
    return self._pool.restarts

  @property
  def pids(self) -> list[int]:
    return self._pool.pids

  def render(self, qpos, looks: VisualParams | rmod.Looks,
             model_variables: Mapping[str, Any] | None = None, *,
             copy_out: bool = True) -> np.ndarray:
    """Renders N envs.

    Args:
      qpos: (N, nq) generalised positions (dm_control's layout).
      looks: the N envs' `VisualParams` (or `Looks` already prepared).
      model_variables: the task's model variables, each (N, …), e.g.
        `State.info`; extra keys are ignored.
      copy_out: return a copy (True) or a view of shared memory that the next
        call overwrites (False).

    Returns:
      uint8 array (N, height, width, 3).
    """
    qpos = np.asarray(qpos)
    if qpos.ndim != 2 or qpos.shape[1] != self.nq:
      raise ValueError(f"qpos must have shape (N, {self.nq}), got {qpos.shape}")
    n = qpos.shape[0]
    if not 1 <= n <= self.max_batch:
      raise ValueError(f"batch size must be in [1, {self.max_batch}], got {n}")
    if isinstance(looks, VisualParams):
      if looks.domain and looks.domain != self.domain:
        raise ValueError(f"looks are for {looks.domain!r}, the pool renders {self.domain!r}")
      looks = rmod.prepare(self.rm, looks)
    if len(looks) != n:
      raise ValueError(f"got {len(looks)} looks for {n} envs")
    missing = [k for k in self._var_specs if model_variables is None or k not in model_variables]
    if missing:
      raise ValueError(f"{self.task} needs model variables {missing} (from State.info)")
    shm = self._pool.inputs
    shm["qpos"][:n] = qpos
    for f in dataclasses.fields(rmod.Looks):
      shm["look." + f.name][:n] = getattr(looks, f.name)
    for k, (_, _, shape) in self._var_specs.items():
      v = np.asarray(model_variables[k], np.float64)
      if v.shape != (n,) + shape:
        raise ValueError(f"model variable {k!r} must have shape {(n,) + shape}, got {v.shape}")
      shm["var." + k][:n] = v
    out = self._pool.run(n)
    return out.copy() if copy_out else out

  def close(self) -> None:
    """Stops the workers and frees shared memory."""
    self._pool.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()
