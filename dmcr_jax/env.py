"""`dmcr_jax.make`: N DMCR envs with pixels, as one gymnasium `VectorEnv`.

Two renderers, one interface (`renderer=`): "pool" (default, `PixelVectorEnv`)
renders MuJoCo's own pixels in CPU worker processes; "jax" (`JaxPixelVectorEnv`)
runs physics, the JAX ray caster (`visuals.jax_render`: close to MuJoCo's pixels,
not equal) and the frame stacks as one jitted call on the device
(`dmcr_jax.jax_env`, whose pure functions a training loop can scan). Both share
the arguments, spaces, visual seeds, auto-reset, observations and info described
below (`_PixelEnvBase`); `workers`, `quality`, `gl`, `egl_devices`, `copy_obs` and
`render_pool` are the pool's,
`shadows`, `reflection`, `render_chunk`, `render_kernel` and `obs_on_device` the
JAX renderer's,
and either refuses the other's. With "jax" a look is made on the device from its
seed (`jax_env`), so a range of any size costs no host memory or time.

Per agent step of the pool env, for the whole batch:
1. physics — one jitted call (`physics_env.step`): frame skip, rewards summed,
   NEXT_STEP auto-reset, next visual seeds (device);
2. transfer — the few arrays the host needs (qpos, task variables, rewards,
   flags, state features, seeds) in one `jax.device_get`;
3. render — looks of envs whose visual seed changed are rebuilt
   (`visuals.sample` + `prepare`), then one `RenderPool.render` call, whose
   workers also append the new frames to the envs' frame stacks (a reset env's
   stack is its first frame repeated);
4. copy — the stacked observations are copied out of shared memory (skipped
   with `copy_obs=False`: observations are then views of the pool's shared
   memory, valid until the step after next — enough to store a transition).
`env.timings` accumulates the seconds spent in each part (the JAX env: "step",
the one jitted call, and "transfer", the observations and info to the host;
with `obs_on_device` and the physics on the host CPU, `step_wait` returns once
the physics is done and the frames are dispatched, without waiting for them, so
"step" times the physics and that dispatch).

`step` is `step_async` (checks the actions and dispatches the physics, without
waiting for it) followed by `step_wait` (waits for the physics, renders,
returns gymnasium's step tuple), as in gymnasium's `AsyncVectorEnv`: a caller can
dispatch its own device work between the two (a training loop dispatches its
gradient updates there), so that work and the env step run at the same time.
The pool env splits `step_wait` once more: `step_submit` waits for the physics
and hands the frames to the render workers, `step_wait` then waits for them, so
the caller can work while the workers draw (`dmcr_jax.protocol` steps two envs'
physics and policy so, each while the other's frames are drawn).

Physics device (`physics_device=`): None runs the physics on JAX's default
device; "cpu" on the host's CPU (XLA:CPU), where a small batch (a few dozen envs)
steps in a fraction of the time an accelerator's launch latency allows, and off
the accelerator's queue, so a learner's updates on the accelerator do not wait
behind it (and it does not wait behind them). Rewards, observations and pixels are
the same either way up to float32 rounding (`tests/test_env.py`). With the physics
on the CPU, `physics_workers=W` steps it in W worker processes, each a slice of
the envs on its own XLA:CPU (`dmcr_jax.physics_pool`): on a many-core host a small
batch steps several times faster than in one process; the results are again the
same up to float32 rounding.

Lifecycle: the first `reset` of an env of a new shape (task, sizes, devices)
announces on stderr that its physics (and, with "jax", its renderer) compiles,
and roughly how long that takes; later envs of the same shape compile nothing
and say nothing. A render or physics worker that is unresponsive for
`worker_timeout` seconds (default: `DMCR_WORKER_TIMEOUT`, else 10) is announced
and replaced, and its slice done again (`visuals.pool`). `close()` frees the
workers and shared memory at once and is recommended, not required: an env left
open is closed at interpreter exit, also after an exception, Ctrl-C or SIGTERM.
A closed env's `reset` and `step` raise RuntimeError.

Auto-reset follows gymnasium's NEXT_STEP mode: the step that ends an episode
returns its last observation, reward and `truncated=True`; the env's next step
ignores its action and returns the new episode's first observation with reward
0 and both flags False. DMC tasks never terminate (`terminated` is always False);
they are truncated at 1,000 control steps.

Visual seeds (`visual_seeds=`):
- an int: every env shows that look (0: dm_control's, the classic setting);
- N ints: a fixed look per env;
- a `SeedRange` (few-shot): every episode of every env draws its seed from the
  range, e.g. `levels(1000)` = seeds [0, 1000); evaluation draws from
  `TEST_SEEDS`, which no training range may overlap (see `visuals.levels`);
- N `SeedRange`s (or an `EnvRanges`): env i draws every episode's seed from its
  own range (e.g. agents with different few-shot ranges in one batch).
A seed's look depends on the seed (and `vary`) alone, whatever range drew it.

Moving looks (`moving=`, `intensity=`; `visuals.moving`): the named factors
("camera", "light", "body", "floor", "background") drift within each episode,
as a function of the env's visual seed and episode step alone
(`visuals.moving.look_at`), inside a range `intensity` ∈ [0, 1] scales; the
physics and rewards are those of static looks. The pool env computes each step's
looks on the host and ships them with the render call; the JAX env makes them in
its jitted step. `moving=None` (default) or intensity 0 gives the static looks.

Observations are uint8 (N, H, W, 3·frame_stack), channels-last, oldest frame
first. `info` holds, per env: "state" (dm_control's state features, flat),
"visual_seed", "episode_index" (episodes begun − 1), "episode_step" (agent steps
in the episode) and "episode_return", each with gymnasium's boolean mask
"_<key>" (every env has every key: all True). "episode" is left to gymnasium's
`RecordEpisodeStatistics` wrappers, which reserve it.
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

from dmcr_jax import jax_env, models, physics_env
from dmcr_jax.physics_pool import PendingStep, PhysicsPool
from dmcr_jax.checks import positive_int
from dmcr_jax.models.base import physics_jit
from dmcr_jax.visuals import render_model as rmod
from dmcr_jax.visuals.factors import check_vary
from dmcr_jax.visuals.levels import TEST_SEEDS, TRAIN_SEEDS, EnvRanges, SeedBounds, SeedRange
from dmcr_jax.visuals.moving import check_moving, look_at
from dmcr_jax.visuals.params import check_seeds
from dmcr_jax.visuals.pool import check_timeout, default_timeout
from dmcr_jax.visuals.render_pool import (RenderPool, RenderRows, check_egl_devices, check_gl,
                                          default_gl, default_workers)

# Action repeat of the paper's Table 4; other tasks take their domain's value and
# domains the table does not list take 4 (PlaNet/DrQ's default).
ACTION_REPEAT = {"walker-walk": 2, "cheetah-run": 4, "hopper-stand": 4, "finger-spin": 2,
                 "ball_in_cup-catch": 4, "cartpole-balance": 8}
_DOMAIN_REPEAT = {"walker": 2, "cheetah": 4, "hopper": 4, "finger": 2, "ball_in_cup": 4,
                  "cartpole": 8}
TIMING_PARTS = ("physics", "transfer", "render", "copy")
INFO_KEYS = ("state", "visual_seed", "episode_index", "episode_step", "episode_return")
"""The per-env entries of `info` (each also with gymnasium's "_<key>" mask)."""
MAX_RESET_SEED = 2**32
"""`reset(seed=…)` and `make(seed=…)` take ints in [0, MAX_RESET_SEED): a JAX key
holds 32 bits of an int seed, so larger ones would repeat smaller ones' episodes."""


def check_reset_seed(seed, num_envs: int) -> np.ndarray | int:
  """A reset seed as an int, or gymnasium's per-env form (a sequence of `num_envs`
  ints) as a uint32 array; ValueError naming the rule otherwise."""
  values = [seed] if np.ndim(seed) == 0 else list(seed)
  if np.ndim(seed) == 1 and len(values) != num_envs:
    raise ValueError(f"seed must be an int or {num_envs} ints (one per env), got "
                     f"{len(values)} ints")
  for v in values:
    if (isinstance(v, bool) or not isinstance(v, (int, np.integer))
        or not 0 <= int(v) < MAX_RESET_SEED):
      raise ValueError(f"seed must be an int in [0, 2**32) or a list of {num_envs} such "
                       f"ints (one per env), got {seed!r}")
  return int(seed) if np.ndim(seed) == 0 else np.asarray(values, np.uint32)


def default_frame_skip(task: str) -> int:
  """The action repeat a task uses by default (see `ACTION_REPEAT`)."""
  domain, _ = models.split_name(task)
  return ACTION_REPEAT.get(task, _DOMAIN_REPEAT.get(domain, 4))


def check_camera(model, camera, task: str) -> None:
  """ValueError unless `camera` is a camera id or name of `model` (listing them)."""
  import mujoco
  from dmcr_jax.models.names import find_id
  names = [model.camera(i).name or str(i) for i in range(model.ncam)]
  if isinstance(camera, str):
    ok = find_id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera) >= 0
  else:
    ok = (not isinstance(camera, bool) and isinstance(camera, (int, np.integer))
          and 0 <= camera < model.ncam)
  if not ok:
    raise ValueError(f"camera must be an id in [0, {model.ncam}) or a name of {task}'s "
                     f"cameras ({', '.join(names)}), got {camera!r}")


