"""The render-pool env: N DMCR envs whose pixels MuJoCo draws in CPU worker processes.

`PixelVectorEnv` (`dmcr_jax.make(..., renderer="pool")`) is a `PixelEnvBase`
whose frames come from a `visuals.render_pool.RenderPool`: per step, the
physics (jitted, `physics_env`), one transfer of what the frames read, the
envs' looks (`env_looks`: static looks kept between steps, or each step's
moving looks) and one render call whose workers also stack the frames. It
offers `step_submit` (the frames drawn while the caller works) and
`set_looks` (one visual condition per env); `timings` splits a step into
`TIMING_PARTS`. The semantics are those described in `dmcr_jax.env`.
"""

from __future__ import annotations

import time
from typing import Any, Sequence

import jax
import numpy as np

from dmcr_jax import physics_env
from dmcr_jax.checks import positive_int
from dmcr_jax.env_base import PixelEnvBase
from dmcr_jax.env_looks import StaticLooks, static_looks, vary_key
from dmcr_jax.physics_pool import PendingStep
from dmcr_jax.visuals import render_model as rmod
from dmcr_jax.visuals.factors import check_vary
from dmcr_jax.visuals.levels import SeedRange
from dmcr_jax.visuals.moving import look_at
from dmcr_jax.visuals.render_pool import (RenderPool, RenderRows, check_egl_devices, check_gl,
                                          default_gl, default_workers)

TIMING_PARTS = ("physics", "transfer", "render", "copy")
"""The parts of a pool env's step its `timings` add up (seconds): the physics,
the transfer of what the frames read, the render call and the copy out."""


def _check_render_pool(pool, env) -> None:
  """ValueError unless `pool` (`make(render_pool=...)`) is a `RenderPool` or
  `RenderRows` of the env's task and frame sizes, with room for its envs."""
  if not isinstance(pool, (RenderPool, RenderRows)):
    raise ValueError(f"render_pool must be a RenderPool or RenderPool.rows(...), got "
                     f"{type(pool).__name__}")
  want = (env.task_name, env.height, env.width, env.frame_stack)
  got = (pool.task, pool.height, pool.width, pool.frame_stack)
  if got != want or pool.max_batch < env.num_envs:
    raise ValueError(f"render_pool draws (task, height, width, frame_stack) = {got} for "
                     f"{pool.max_batch} envs; this env needs {want} for {env.num_envs}")


class _Frames:
  """A step whose frames `PixelVectorEnv.step_submit` handed to the workers:
  its host fields (`host`)."""

  def __init__(self, host: dict):
    self.host = host


