"""What both pixel vector envs share: arguments, spaces, physics, seeds, the gymnasium API.

`PixelEnvBase` is the gymnasium `VectorEnv` under `PixelVectorEnv` (the render
pool, `dmcr_jax.env_pool`) and `JaxPixelVectorEnv` (the ray caster,
`dmcr_jax.env_jax`): it checks `make`'s shared arguments, builds the spaces,
points its jitted physics (`physics_env`, shared by every env of one task, size
and frame skip; or the `physics_pool` workers) at the current visual seeds, and
implements `reset`, `step` (`step_async` then `step_wait`), `set_visuals`,
`set_state`, info, timings and `close`. A subclass renders. `announce_compile`
prints the one stderr line before the first compilation of an env's shape.
The semantics (auto-reset, observations, info, seeds) are described in
`dmcr_jax.env`.
"""

from __future__ import annotations

import functools
import sys
import time
from typing import Any, Sequence

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from dmcr_jax import models, physics_env
from dmcr_jax.checks import positive_int
from dmcr_jax.env_checks import (check_camera, check_physics_device, check_physics_workers,
                                 check_reset_seed, default_frame_skip, seed_source)
from dmcr_jax.models.base import physics_jit
from dmcr_jax.physics_pool import PendingStep, PhysicsPool
from dmcr_jax.visuals.factors import check_vary
from dmcr_jax.visuals.levels import EnvRanges, SeedBounds, SeedRange
from dmcr_jax.visuals.moving import check_moving
from dmcr_jax.visuals.pool import check_timeout, default_timeout

INFO_KEYS = ("state", "visual_seed", "episode_index", "episode_step", "episode_return")
"""The per-env entries of `info` (each also with gymnasium's "_<key>" mask)."""


@functools.lru_cache(maxsize=64)
def _physics_fns(task, num_envs: int, frame_skip: int, donate: bool):
  """Jitted (init, step) for N envs of `task`, shared by every env built alike.

  `models.load` returns one `Task` object per name and solver budget, so envs
  with the same task, size and frame skip reuse one compilation (an evaluation's
  or a test's second env compiles nothing). The visual seeds are the functions'
  last argument (`physics_env.seed_argument`): fixed seeds compile once, ranges
  (`SeedBounds`) once, whatever their values.
  """
  init = physics_jit(lambda key, seeds: physics_env.init(task, seeds, key, num_envs))
  step = physics_jit(lambda es, a, seeds: physics_env.step(task, seeds, frame_skip, es, a),
                     donate_argnums=(0,) if donate else ())
  return init, step