def _check_one_side(r: SeedRange) -> SeedRange:
  """`r` if it lies inside `TRAIN_SEEDS` or inside `TEST_SEEDS`, else ValueError."""
  if not any(s.start <= r.start and r.stop <= s.stop for s in (TRAIN_SEEDS, TEST_SEEDS)):
    raise ValueError(f"visual_seeds {r} straddles the training range "
                     f"{TRAIN_SEEDS} and the held-out test range {TEST_SEEDS}; "
                     "use a range inside one of them")
  return r


def _seed_source(visual_seeds, num_envs: int) -> SeedRange | EnvRanges | np.ndarray:
  if isinstance(visual_seeds, SeedRange):
    return _check_one_side(visual_seeds)
  if isinstance(visual_seeds, (list, tuple)) and any(
      isinstance(v, SeedRange) for v in visual_seeds):
    if not all(isinstance(v, SeedRange) for v in visual_seeds):
      raise ValueError("visual_seeds mixes SeedRanges and fixed seeds; pass N ints or N "
                       "SeedRanges (one per env)")
    visual_seeds = EnvRanges(tuple(visual_seeds))
  if isinstance(visual_seeds, EnvRanges):
    if len(visual_seeds) != num_envs:
      raise ValueError(f"visual_seeds must hold one SeedRange per env ({num_envs}), got "
                       f"{len(visual_seeds)}")
    for r in visual_seeds.ranges:
      _check_one_side(r)
    return visual_seeds
  seeds = np.asarray(check_seeds(visual_seeds))
  if np.ndim(visual_seeds) == 0:
    return np.full((num_envs,), seeds[0], np.int32)
  if seeds.shape != (num_envs,):
    raise ValueError(f"visual_seeds must be one int, {num_envs} ints (one per env) or a "
                     f"SeedRange; got {seeds.shape[0]} seeds for {num_envs} envs")
  return seeds


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