class PixelVectorEnv(PixelEnvBase):
  """N DMCR envs with pixel observations from the CPU render pool (a gymnasium
  `VectorEnv`).

  Build it with `dmcr_jax.make` (same arguments). Use as a context manager or
  call `close()` to stop the render workers when done with it; an env left open
  is closed at interpreter exit (`visuals.pool`).
  """

  timing_parts = TIMING_PARTS

  def __init__(self, task: str, num_envs: int = 1, visual_seeds: Any = 0,
               vary: str | Sequence[str] | None = "all", frame_skip: int | None = None,
               frame_stack: int = 3, image_size: int | tuple[int, int] = 84,
               camera: int | str = 0, seed: int = 0, *, workers: int | None = None,
               quality: str = "exact", gl: str | None = None, copy_obs: bool = True,
               egl_devices: Sequence[int] | None = None,
               solver_iterations: int | None = None, ls_iterations: int | None = None,
               physics_device: str | None = None, physics_workers: int | None = None,
               worker_timeout: float | None = None, moving=None, intensity: float = 0.0,
               render_pool=None):
    self._pool = None
    if workers is not None:
      positive_int("workers", workers)
    check_egl_devices(egl_devices, check_gl(default_gl() if gl is None else gl))
    super().__init__(task, num_envs, visual_seeds, vary, frame_skip, frame_stack,
                     image_size, camera, seed, solver_iterations, ls_iterations,
                     physics_device, physics_workers, worker_timeout, moving, intensity)
    n = self.num_envs
    self.copy_obs = bool(copy_obs)
    self._owns_pool = render_pool is None
    if render_pool is not None:
      _check_render_pool(render_pool, self)
      self._pool = render_pool
    else:
      self._pool = RenderPool(task, max_batch=n, height=self.height, width=self.width,
                              camera=camera, workers=min(n, workers or default_workers()),
                              quality=quality, gl=gl, frame_stack=self.frame_stack,
                              egl_devices=egl_devices, timeout=self.worker_timeout)
    self._use_seeds()
    self._static_params = None   # the envs' `StaticLooks` (`env_looks`), kept between steps
    self._env_varies = None      # per-env `vary_key`s (`set_looks`), else `vary` for all
    self._needs_reset = np.zeros(n, bool)

  def step_submit(self) -> None:
    """Waits for the physics `step_async` dispatched and hands the step's frames
    to the render workers without waiting for them; `step_wait` then waits for
    the frames and returns what `step` returns (the same pixels). In between,
    the caller can work while the workers draw (e.g. step another env's physics
    and policy: `dmcr_jax.protocol` pipelines two envs so).

    Raises:
      RuntimeError: no `step_async` pending (or its frames already submitted),
        or after `close`.
    """
    self._check_open()
    if self._pending is None or isinstance(self._pending[2], _Frames):
      raise RuntimeError("step_submit() without a pending step_async()")
    (t0, resetting, stepped), self._pending = self._pending, None
    if isinstance(stepped, PendingStep):  # physics workers
      stepped = stepped.result()
    self._pending = (t0, resetting, self._submit_frames(t0, *stepped))

  def _finish_step(self, t0, resetting, es, reward, truncated):
    """Waits for the physics, fetches what rendering needs, renders and stacks."""
    return self._collect_frames(self._submit_frames(t0, es, reward, truncated))

  def _complete(self, t0, resetting, stepped):
    if isinstance(stepped, _Frames):  # submitted by step_submit
      return self._collect_frames(stepped)
    return super()._complete(t0, resetting, stepped)

  def _submit_frames(self, t0, es, reward, truncated) -> _Frames:
    """Waits for the physics, fetches what rendering needs and submits the frames."""
    self._es = jax.block_until_ready(es)
    t1 = time.perf_counter()
    host = self._fetch(self._es, reward, truncated)
    t2 = time.perf_counter()
    self._render(host, restart=self._needs_reset, wait=False)
    self.timings["physics"] += t1 - t0
    self.timings["transfer"] += t2 - t1
    self.timings["render"] += time.perf_counter() - t2
    return _Frames(host)

  def _collect_frames(self, frames: _Frames):
    """Waits for the submitted frames and stacks; (obs, host fields)."""
    t0 = time.perf_counter()
    stacked = self._pool.collect(copy_out=False)
    t1 = time.perf_counter()
    obs = self._obs = self._output(stacked)
    self._needs_reset = frames.host["truncated"]
    self.timings["render"] += t1 - t0
    self.timings["copy"] += time.perf_counter() - t1
    return obs, frames.host

  def close(self, **kwargs) -> None:
    """Stops the render and physics workers (idempotent)."""
    super().close()
    if self._pool is not None:
      if self._owns_pool:
        self._pool.close()
      else:
        self._drain()
      self._pool = None

  def __del__(self):
    if getattr(self, "_pool", None) is not None or getattr(self, "_physics_pool", None):
      self.close()

  # Internals ------------------------------------------------------------------

  def set_visuals(self, visual_seeds: Any, vary: str | Sequence[str] | None = None) -> None:
    super().set_visuals(visual_seeds, vary)
    self._drain()
    self._env_varies = None

  set_visuals.__doc__ = PixelEnvBase.set_visuals.__doc__

  def _reset(self, key):
    return self._start_from(self._init(key, self._seed_arg))

  def _start_from(self, es: physics_env.EnvState):
    """Makes `es` the current state and renders fresh frame stacks from it."""
    self._drain()
    self._es = es
    host = self._fetch(es, None, None)
    self._obs = self._output(self._render(host, restart=None))
    self._needs_reset = np.asarray(jax.device_get(es.needs_reset), bool).copy()
    return self._obs, self._info(host)

  def _use_seeds(self) -> None:
    self._use_physics()

  def _drain(self) -> None:
    """Waits for (and drops) frames `step_submit` handed out and no `step_wait`
    collected (a reset or new looks end that step)."""
    if self._pool is not None and self._pool.busy:
      self._pool.collect(copy_out=False)

  def _fetch(self, es: physics_env.EnvState, reward, truncated) -> dict:
    out = self._host_fields(es, reward, truncated)
    out["qpos"] = es.task.data.qpos
    out["variables"] = {k: es.task.info[k] for k in self.task.model_variable_ids}
    return jax.device_get(out)

  def set_looks(self, visual_seeds, varies: Sequence) -> None:
    """Fixed looks with factors of their own: env i shows visual seed
    `visual_seeds[i]` under the factors `varies[i]` (each as `make`'s `vary`), so
    envs of several visual conditions step as one batch (the pool env only).
    `set_visuals` gives every env one `vary` again. The running episodes end:
    call `reset` next.

    Args:
      visual_seeds: N ints ≥ 0.
      varies: N values of `vary` ("none", "floor", "all", …).

    Raises:
      ValueError: not N seeds and N varies, a bad seed or factor (the env is
        left unchanged).
    """
    varies = list(varies)
    if self.moving and self.intensity > 0:
      raise ValueError(f"set_looks sets static looks; this env's looks move "
                       f"(moving={self.moving!r}): make it with moving=None")
    if (np.ndim(visual_seeds) != 1 or len(varies) != self.num_envs
        or any(isinstance(v, SeedRange) for v in visual_seeds)):
      raise ValueError(f"set_looks takes {self.num_envs} visual seeds and {self.num_envs} "
                       f"varies (one each per env), got {np.shape(visual_seeds)} seeds and "
                       f"{len(varies)} varies")
    for v in {vary_key(v): v for v in varies}.values():
      check_vary(self.domain, v)
    self.set_visuals(visual_seeds)
    self._env_varies = tuple(vary_key(v) for v in varies)

  def _static_looks(self, seeds) -> StaticLooks:
    """The envs' static looks for visual seeds `seeds`, each env under its factors
    (`set_looks`, else `vary`), kept in the envs' look cache."""
    varies = self._env_varies or (vary_key(self.vary),) * self.num_envs
    self._static_params = static_looks(self._pool.rm, seeds, varies, self._static_params)
    return self._static_params

  def _output(self, stacked: np.ndarray) -> np.ndarray:
    return stacked.copy() if self.copy_obs else stacked

  def step_params(self, seeds: np.ndarray, steps: np.ndarray):
    """The `VisualParams` the envs draw with visual seeds `seeds` at episode steps
    `steps` (int (N,) each): `moving.look_at` of their static looks under `vary`
    (the static looks themselves when nothing moves), the static looks kept in
    the envs' look cache (`env_looks.static_looks`)."""
    seeds = np.asarray(seeds, np.int32)
    varies = (vary_key(self.vary),) * len(seeds)
    self._static_params = static_looks(self._pool.rm, seeds, varies, self._static_params)
    return look_at(self._static_params.params, np.asarray(steps, np.int32), self.moving,
                   self.intensity, num_backgrounds=self._pool.rm.bank.num_backgrounds)

  def _render(self, host: dict, restart, wait: bool = True) -> np.ndarray | None:
    """The stacked frames of `host`'s envs (a view of shared memory); with
    `wait=False` only submitted (`RenderPool.collect` waits)."""
    if self._pool is None:
      raise RuntimeError("the env is closed")
    if self.moving and self.intensity > 0:   # this step's looks, shipped with the call
      looks = rmod.prepare(self._pool.rm, self.step_params(host["visual_seed"],
                                                           host["episode_step"]))
    else:
      looks = self._static_looks(host["visual_seed"]).looks
    self._pool.submit(host["qpos"], looks, host["variables"], restart=restart)
    return self._pool.collect(copy_out=False) if wait else None