class PixelEnvBase(gymnasium.vector.VectorEnv):
  """What both pixel envs share: arguments, spaces, visual seeds, the gymnasium
  reset/step checks, `set_visuals`, `set_state`, info and timings. A subclass
  renders: `_use_seeds` (the seeds changed), `_reset(key)` and `_start_from(es)`
  (fresh stacks; both set `_es` and `_obs` and return (obs, info)),
  `_finish_step` (the frames of a stepped physics state) and `_compile_note`
  (what its first `reset` compiles, for `announce_compile`)."""

  metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"]}
  timing_parts: tuple[str, ...] = ()

  def __init__(self, task: str, num_envs: int, visual_seeds: Any, vary, frame_skip,
               frame_stack: int, image_size, camera, seed: int,
               solver_iterations: int | None, ls_iterations: int | None,
               physics_device: str | None = None, physics_workers: int | None = None,
               worker_timeout: float | None = None, moving=None, intensity: float = 0.0):
    self._physics_pool = None
    self.closed = False
    self.worker_timeout = (default_timeout() if worker_timeout is None
                           else check_timeout("worker_timeout", worker_timeout))
    domain, _ = models.split_name(task)
    check_physics_device(physics_device)
    self.physics_workers = check_physics_workers(physics_workers, physics_device)
    self.physics_device = physics_device
    self._physics_on = jax.devices("cpu")[0] if physics_device == "cpu" else jax.devices()[0]
    n = positive_int("num_envs", num_envs)
    self.frame_skip = positive_int(
        "frame_skip", default_frame_skip(task) if frame_skip is None else frame_skip)
    self.frame_stack = positive_int("frame_stack", frame_stack)
    h, w = (image_size, image_size) if np.ndim(image_size) == 0 else tuple(image_size)
    self.height, self.width = positive_int("image height", h), positive_int("image width", w)
    if np.ndim(seed) != 0:
      raise ValueError(f"seed must be an int, got {seed!r}")
    check_reset_seed(seed, num_envs)
    check_vary(domain, vary)  # validates `vary`, listing the factors
    self.moving, self.intensity = check_moving(domain, moving, intensity)
    self.task_name, self.domain, self.vary, self.camera = task, domain, vary, camera
    self.seeds = seed_source(visual_seeds, n)
    self.task = models.load(task, solver_iterations, ls_iterations)
    check_camera(self.task.mj_model, camera, task)
    self.num_envs = n
    self.single_action_space = gymnasium.spaces.Box(
        self.task.action_low, self.task.action_high, (self.task.action_size,), np.float32)
    self.single_observation_space = gymnasium.spaces.Box(
        0, 255, (self.height, self.width, 3 * self.frame_stack), np.uint8)
    self.action_space = batch_space(self.single_action_space, n)
    self.observation_space = batch_space(self.single_observation_space, n)
    self.render_mode = "rgb_array"
    self.episode_length = -(-self.task.time_limit // self.frame_skip)
    self._key = jax.random.key(int(seed))
    self._es = None
    self._obs = None
    self._pending = None
    self.reset_timings()

  def _use_physics(self) -> None:
    """Points `_init`/`_step` at the physics (in process, or the physics workers)
    and `_seed_arg` at the current seed source, their traced seed argument (fixed
    seeds, or ranges as `SeedBounds`): one compilation, and one set of workers,
    serve any seeds."""
    seed_arg = physics_env.seed_argument(self.seeds, self.num_envs)
    if self.physics_workers:
      if self._physics_pool is None:
        self._physics_pool = PhysicsPool(self.task, self.num_envs, self.frame_skip,
                                         self.physics_workers, timeout=self.worker_timeout,
                                         ranged=isinstance(seed_arg, SeedBounds))
      self._init, self._step = self._physics_pool.init, self._physics_pool.step
      self._seed_arg = seed_arg
      return
    self._init, self._step = _physics_fns(self.task, self.num_envs, self.frame_skip,
                                          self._physics_on.platform != "cpu")
    self._seed_arg = self._on_physics(seed_arg)

  def _close_physics(self) -> None:
    """Stops the physics workers, if any (idempotent)."""
    if getattr(self, "_physics_pool", None) is not None:
      self._physics_pool.close()
      self._physics_pool = None

  def _on_physics(self, tree):
    """`tree` committed to the physics device (the jitted physics runs where its
    inputs are)."""
    return jax.device_put(tree, self._physics_on)

  def set_visuals(self, visual_seeds: Any, vary: str | Sequence[str] | None = None) -> None:
    """Changes the looks: new visual seeds (and optionally `vary`) for every env.

    The physics is not recompiled when fixed seeds replace fixed seeds, or ranges
    replace ranges (the seeds are an argument of the jitted step), so an
    evaluation can sweep many visual conditions with one env. The running
    episodes end: call `reset` next.

    Args:
      visual_seeds: as for `make` (one int, one per env, a `SeedRange`, or one
        `SeedRange` per env).
      vary: the factors the seeds change (as for `make`); None keeps the current.

    Raises:
      ValueError: bad seeds or factors (the env is left unchanged).
    """
    self._check_open()
    vary = self.vary if vary is None else vary
    check_vary(self.domain, vary)
    seeds = seed_source(visual_seeds, self.num_envs)
    self.seeds, self.vary = seeds, vary
    self._use_seeds()
    self._es = self._obs = self._pending = None

  def set_state(self, state: physics_env.EnvState):
    """Replaces every env's state (e.g. to render one physical state under many
    looks) and restarts the frame stacks from it.

    Args:
      state: an `EnvState` shaped like `env.state` (each env's look follows its
        `visual_seed`).

    Returns:
      (observations, info) as after `reset`.

    Raises:
      ValueError: the state's structure or shapes differ from the env's.
      RuntimeError: before `reset`, or after `close`.
    """
    self._check_open()
    if self._es is None:
      raise RuntimeError("call reset() before set_state()")
    want = jax.tree.structure(self._es)
    if jax.tree.structure(state) != want or any(
        np.shape(a) != np.shape(b) for a, b in zip(jax.tree.leaves(state),
                                                   jax.tree.leaves(self._es))):
      raise ValueError("state must be an EnvState shaped like env.state")
    return self._start_from(self._on_physics(state))

  # gymnasium API -------------------------------------------------------------

  def reset(self, *, seed: int | None = None, options: dict | None = None):
    """Starts a new episode in every env.

    Args:
      seed: an int in [0, 2**32) re-seeds the dynamics keys (and few-shot seed
        draws); a list of N such ints (gymnasium's per-env form) gives env i the
        key of seed[i], so its episodes depend on seed[i] alone; None continues
        the env's key stream (a different episode each call).
      options: not used (must be None or empty).

    Returns:
      (observations, info) for all N envs.

    Raises:
      RuntimeError: after `close`.
    """
    self._check_open()
    if options:
      raise ValueError(f"{type(self).__name__}.reset takes no options, got {sorted(options)}")
    if seed is not None:
      seed = check_reset_seed(seed, self.num_envs)
      if np.ndim(seed) == 1:
        key = jax.vmap(jax.random.key)(jnp.asarray(seed))
        self._key = jax.random.fold_in(key[0], self.num_envs)
      else:
        self._key = jax.random.key(seed)
    if seed is None or np.ndim(seed) == 0:
      self._key, key = jax.random.split(self._key)
    self._pending = None
    announce_compile(self)
    return self._reset(self._on_physics(key))

  def step(self, actions):
    """One agent step of every env (NEXT_STEP auto-reset, see the module docstring):
    `step_async(actions)`, then `step_wait()`.

    Args:
      actions: float (N, action_size), finite (clipped to the action bounds).

    Returns:
      (observations, rewards, terminated, truncated, info).

    Raises:
      ValueError: wrong shape or non-finite actions (nothing is stepped).
      RuntimeError: `step` before `reset`, or after `close`.
    """
    self.step_async(actions)
    return self.step_wait()

  def step_async(self, actions) -> None:
    """Checks the actions and dispatches the physics of one agent step, without
    waiting for it; `step_wait` completes the step.

    Raises:
      ValueError: wrong shape or non-finite actions (nothing is stepped).
      RuntimeError: before `reset`, after `close`, or a step already pending.
    """
    self._check_open()
    if self._es is None:
      raise RuntimeError("call reset() before step()")
    if self._pending is not None:
      raise RuntimeError("step_async() called twice: call step_wait() first")
    actions = self._on_physics(self._check_actions(actions))
    t0 = time.perf_counter()
    resetting = self._es.needs_reset
    self._pending = (t0, resetting, self._step(self._es, actions, self._seed_arg))

  def step_wait(self):
    """Completes the step `step_async` began (as `step`'s returns)."""
    self._check_open()
    if self._pending is None:
      raise RuntimeError("step_wait() without a pending step_async()")
    pending, self._pending = self._pending, None
    obs, host = self._complete(*pending)
    self.timed_steps += 1
    terminated = np.zeros(self.num_envs, bool)
    return obs, host["reward"], terminated, host["truncated"], self._info(host)

  def _complete(self, t0, resetting, stepped):
    """(obs, host fields) of the pending step: waits for its physics, then
    `_finish_step`."""
    if isinstance(stepped, PendingStep):  # physics workers
      stepped = stepped.result()
    return self._finish_step(t0, resetting, *stepped)

  def render(self) -> np.ndarray | None:
    """The latest frame of every env, uint8 (N, H, W, 3) (None before reset)."""
    return None if self._obs is None else np.array(self._obs[..., -3:])

  def close(self, **kwargs) -> None:
    """Releases the renderer and the physics workers (idempotent); `reset` and
    `step` then raise. Optional: envs not closed are closed at interpreter exit."""
    self.closed = True
    self._close_physics()
    self._es = self._obs = self._pending = None

  def _check_open(self) -> None:
    """RuntimeError once the env is closed."""
    if self.closed:
      raise RuntimeError(f"this {type(self).__name__} is closed; make a new env with "
                         "dmcr_jax.make to step again")

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  @property
  def state(self) -> physics_env.EnvState | None:
    """The envs' current `EnvState` on the physics device (None before reset)."""
    if self._physics_pool is not None and self._es is not None:
      return self._on_physics(self._es)  # a copy: the workers' records change
    return self._es

  def reset_timings(self) -> None:
    """Zeroes `timings` (seconds per part of a step, `timing_parts`) and
    `timed_steps` (steps timed since)."""
    self.timings = dict.fromkeys(self.timing_parts, 0.0)
    self.timed_steps = 0

  def __repr__(self):
    seeds = (self.seeds if isinstance(self.seeds, (SeedRange, EnvRanges))
             else f"fixed {np.unique(self.seeds)[:4].tolist()}…")
    return (f"{type(self).__name__}({self.task_name!r}, num_envs={self.num_envs}, "
            f"visual_seeds={seeds}, vary={self.vary!r}, frame_skip={self.frame_skip}, "
            f"frame_stack={self.frame_stack}, image={self.height}x{self.width}"
            + (f", moving={','.join(self.moving)!r}, intensity={self.intensity}"
               if self.moving else "") + ")")

  def _compile_note(self) -> tuple[tuple, str, str, str]:
    """What `announce_compile` says of this env: (the options that key its compiled
    shape, what compiles, where besides the physics device, roughly how long)."""
    return (), "physics", "", "~10-60 s"

  # Internals ------------------------------------------------------------------

  def _check_actions(self, actions) -> np.ndarray:
    a = np.asarray(actions, dtype=np.float32)
    want = (self.num_envs, self.task.action_size)
    if a.shape != want:
      raise ValueError(f"actions must have shape {want} (num_envs, action_size), "
                       f"got {np.shape(actions)}")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
      raise ValueError(f"actions must be finite; envs {np.flatnonzero(bad)[:8].tolist()} "
                       "have NaN or inf entries")
    return a

  def _host_fields(self, es: physics_env.EnvState, reward, truncated) -> dict:
    """What the host reads of a step besides pixels (fetched with them)."""
    out = {"state": es.task.obs, "visual_seed": es.visual_seed,
           "episode_index": es.episode, "episode_step": es.episode_step,
           "episode_return": es.episode_return}
    if reward is not None:
      out["reward"], out["truncated"] = reward, truncated
    return out

  def _info(self, host: dict) -> dict:
    info = {k: host[k] for k in INFO_KEYS}
    every = np.ones(self.num_envs, bool)
    info.update({f"_{k}": every for k in INFO_KEYS})
    return info


_ANNOUNCED: set[tuple] = set()
"""The env shapes whose first compilation this process has announced."""


def announce_compile(env: PixelEnvBase) -> None:
  """Prints one line on stderr before the first `reset` of an env of a shape this
  process has not built yet: what compiles (its `reset` and first `step`), for how
  many envs, on which devices, and roughly how long it takes (JAX's persistent
  compilation cache, where enabled, makes later processes faster).

  Args:
    env: a pixel env about to reset (`env._compile_note()` says what it compiles).
  """
  options, what, frames_on, took = env._compile_note()
  shape = (type(env).__name__, env.task_name, env.num_envs, env.frame_skip, env.frame_stack,
           env.height, env.width, env.physics_device, env.physics_workers, options)
  if shape in _ANNOUNCED:
    return
  _ANNOUNCED.add(shape)
  where = env._physics_on.platform
  if env.physics_workers:
    where += f", in {env.physics_workers} physics worker process(es)"
  where += frames_on
  print(f"dmcr_jax: compiling {env.task_name}'s {what} for {env.num_envs} envs on {where} "
        f"(first reset and step); this takes {took} the first time", file=sys.stderr,
        flush=True)