RENDERERS = ("pool", "jax")
"""What `make(renderer=...)` accepts: the CPU render pool (MuJoCo's own pixels) or
the JAX ray caster (physics, rendering and stacking in one jitted call)."""


def check_renderer_name(renderer: str) -> str:
  """`renderer` if it is one of `RENDERERS`, else a ValueError naming them."""
  if renderer not in RENDERERS:
    raise ValueError(f"Unknown renderer {renderer!r}; valid: {', '.join(RENDERERS)}.")
  return renderer
_POOL_ONLY = ("workers", "quality", "gl", "egl_devices", "copy_obs", "render_pool")
PHYSICS_DEVICES = (None, "cpu")
"""What `make(physics_device=...)` accepts: JAX's default device, or the host CPU."""


def check_physics_workers(workers, physics_device: str | None) -> int:
  """`make(physics_workers=...)` as an int: 0 or None (the physics in this
  process), or W ≥ 1 worker processes, which need `physics_device="cpu"`."""
  if workers is None:
    return 0
  if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 0:
    raise ValueError(f"physics_workers must be None, 0 or a positive int, got {workers!r}")
  if workers and physics_device != "cpu":
    raise ValueError(f"physics_workers={workers} steps the physics in CPU processes: it "
                     f"needs physics_device='cpu', got physics_device={physics_device!r}")
  return int(workers)
