"""The ray caster's protocol block: one jitted program per block of envs on the device.

`_ray_block` makes each env's look from its visual seed and factor mask, resets the
physics from its reset seed and `lax.scan`s the episode with the policy inside:
each scan step draws the frames (`jax_env.PixelEnv.draw`), stacks them, asks the
policy (`protocol_policy.policy_actions`) and steps the physics (`episode_step`,
without the reset branch: no env resets inside a block). `_ray_block_jit` is that
program jitted (one compilation per policy and sizes); `_pixel_env` the
`jax_env.PixelEnv` without looks it renders with; `render_chunk` and
`render_padding` keep the render one vmapped chunk program of one size. Moving
conditions share the program: each env moves its own factors at its own intensity
(`step_looks`), so one compilation serves every static and moving condition.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from dmcr_jax.protocol_policy import env_actions, policy_actions, worst_action


def block_looks(maker, masks: jax.Array, seeds: jax.Array):
  """Each env's `DeviceLook`: its visual seed under its own factor mask.

  Args:
    maker: the domain's `jax_render_scene.LookMaker` (its own mask is replaced).
    masks: bool (N, 7) factor masks (`params.factor_mask`).
    seeds: int32 (N,) visual seeds.

  Returns:
    The `DeviceLook` of the N envs (leading axis N).
  """
  looks = jax.vmap(lambda m, s: maker.replace(mask=m)(s[None]))(masks, seeds)
  return jax.tree.map(lambda x: x[:, 0], looks)


def block_params(maker, masks: jax.Array, seeds: jax.Array):
  """Each env's static `VisualParams`: its visual seed under its own factor mask
  (what `block_looks` makes its looks from; moving looks move them each step).

  Args: as for `block_looks`.

  Returns:
    The `VisualParams` of the N envs (leading axis N).
  """
  params = jax.vmap(lambda m, s: maker.replace(mask=m).params(s[None]))(masks, seeds)
  return jax.tree.map(lambda x: x[:, 0], params)


def step_looks(maker, params, t: jax.Array, moving: tuple[str, ...], motion):
  """Each env's `DeviceLook` at agent step `t` of its episode, its own factors moving
  (`visuals.moving.look_at_each`): what `dmcr_jax.make(..., moving=F, intensity=I)`
  draws at that step for an env with F and I.

  Args:
    maker: the domain's `LookMaker`.
    params: the N envs' static `VisualParams` (`block_params`).
    t: int32 scalar, the episode step.
    moving: static; the factors any env moves (`Plan.moving`).
    motion: (bool (N, len(moving)) which of them each env moves, float32 (N,)
      each env's intensity).

  Returns:
    The `DeviceLook` of the N envs.
  """
  from dmcr_jax.visuals.moving import look_at_each
  on, intensity = motion
  return maker.device_look(look_at_each(params, t, moving, on, intensity,
                                         num_backgrounds=maker.num_backgrounds))


def episode_step(task, frame_skip: int, physics, actions: jax.Array):
  """One agent step of N envs inside an episode: `physics_env.step` where no env
  resets (no env's previous step ended its episode), without its reset branch.

  Args:
    task: the `Task`.
    frame_skip: control steps per agent step.
    physics: the `physics_env.EnvState`, no env with `needs_reset` set.
    actions: float (N, A) in the task's bounds.

  Returns:
    The next `EnvState` (its `needs_reset` marks the envs whose episode ended).
  """
  from dmcr_jax import physics_env
  stepped, reward = jax.vmap(lambda s, a: physics_env.skip_step(task, s, a, frame_skip))(
      physics.task, actions)
  return physics.replace(task=stepped, episode_step=physics.episode_step + 1,
                         episode_return=physics.episode_return + reward,
                         needs_reset=stepped.done)


def render_chunk(num_envs: int) -> int | None:
  """Envs per render chunk for a block of `num_envs` envs: the fewest chunks of
  at most `jax_env.RENDER_CHUNK` envs, all of one size (None: one chunk)."""
  from dmcr_jax import jax_env
  if num_envs <= jax_env.RENDER_CHUNK:
    return None
  return -(-num_envs // -(-num_envs // jax_env.RENDER_CHUNK))


def render_padding(penv) -> int:
  """Envs the block's frames are padded with (copies of env 0) to a whole number
  of `penv.render_chunk`-env chunks, so the render is one vmapped chunk program
  (`lax.map` renders a remainder with a second one); 0 for the fused kernel."""
  chunk = penv.render_chunk
  if penv.render_kernel or not chunk or chunk >= penv.num_envs:
    return 0
  return -penv.num_envs % chunk


def _pad(tree, extra: int):
  """Every leaf with `extra` copies of its row 0 appended."""
  if not extra:
    return tree
  return jax.tree.map(lambda x: jnp.concatenate(
      [x, jnp.broadcast_to(x[:1], (extra,) + x.shape[1:])]), tree)


def _ray_block(penv, params, seeds, masks, resets, index, key, motion=None, *, policy,
               agents, steps, moving=()):
  """One block of the ray caster's pass: looks, reset, `steps` agent steps.

  Each scan step renders the envs' frames, stacks them, asks the policy and
  steps the physics (`episode_step`: `steps` is the episode length, so no env
  resets inside the block); a frame is rendered once, at one place in the
  program. The stacks and returns are those of `jax_env.PixelEnv` stepped from
  `start` (the first stack is the first frame repeated). Static looks (`moving`
  empty) are made once per block; with `moving`, each step's looks are made from
  the envs' static looks and the step (`step_looks`), each env moving its own
  factors (none: its static look).

  Args: the block's envs' int32 visual seeds (N,), bool factor masks (N, 7),
  uint32 reset seeds (N,), int32 episode indices (N,); `penv` a `PixelEnv` of N
  envs without looks, its frames padded by `render_padding`; `key` the policy key;
  `motion` and `moving` as for `step_looks` (None and (): no env moves).

  Returns:
    (episode returns float32 (N,), `worst_action` float32 (K,) over the episode).
  """
  from dmcr_jax import physics_env
  n, k = penv.num_envs, agents or 1
  extra = render_padding(penv)
  if moving:
    static = block_params(penv.maker, masks, seeds)
    looks_at = lambda t: _pad(step_looks(penv.maker, static, t, moving, motion), extra)
  else:
    looks = _pad(block_looks(penv.maker, masks, seeds), extra)
    looks_at = lambda t: looks
  physics = physics_env.init(penv.task, seeds, jax.vmap(jax.random.key)(resets), n)
  low, high = penv.task.action_low, penv.task.action_high

  def body(carry, t):
    physics, obs, worst = carry
    frame = penv.draw(_pad(penv.render_inputs(physics), extra), looks_at(t))[:n]
    obs = jnp.where(t == 0, jnp.tile(frame, (1, 1, 1, penv.frame_stack)),
                    jnp.concatenate([obs[..., 3:], frame], axis=-1))
    actions = policy_actions(policy, params, obs, index, t, key, agents)
    worst = jnp.maximum(worst, worst_action(actions, k))  # NaN stays NaN
    physics = episode_step(penv.task, penv.frame_skip, physics,
                           env_actions(actions, low, high))
    return (physics, obs, worst), None

  obs = jnp.zeros((n, penv.height, penv.width, 3 * penv.frame_stack), jnp.uint8)
  init = (physics, obs, jnp.zeros((k,), jnp.float32))
  (physics, _, worst), _ = jax.lax.scan(body, init, jnp.arange(steps, dtype=jnp.int32))
  return physics.episode_return, worst


@functools.cache
def _ray_block_jit():
  from dmcr_jax.models.base import physics_jit
  return physics_jit(_ray_block, static_argnames=("policy", "agents", "steps", "moving"))


@functools.lru_cache(maxsize=8)
def _pixel_env(task: str, num_envs: int, frame_skip: int, frame_stack: int, height: int,
               width: int, render: tuple):
  """A `jax_env.PixelEnv` of `num_envs` envs without looks (the block program makes
  them), built once per sizes."""
  from dmcr_jax import jax_env, models
  from dmcr_jax.visuals import jax_render as JR
  from dmcr_jax.visuals import jax_render_scene as JS
  opts = dict(render)
  t = models.load(task)
  rm, scene = jax_env.scene_of(t.spec.domain, opts.get("camera", 0))
  chunk = opts.get("render_chunk")
  if chunk is None:
    chunk = render_chunk(num_envs)
  return jax_env.PixelEnv(
      scene=scene, maker=JS.look_maker(scene, rm, "all"), looks=None, fixed_seeds=None,
      seed_bounds=None, task=t, num_envs=int(num_envs), frame_skip=int(frame_skip),
      frame_stack=int(frame_stack), height=int(height), width=int(width),
      shadows=bool(opts.get("shadows", True)), reflection=bool(opts.get("reflection", True)),
      render_chunk=chunk, render_kernel=JR.use_kernel(opts.get("render_kernel", False)))
