"""The ray-caster env: N DMCR envs whose physics, frames and stacks are one jitted call.

`JaxPixelVectorEnv` (`dmcr_jax.make(..., renderer="jax")`) is a `PixelEnvBase`
over the pure `dmcr_jax.jax_env.PixelEnv`: the JAX ray caster replaces the
render pool, each look is made on the device from its seed, and with the
physics on another device (the host CPU, or physics workers) the few arrays the
frames read move to the render device once per step. `to_host` fetches the
observations through page-locked host memory. The semantics are those
described in `dmcr_jax.env`.
"""

from __future__ import annotations

import time
from typing import Any, Sequence

import jax
import numpy as np

from dmcr_jax import jax_env, physics_env
from dmcr_jax.checks import positive_int
from dmcr_jax.env_base import PixelEnvBase


class JaxPixelVectorEnv(PixelEnvBase):
  """N DMCR envs whose physics, frames and frame stacks are one jitted call on the
  device (`dmcr_jax.jax_env`): the JAX ray caster replaces the render pool.

  Build it with `dmcr_jax.make(..., renderer="jax")`. Observations and info are
  those of `PixelVectorEnv` (NEXT_STEP auto-reset, stacks oldest first); the
  pixels are the ray caster's, close to MuJoCo's but not equal (see
  `dmcr_jax.visuals.jax_render`). `functional` is the pure `jax_env.PixelEnv`
  and `pixel_state` the current `jax_env.PixelState`, for code that scans steps
  on the device itself (`train/device_loop.py`).
  """

  timing_parts = ("step", "transfer")

  def __init__(self, task: str, num_envs: int = 1, visual_seeds: Any = 0,
               vary: str | Sequence[str] | None = "all", frame_skip: int | None = None,
               frame_stack: int = 3, image_size: int | tuple[int, int] = 84,
               camera: int | str = 0, seed: int = 0, *, shadows: bool = True,
               reflection: bool = True, render_chunk: int | None = None,
               render_kernel: bool | None = False, obs_on_device: bool = False,
               solver_iterations: int | None = None, ls_iterations: int | None = None,
               physics_device: str | None = None, physics_workers: int | None = None,
               worker_timeout: float | None = None, moving=None, intensity: float = 0.0):
    super().__init__(task, num_envs, visual_seeds, vary, frame_skip, frame_stack,
                     image_size, camera, seed, solver_iterations, ls_iterations,
                     physics_device, physics_workers, worker_timeout, moving, intensity)
    self._render_on = jax.devices()[0]
    if render_chunk is not None:
      render_chunk = positive_int("render_chunk", render_chunk)
    self._options = dict(camera=camera, shadows=bool(shadows), reflection=bool(reflection),
                         render_chunk=render_chunk, render_kernel=render_kernel)
    self.obs_on_device = bool(obs_on_device)
    self._ps = None
    self._use_seeds()

  def _finish_step(self, t0, resetting, es, reward, truncated):
    """The step's frames and stacks: with the physics on the render device, the
    fused call `_step` already made them; else what the frames read of the
    physics (`render_inputs`) moves to the render device and
    `jax_env.observe_inputs` renders there, and with `obs_on_device` the frames
    are not waited for (the caller's next device work queues behind them). Then
    the transfer to the host."""
    if isinstance(es, jax_env.PixelState):
      ps, es = es, None
    else:
      with jax.default_device(self._physics_on):  # NumPy leaves from physics workers
        inputs = jax_env.render_inputs(es, self.functional.drawn_variables)
      inputs = jax.device_put(inputs, self._render_on)
      ps = jax_env.observe_inputs(self.functional, self._ps.replace(physics=None), inputs,
                                  jax.device_put(resetting, self._render_on))
    if es is None or not self.obs_on_device:
      jax.block_until_ready(ps)
    t1 = time.perf_counter()
    obs, host = self._adopt(ps, reward, truncated, es=es)
    self.timings["step"] += t1 - t0
    self.timings["transfer"] += time.perf_counter() - t1
    return obs, host

  def close(self, **kwargs) -> None:
    """Stops the physics workers, if any, and drops the device state (idempotent);
    `reset` and `step` then raise."""
    super().close()
    self._ps = None

  def _compile_note(self) -> tuple[tuple, str, str, str]:
    """The ray caster compiles with the physics; its options key the shape."""
    options = tuple(sorted(self._options.items())) + (self.moving, self.intensity)
    frames_on = (f" (frames on {self._render_on.platform})"
                 if self._render_on.platform != self._physics_on.platform else "")
    took = ("several minutes (render_kernel=True)" if self._options["render_kernel"]
            else "~20-120 s")
    return options, "physics and ray-cast renderer", frames_on, took

  @property
  def pixel_state(self) -> jax_env.PixelState | None:
    """The current `jax_env.PixelState` (None before reset; with the physics on
    another device than the frames, its `physics` is None after a step: see
    `state` for the physics)."""
    return self._ps

  def _use_seeds(self) -> None:
    """Builds the functional env for the current seeds: fixed seeds only replace
    its look table, ranges its `SeedBounds` (nothing recompiles)."""
    self._use_physics()
    self.functional = jax_env.make_env(
        self.task, self.num_envs, self.seeds, self.vary, self.frame_skip, self.frame_stack,
        self.height, self.width, moving=self.moving, intensity=self.intensity,
        **self._options)
    self._ps = None
    if self._physics_on == self._render_on and not self.physics_workers:
      # physics, frames and stacks in one call
      fused = jax_env.step if jax.default_backend() == "cpu" else jax_env.step_donated
      self._step = lambda es, actions, seed_arg: fused(self.functional, self._ps, actions)

  def _reset(self, key):
    # The pool env's jitted `physics_env.init` (shared compilation), then the
    # looks made on the device and fresh stacks (`jax_env.start`, as `set_state`).
    # The same as `jax_env.reset(self.functional, key)`.
    es = self._init(key, self._seed_arg)
    physics = jax.device_put(es, self._render_on)
    look = self.functional.looks_of(physics.visual_seed)
    return self._adopt(jax_env.start(self.functional, physics, look), es=es)

  def _start_from(self, es: physics_env.EnvState):
    """Fresh stacks from `es`; each env's look follows its `visual_seed`."""
    look = jax_env.make_looks(self.functional.maker,
                              jax.device_put(es.visual_seed, self._render_on))
    return self._adopt(jax_env.start(self.functional, jax.device_put(es, self._render_on),
                                     look), es=es)

  def _adopt(self, ps: jax_env.PixelState, reward=None, truncated=None, es=None):
    """Makes `ps` (and `es`, its physics on the physics device; default
    `ps.physics`) current; (obs, host fields) or, without a reward, (obs, info)."""
    self._ps = ps
    self._es = ps.physics if es is None else es
    fields = self._host_fields(self._es, reward, truncated)
    host = jax.device_get(fields)
    self._obs = ps.obs if self.obs_on_device else to_host(ps.obs)
    return (self._obs, host) if reward is not None else (self._obs, self._info(host))


def to_host(x: jax.Array) -> np.ndarray:
  """A device array as a (read-only) NumPy array, through page-locked host memory.

  `jax.device_get` copies into pageable memory; put into the device's
  "pinned_host" memory first, a batch arrives in one DMA and NumPy views it
  without a copy (the timings: benchmarks/results/env_h100.md). Devices without
  that memory kind take the plain path.

  Args:
    x: an array on one device.
  """
  device = next(iter(x.devices()))
  if "pinned_host" in {m.kind for m in device.addressable_memories()}:
    x = jax.device_put(x, jax.sharding.SingleDeviceSharding(device, memory_kind="pinned_host"))
  return np.asarray(x)