_JAX_ONLY = ("shadows", "reflection", "render_chunk", "render_kernel", "obs_on_device")


class _PixelEnvBase(gymnasium.vector.VectorEnv):
  """What both pixel envs share: arguments, spaces, visual seeds, the gymnasium
  reset/step checks, `set_visuals`, `set_state`, info and timings. A subclass
  renders: `_use_seeds` (the seeds changed), `_reset(key)` and `_start_from(es)`
  (fresh stacks; both set `_es` and `_obs` and return (obs, info)) and `step`."""

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
    if physics_device not in PHYSICS_DEVICES:
      raise ValueError(f"physics_device must be None (JAX's default device) or 'cpu', "
                       f"got {physics_device!r}")
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
    self.seeds = _seed_source(visual_seeds, n)
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
    seeds = _seed_source(visual_seeds, self.num_envs)
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


def _vary_key(vary) -> str | tuple:
  """A `vary` value as a hashable key (a sequence of factors as a tuple)."""
  return vary if isinstance(vary, str) else tuple(vary)


class _Frames:
  """A step whose frames `PixelVectorEnv.step_submit` handed to the workers:
  its host fields (`host`)."""

  def __init__(self, host: dict):
    self.host = host


class PixelVectorEnv(_PixelEnvBase):
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
    self._looks = None
    self._look_seeds = None
    self._static_params = None      # (seeds, vary, VisualParams) of moving looks
    self._env_varies = None   # per-env factors (`set_looks`), else `vary` for all
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
    self._looks = self._look_seeds = self._env_varies = None

  set_visuals.__doc__ = _PixelEnvBase.set_visuals.__doc__

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
    for v in {_vary_key(v): v for v in varies}.values():
      check_vary(self.domain, v)
    self.set_visuals(visual_seeds)
    self._env_varies = varies

  def _looks_of(self, seeds: np.ndarray, rows: np.ndarray) -> rmod.Looks:
    """The prepared looks of envs `rows` showing `seeds`, each under its factors."""
    rm = self._pool.rm
    if self._env_varies is None:
      return rmod.prepare(rm, rm.sample(seeds, vary=self.vary))
    varies = [self._env_varies[i] for i in rows]
    keys = [_vary_key(v) for v in varies]
    out = None
    for key in dict.fromkeys(keys):
      sel = np.flatnonzero([k == key for k in keys])
      part = rmod.prepare(rm, rm.sample(seeds[sel], vary=varies[sel[0]]))
      if out is None:
        out = rmod.Looks(**{f: np.empty((len(rows),) + getattr(part, f).shape[1:],
                                        getattr(part, f).dtype)
                            for f in rmod.Looks.__dataclass_fields__})
      for f in rmod.Looks.__dataclass_fields__:
        getattr(out, f)[sel] = getattr(part, f)
    return out

  def _update_looks(self, seeds: np.ndarray) -> None:
    if self._looks is None:
      changed = np.arange(len(seeds))
    else:
      changed = np.flatnonzero(seeds != self._look_seeds)
      if not len(changed):
        return
    new = self._looks_of(seeds[changed], changed)
    if self._looks is None:
      self._looks = new
    else:
      for field in rmod.Looks.__dataclass_fields__:
        getattr(self._looks, field)[changed] = getattr(new, field)
    self._look_seeds = seeds.copy()

  def _output(self, stacked: np.ndarray) -> np.ndarray:
    return stacked.copy() if self.copy_obs else stacked

  def step_params(self, seeds: np.ndarray, steps: np.ndarray):
    """The `VisualParams` the envs draw with visual seeds `seeds` at episode steps
    `steps` (int (N,) each): `moving.look_at` of their static looks (the static
    looks themselves when nothing moves)."""
    seeds = np.asarray(seeds, np.int32)
    cached = self._static_params
    if cached is None or cached[1] != self.vary or not np.array_equal(cached[0], seeds):
      cached = self._static_params = (seeds.copy(), self.vary,
                                      self._pool.rm.sample(seeds, vary=self.vary))
    return look_at(cached[2], np.asarray(steps, np.int32), self.moving, self.intensity,
                   num_backgrounds=self._pool.rm.bank.num_backgrounds)

  def _render(self, host: dict, restart, wait: bool = True) -> np.ndarray | None:
    """The stacked frames of `host`'s envs (a view of shared memory); with
    `wait=False` only submitted (`RenderPool.collect` waits)."""
    if self._pool is None:
      raise RuntimeError("the env is closed")
    if self.moving and self.intensity > 0:   # this step's looks, shipped with the call
      looks = rmod.prepare(self._pool.rm, self.step_params(host["visual_seed"],
                                                           host["episode_step"]))
    else:
      self._update_looks(np.asarray(host["visual_seed"]))
      looks = self._looks
    self._pool.submit(host["qpos"], looks, host["variables"], restart=restart)
    return self._pool.collect(copy_out=False) if wait else None


