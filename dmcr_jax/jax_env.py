"""N DMCR pixel envs as pure JAX functions: physics, ray-cast frames and frame stacks in one call.

The functional core of `dmcr_jax.make(..., renderer="jax")`. A `PixelEnv` (a
frozen pytree: the task, the domain's `Scene` with its texture bank on device,
the table of looks the visual seeds select, and static sizes) offers

* `env.reset(key) -> PixelState` — every env's first episode and first stack;
* `env.step(state, actions) -> (PixelState, reward, truncated)` — one agent step
  of all N envs: `physics_env.step` (frame skip, rewards summed, NEXT_STEP
  auto-reset, next visual seeds), the looks of the envs that reset, one
  `jax_render.render_batch` of the post-step body poses and task model variables
  (targets), and the frame stacks;
* `env.observe(state, physics, resetting) -> PixelState` — the render half of
  `step` alone: the frames and stacks of a stepped physics state (for physics
  stepped elsewhere, e.g. on the host CPU);
* `env.observe_inputs(state, inputs, resetting) -> PixelState` — the same from
  `env.render_inputs(physics)`, the few arrays the frames read (body poses, task
  model variables, visual seeds): what a physics stepped on another device
  needs to move to this one;
* `env.start(physics, look) -> PixelState` — fresh stacks for a given physics
  state (reset and `set_state` use it).

All are pure and jittable (pass the `PixelEnv` as an argument, not a closure: its
texture bank is ~100 MB), so a training loop can `lax.scan` them
(`train/device_loop.py`). Semantics are those of the pool env (`dmcr_jax.env`):
gymnasium's NEXT_STEP auto-reset (the step that ends an episode returns its last
frame, reward and `truncated=True`; the env's next step ignores its action and
returns the new episode's first frame with reward 0), stacks of uint8
(N, H, W, 3·frame_stack) frames, oldest first, a reset env's stack being its
first frame repeated.

Visual seeds (`make_env(visual_seeds=...)`): a look is made on the device from
its seed alone (`jax_render_scene.LookMaker`: the seed's `VisualParams` and
what `render_model.prepare` derives from them, in float32), so the same seed
shows the same look in every env, range and batch. Fixed seeds (one per env)
give a table of N looks, row i for env i, made once. A few-shot `SeedRange`,
or an `EnvRanges` (a range per env), keeps no table: an env that resets draws
its seed (`physics_env`) and its look is made then, so a range of any size
costs neither host memory nor host time.

Moving looks (`make_env(moving=..., intensity=...)`, `visuals.moving`): the look
of every frame is made from the env's seed and its episode step
(`LookMaker(seeds, step)`, i.e. `moving.look_at` inside the jitted step), so the
table of fixed seeds is not read and no state beyond the physics' episode step is
carried.

The frames are the JAX ray caster's (`dmcr_jax.visuals.jax_render`), close to,
not equal to, MuJoCo's (see that module's docstring for what differs).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from dmcr_jax import physics_env
from dmcr_jax.models.base import Task
from dmcr_jax.visuals import jax_render as JR
from dmcr_jax.visuals import jax_render_scene as JS
from dmcr_jax.visuals import render_model as rmod
from dmcr_jax.visuals.levels import EnvRanges, SeedBounds, SeedRange

RENDER_CHUNK = 256
"""Default envs per vmapped render chunk above which `render_batch` maps over chunks
(bounds memory and keeps a chunk's arrays in cache; chunk sizes compared in the rows of
benchmarks/results/jax_render_h100.jsonl)."""


@struct.dataclass
class PixelState:
  """The state of N pixel envs (leading axis N everywhere).

  Attributes:
    physics: the `physics_env.EnvState` (task states, visual seeds, keys,
      `needs_reset`, and the episode counters `episode`, `episode_step`,
      `episode_return`), or None after `observe_inputs` (physics kept elsewhere).
    look: the `DeviceLook` of every env's current episode.
    obs: uint8 (N, H, W, 3·frame_stack) frame stacks, oldest frame first.
  """
  physics: physics_env.EnvState
  look: JS.DeviceLook
  obs: jax.Array


@struct.dataclass
class RenderInputs:
  """What the frames of N envs read of their physics (`PixelEnv.render_inputs`).

  Attributes:
    poses: the bodies' `BodyPoses` (positions, rotations, subtree centres of mass).
    variables: the task's model variables the scene draws (e.g. a target's
      position), name → (N, …) array, or None when it draws none.
    visual_seed: int32 (N,), each env's visual seed (drawn seeds pick looks).
    episode_step: int32 (N,), each env's agent step in its episode (moving looks).
  """
  poses: JS.BodyPoses
  variables: dict | None
  visual_seed: jax.Array
  episode_step: jax.Array


def physics_render_inputs(physics: physics_env.EnvState, variables: tuple[str, ...]
                          ) -> RenderInputs:
  """The `RenderInputs` of `physics`, with the named task model variables.

  Reads nothing of a `PixelEnv`, so it runs where `physics` is (e.g. the host
  CPU) and only its result moves to the render device.
  """
  info = physics.task.info
  return RenderInputs(poses=JS.poses(physics.task.data),
                      variables={k: info[k] for k in variables} or None,
                      visual_seed=physics.visual_seed, episode_step=physics.episode_step)


@struct.dataclass
class PixelEnv:
  """N envs of one task, rendered by the JAX ray caster (build with `make_env`).

  Attributes:
    scene: the domain's `Scene` (objects, lights, camera, texture bank).
    maker: the `LookMaker` (seeds → looks on the device, for the env's `vary`).
    looks: `DeviceLook` table of fixed seeds, (N, …) row i for env i; None
      when the seeds are drawn.
    fixed_seeds: int32 (N,) visual seeds (fixed seeds) or None (drawn).
    seed_bounds: the few-shot ranges the seeds are drawn from, as `SeedBounds`
      (traced: one compilation serves any ranges of N envs), or None (fixed seeds).
    task: static; the `Task`.
    num_envs, frame_skip, frame_stack, height, width: static sizes.
    shadows, reflection: static; the ray caster's options (`jax_render.render`).
    render_chunk: static; envs per render chunk (None: all at once).
    render_kernel: static; render in one fused GPU kernel
      (`jax_render.render_batch(kernel=True)`; chunks do not apply); resolved by
      `make_env` (False by default: through XLA).
  """
  scene: JS.Scene
  maker: JS.LookMaker
  looks: JS.DeviceLook | None
  fixed_seeds: jax.Array | None
  seed_bounds: SeedBounds | None
  task: Task = struct.field(pytree_node=False)
  num_envs: int = struct.field(pytree_node=False)
  frame_skip: int = struct.field(pytree_node=False)
  frame_stack: int = struct.field(pytree_node=False)
  height: int = struct.field(pytree_node=False)
  width: int = struct.field(pytree_node=False)
  shadows: bool = struct.field(pytree_node=False, default=True)
  reflection: bool = struct.field(pytree_node=False, default=True)
  render_chunk: int | None = struct.field(pytree_node=False, default=None)
  render_kernel: bool = struct.field(pytree_node=False, default=False)

  @property
  def _seeds(self) -> physics_env.SeedSource:
    return self.seed_bounds if self.seed_bounds is not None else self.fixed_seeds

  def looks_of(self, visual_seed: jax.Array, episode_step: jax.Array | None = None
               ) -> JS.DeviceLook:
    """The looks of envs showing `visual_seed` (int32 (N,), drawn by this env) at
    their `episode_step` (int32 (N,); read when the looks move, None: step 0).

    Moving looks: made from the seed and step (`maker`). Else fixed seeds: the
    table (row i is env i's seed); drawn seeds: made from `visual_seed` (`maker`).
    """
    if self.maker.moves:
      return self.maker(visual_seed, episode_step)
    if self.seed_bounds is None:
      return self.looks
    return self.maker(visual_seed)

  @property
  def drawn_variables(self) -> tuple[str, ...]:
    """The task's model variables the scene draws (static)."""
    keys = {k for k, _, _ in self.scene.variables}
    return tuple(k for k in self.task.model_variable_ids if k in keys)

  def render_inputs(self, physics: physics_env.EnvState) -> RenderInputs:
    """The arrays of `physics` that its frames depend on (`physics_render_inputs`)."""
    return physics_render_inputs(physics, self.drawn_variables)

  def draw(self, inputs: RenderInputs, look: JS.DeviceLook) -> jax.Array:
    """One frame per env, uint8 (N, H, W, 3), of `render_inputs` under `look`."""
    return JR.render_batch(self.scene, inputs.poses, look, inputs.variables,
                           chunk=self.render_chunk, kernel=self.render_kernel,
                           height=self.height, width=self.width,
                           shadows=self.shadows, reflection=self.reflection)

  def render(self, physics: physics_env.EnvState, look: JS.DeviceLook) -> jax.Array:
    """One frame per env, uint8 (N, H, W, 3), of the physics state under `look`."""
    return self.draw(self.render_inputs(physics), look)

  def start(self, physics: physics_env.EnvState, look: JS.DeviceLook) -> PixelState:
    """Fresh frame stacks (the first frame repeated) for a physics state.

    Args:
      physics: an `EnvState` of N envs.
      look: their `DeviceLook` (leading axis N); with moving looks, ignored: the
        look at each env's seed and episode step is made.

    Returns:
      The `PixelState`.
    """
    if self.maker.moves:
      look = self.looks_of(physics.visual_seed, physics.episode_step)
    frame = self.render(physics, look)
    # A copy, so the state never shares buffers with `self.looks` (a jitted
    # identity would forward them, and a donated state would delete the table).
    look = jax.tree.map(jnp.copy, look)
    return PixelState(physics=physics, look=look,
                      obs=jnp.tile(frame, (1, 1, 1, self.frame_stack)))

  def reset(self, key: jax.Array) -> PixelState:
    """Starts every env (as `physics_env.init`, then `start`).

    Args:
      key: a `jax.random` key (the run's dynamics key; and few-shot seed draws).

    Returns:
      The `PixelState` of N new episodes.
    """
    physics = physics_env.init(self.task, self._seeds, key, self.num_envs)
    return self.start(physics, self.looks_of(physics.visual_seed))

  def step(self, state: PixelState, actions: jax.Array
           ) -> tuple[PixelState, jax.Array, jax.Array]:
    """One agent step of N envs (NEXT_STEP auto-reset, see the module docstring).

    Args:
      state: the current `PixelState`.
      actions: float (N, action_size) in the task's bounds (clipped; NaN → 0).

    Returns:
      (next PixelState, reward float32 (N,), truncated bool (N,)).
    """
    resetting = state.physics.needs_reset
    physics, reward, truncated = physics_env.step(self.task, self._seeds, self.frame_skip,
                                                  state.physics, actions)
    return self.observe(state, physics, resetting), reward, truncated

  def observe(self, state: PixelState, physics: physics_env.EnvState,
              resetting: jax.Array) -> PixelState:
    """The render half of `step`: the new frames and stacks after `physics`.

    Args:
      state: the `PixelState` before the step.
      physics: the `EnvState` after `physics_env.step` of `state.physics`.
      resetting: bool (N,), the envs that began a new episode in that step
        (`state.physics.needs_reset`).

    Returns:
      The next `PixelState`.
    """
    return self.observe_inputs(state, self.render_inputs(physics),
                               resetting).replace(physics=physics)

  def observe_inputs(self, state: PixelState, inputs: RenderInputs,
                     resetting: jax.Array) -> PixelState:
    """`observe` from the stepped physics' `render_inputs` alone.

    Args:
      state: the `PixelState` before the step (its `physics` is not read).
      inputs: `render_inputs` of the `EnvState` after the step.
      resetting: as for `observe`.

    Returns:
      The next `PixelState`, with `physics` None (the physics lives elsewhere).
    """
    look = state.look
    if self.maker.moves:                # every frame its own look
      look = self.looks_of(inputs.visual_seed, inputs.episode_step)
    elif self.seed_bounds is not None:  # fixed seeds keep their look across resets
      pick = lambda new, old: jnp.where(
          resetting.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)
      # New looks are made only in steps where some env resets (rare).
      look = jax.lax.cond(
          jnp.any(resetting),
          lambda: jax.tree.map(pick, self.looks_of(inputs.visual_seed), look),
          lambda: look)
    frame = self.draw(inputs, look)
    shifted = jnp.concatenate([state.obs[..., 3:], frame], axis=-1)
    obs = jnp.where(resetting[:, None, None, None],
                    jnp.tile(frame, (1, 1, 1, self.frame_stack)), shifted)
    return PixelState(physics=None, look=look, obs=obs)


def host_looks(scene: JS.Scene, rm: rmod.RenderModel, seeds, vary) -> JS.DeviceLook:
  """The `DeviceLook` of visual seeds made on the host (`sample`, then `prepare` in
  float64, then `device_looks`): the reference `make_looks` is checked against.

  Args:
    scene: the domain's scene.
    rm: its render model.
    seeds: int visual seeds (S,).
    vary: the factors the seeds change.

  Returns:
    `DeviceLook` with leading axis S.
  """
  seeds = np.asarray(seeds, np.int32)
  return JS.device_looks(scene, rm, rmod.prepare(rm, rm.sample(seeds, vary=vary)))


@functools.lru_cache(maxsize=8)
def scene_of(domain: str, camera: int | str = 0) -> tuple[rmod.RenderModel, JS.Scene]:
  """The domain's render model and `Scene` for `camera` (built once per process)."""
  rm = rmod.build_render_model(domain)
  return rm, JS.build_scene(rm, camera)


def make_env(task: Task, num_envs: int, seeds: SeedRange | EnvRanges | np.ndarray, vary,
             frame_skip: int, frame_stack: int, height: int, width: int, *,
             camera: int | str = 0, shadows: bool = True, reflection: bool = True,
             render_chunk: int | None = None,
             render_kernel: bool | None = False, moving: tuple[str, ...] = (),
             intensity: float = 0.0) -> PixelEnv:
  """Builds a `PixelEnv` (host work: the scene once per domain, the looks per call).

  Args:
    task: the `Task` (`models.load`).
    num_envs: N.
    seeds: a `SeedRange` (few-shot, any size), an `EnvRanges` of N ranges (one
      per env) or fixed int32 (N,) visual seeds.
    vary: the factors the visual seeds change.
    frame_skip, frame_stack, height, width: as for `dmcr_jax.make`.
    camera: camera id or name (camera 0 is the one the looks move).
    shadows, reflection: the ray caster's options (default: MuJoCo's picture).
    render_chunk: envs per render chunk; None = all at once up to `RENDER_CHUNK`
      envs, `RENDER_CHUNK` above.
    render_kernel: render in one fused GPU kernel (`jax_render_kernel`; same
      frames, faster, but minutes of compiling: benchmarks/results/jax_env_h100.md);
      None: on a GPU only (`jax_render.use_kernel`); False (default): through XLA.
    moving, intensity: the factors that move within an episode and how far, as
      `visuals.moving.check_moving` returns them (default: static looks).

  Returns:
    The `PixelEnv`.

  Raises:
    ValueError: fixed seeds not (N,), an `EnvRanges` not of N ranges, or
      `render_kernel` without a GPU.
    NotImplementedError: a scene the ray caster cannot draw (`build_scene`).
  """
  rm, scene = scene_of(task.spec.domain, camera)
  maker = JS.look_maker(scene, rm, vary, moving, intensity)
  drawn = isinstance(seeds, (SeedRange, EnvRanges))
  if isinstance(seeds, EnvRanges) and len(seeds) != num_envs:
    raise ValueError(f"EnvRanges must hold one range per env ({num_envs}), got {len(seeds)}")
  table = fixed = bounds = None
  if drawn:
    bounds = jax.tree.map(jnp.asarray, SeedBounds.of(seeds, num_envs))
  else:
    fixed = np.asarray(seeds, np.int32)
    if fixed.shape != (num_envs,):
      raise ValueError(f"fixed visual seeds must have shape ({num_envs},), got {fixed.shape}")
    fixed = jnp.asarray(fixed)
    table = make_looks(maker, fixed)
  render_kernel = JR.use_kernel(render_kernel)
  if render_chunk is None and num_envs > RENDER_CHUNK:
    render_chunk = RENDER_CHUNK
  return PixelEnv(scene=scene, maker=maker, looks=table, fixed_seeds=fixed,
                  seed_bounds=bounds, task=task,
                  num_envs=int(num_envs), frame_skip=int(frame_skip),
                  frame_stack=int(frame_stack), height=int(height), width=int(width),
                  shadows=bool(shadows), reflection=bool(reflection),
                  render_chunk=render_chunk, render_kernel=render_kernel)


# Jitted entry points (the env is an argument: its arrays are not baked in as constants).
make_looks = jax.jit(lambda maker, seeds: maker(seeds))
"""The `DeviceLook`s of int32 (N,) visual seeds on the device (`LookMaker`)."""
make_looks_at = jax.jit(lambda maker, seeds, steps: maker(seeds, steps))
"""The `DeviceLook`s of int32 (N,) visual seeds at int32 (N,) episode steps (moving looks)."""
reset = jax.jit(lambda env, key: env.reset(key))
start = jax.jit(lambda env, physics, look: env.start(physics, look))
step = jax.jit(lambda env, state, actions: env.step(state, actions))
observe = jax.jit(lambda env, state, physics, resetting: env.observe(state, physics, resetting))
render_inputs = jax.jit(physics_render_inputs, static_argnums=(1,))
"""`physics_render_inputs`, jitted (on the physics' device)."""
observe_inputs = jax.jit(lambda env, state, inputs, resetting:
                         env.observe_inputs(state, inputs, resetting))
step_donated = jax.jit(lambda env, state, actions: env.step(state, actions),
                       donate_argnums=(1,))