class JaxPixelVectorEnv(_PixelEnvBase):
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


_ANNOUNCED: set[tuple] = set()
"""The env shapes whose first compilation this process has announced."""


def announce_compile(env: _PixelEnvBase) -> None:
  """Prints one line on stderr before the first `reset` of an env of a shape this
  process has not built yet: what compiles (its `reset` and first `step`), for how
  many envs, on which devices, and roughly how long it takes (JAX's persistent
  compilation cache, where enabled, makes later processes faster)."""
  jax_renderer = isinstance(env, JaxPixelVectorEnv)
  options = tuple(sorted(env._options.items())) + (env.moving, env.intensity) \
      if jax_renderer else ()
  shape = (type(env).__name__, env.task_name, env.num_envs, env.frame_skip, env.frame_stack,
           env.height, env.width, env.physics_device, env.physics_workers, options)
  if shape in _ANNOUNCED:
    return
  _ANNOUNCED.add(shape)
  where = env._physics_on.platform
  if env.physics_workers:
    where += f", in {env.physics_workers} physics worker process(es)"
  what = "physics"
  if jax_renderer:
    what = "physics and ray-cast renderer"
    if env._render_on.platform != env._physics_on.platform:
      where += f" (frames on {env._render_on.platform})"
  took = ("several minutes (render_kernel=True)" if jax_renderer and env._options["render_kernel"]
          else "~20-120 s" if jax_renderer else "~10-60 s")
  print(f"dmcr_jax: compiling {env.task_name}'s {what} for {env.num_envs} envs on {where} "
        f"(first reset and step); this takes {took} the first time", file=sys.stderr,
        flush=True)


def to_host(x: jax.Array) -> np.ndarray:
  """A device array as a (read-only) NumPy array, through page-locked host memory.

  `jax.device_get` copies into pageable memory; put into the device's
  "pinned_host" memory first, a batch arrives in one DMA and NumPy views it
  without a copy (the timings: benchmarks/results/env_h100.md).
  Devices without that memory kind take the plain path.
  """
  device = next(iter(x.devices()))
  if "pinned_host" in {m.kind for m in device.addressable_memories()}:
    x = jax.device_put(x, jax.sharding.SingleDeviceSharding(device, memory_kind="pinned_host"))
  return np.asarray(x)


def make(task: str, num_envs: int = 1, visual_seeds: Any = 0,
         vary: str | Sequence[str] | None = "all", frame_skip: int | None = None,
         frame_stack: int = 3, image_size: int | tuple[int, int] = 84,
         camera: int | str = 0, seed: int = 0, renderer: str = "pool",
         moving: str | Sequence[str] | None = None, intensity: float = 0.0,
         **kwargs) -> PixelVectorEnv | JaxPixelVectorEnv:
  """N DMCR envs with pixels, stepped as one batch (see the module docstring).

  Args:
    task: one of `dmcr_jax.ALL_TASKS`, e.g. "walker-walk".
    num_envs: N ≥ 1.
    visual_seeds: an int (every env), N ints (one per env), a `SeedRange`
      drawn from at every reset (few-shot: `levels(1000)`; test: `TEST_SEEDS`),
      or N `SeedRange`s (an `EnvRanges`): env i draws from its own.
    vary: factors the visual seeds change ("all", "none", "floor,background", …;
      named factors must apply to the task's domain, `visuals.factors.APPLICABLE`).
    frame_skip: control steps per agent step, rewards summed (default: the
      paper's action repeat, `default_frame_skip(task)`).
    frame_stack: frames per observation, stacked on the channel axis.
    image_size: H = W, or (H, W).
    camera: camera id or name (camera 0 is the one the visual seeds move).
    seed: dynamics seed, an int in [0, 2**32) (initial states; and few-shot seed
      draws).
    renderer: "pool" (default: MuJoCo's renderer in CPU worker processes,
      dm_control's pixels) or "jax" (the JAX ray caster on the device, physics,
      frames and stacks in one jitted call; close to MuJoCo's pixels, not equal).
    moving: factors that move within each episode: None (default: static looks),
      "all", or names from `visuals.moving.MOVING_FACTORS` ("camera", "light",
      "body", "floor", "background"; comma-separated or a sequence), each
      applicable to the task's domain (docs/moving.md).
    intensity: how far they move, in [0, 1] (a fraction of each factor's range, as
      the Distracting Control Suite's difficulty: .1, .2, .3); 0 is static.
    **kwargs: for "pool": `workers`, `quality` ("exact", "fast", "fastest"), `gl`
      ("egl", the default, or "osmesa", which needs the OSMesa library; no
      environment variable needed), `egl_devices` (EGL device indices the
      workers are spread over; None: MuJoCo's default) for the `RenderPool`, `copy_obs` (default True; False
      returns views of shared memory, see the module docstring), `render_pool` (a
      `RenderPool` of the task and frame sizes, or a `RenderPool.rows(a, b)` view
      of one, drawn with instead of starting workers of its own: envs that share
      workers, one step's frames in flight at a time among them; the env does not
      close it; its workers, quality, GL and camera are the pool's). For "jax"
      (which has no workers and no quality presets): `shadows`, `reflection`
      (default True: MuJoCo's picture), `render_chunk` (envs per render chunk,
      see `jax_env.make_env`), `render_kernel` (default False: render through
      XLA; True: in one fused GPU kernel, `visuals.jax_render_kernel`, with the same
      frames, faster, for minutes of compiling: benchmarks/results/jax_env_h100.md;
      None: the kernel on a GPU only), `obs_on_device`
      (default False; True returns observations as device arrays, skipping
      their transfer). Both:
      `solver_iterations`, `ls_iterations` for the physics (`models.load`);
      `physics_device` (None: JAX's default device; "cpu": the host CPU, see the
      module docstring; with renderer="jax" the frames are still rendered on
      the default device); `physics_workers` (None or 0: the physics in this
      process; W ≥ 1: in W CPU worker processes, with `physics_device="cpu"`);
      `worker_timeout` (seconds a busy render or physics worker may send no
      heartbeat before it is announced on stderr and replaced, its slice redone;
      None: the `DMCR_WORKER_TIMEOUT` environment variable, else 10).

  Returns:
    A `PixelVectorEnv` or a `JaxPixelVectorEnv` (gymnasium `VectorEnv`s); call
    `reset()` first (its first call, and the first `step`, compile, announced
    on stderr once per shape). `close()` when done is recommended (it frees the
    workers and shared memory at once) but optional: an env left open is closed
    at interpreter exit, also after an exception, Ctrl-C or SIGTERM.

  Raises:
    ValueError: unknown task, factor, camera, renderer, quality or GL backend (the
      message lists the valid ones), a factor that does not apply to the task's
      domain or an empty `vary`, num_envs or workers ≤ 0, a seed outside
      [0, 2**32), a worker_timeout that is not a number > 0, a visual-seed
      count other than 1 or N, an option of the other
      renderer, a range straddling `TRAIN_SEEDS` and `TEST_SEEDS`, ranges mixed
      with fixed seeds, an unknown or inapplicable moving factor, an intensity
      outside [0, 1].
  """
  check_renderer_name(renderer)
  other = _JAX_ONLY if renderer == "pool" else _POOL_ONLY
  wrong = sorted(set(kwargs) & set(other))
  if wrong:
    owner = "jax" if renderer == "pool" else "pool"
    raise ValueError(f"{', '.join(wrong)} apply only to renderer={owner!r}, not "
                     f"renderer={renderer!r}")
  cls = PixelVectorEnv if renderer == "pool" else JaxPixelVectorEnv
  return cls(task, num_envs, visual_seeds, vary, frame_skip, frame_stack, image_size,
             camera, seed, moving=moving, intensity=intensity, **kwargs)
