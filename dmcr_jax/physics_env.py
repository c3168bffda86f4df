"""The JAX half of the pixel env: N envs' physics, frame skip, auto-reset, visual seeds.

Pure functions over a frozen `EnvState`, written for the whole batch: `init`
resets every env, `step` advances every env by one agent step (`frame_skip`
control steps of the `Task`, rewards summed: the paper's action repeat) and
resets the envs whose episode ended on the previous call. That is gymnasium's
NEXT_STEP auto-reset: the call that ends an episode returns its last reward and
`truncated=True`; the env's next call ignores its action, starts a new episode
and returns reward 0. DMC tasks never terminate, they are truncated at the time
limit (1,000 control steps: 500 agent steps at frame skip 2).

Keys: every env carries its own key. A reset splits it into the env's next key,
the dynamics key (initial state, `Task.reset`) and a visual key (the next visual
seed, when seeds are drawn from a `SeedRange` or an `EnvRanges`; a fixed seed
per env ignores it).
So a run is fixed by `init`'s key, and an env's looks never influence its
physics. The host half (`dmcr_jax.env`) renders the pixels.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from dmcr_jax.models.base import State, Task
from dmcr_jax.visuals.levels import EnvRanges, SeedBounds, SeedRange

SeedSource = SeedRange | EnvRanges | SeedBounds | jax.Array
"""A range to draw from, a range per env (static, or as `SeedBounds` arrays), or a
fixed int32 (N,) seed per env."""


def seed_argument(seeds: SeedRange | EnvRanges | jax.Array, num_envs: int
                  ) -> SeedBounds | jax.Array:
  """`seeds` as the traced argument of a jitted `init`/`step`: ranges as
  `SeedBounds`, fixed seeds as int32 (N,). One compilation then serves every
  range (and one every set of fixed seeds) of `num_envs` envs; the draws are
  those of the static `seeds`."""
  if isinstance(seeds, (SeedRange, EnvRanges)):
    return SeedBounds.of(seeds, num_envs)
  return np.asarray(seeds, np.int32)


@struct.dataclass
class EnvState:
  """The state of N envs (every array has a leading axis N).

  Attributes:
    task: the `Task`'s `State` of every env.
    visual_seed: int32 visual seed of every env's current episode.
    key: every env's PRNG key (for its next reset).
    needs_reset: bool, the env's episode ended: the next `step` resets it.
    episode: int32 episodes started so far by the env, minus one (0 in the first).
    episode_step: int32 agent steps taken in the current episode.
    episode_return: float32 sum of rewards in the current episode.
  """
  task: State
  visual_seed: jax.Array
  key: jax.Array
  needs_reset: jax.Array
  episode: jax.Array
  episode_step: jax.Array
  episode_return: jax.Array


def _reset_one(task: Task, seeds: SeedSource, key: jax.Array, index: jax.Array):
  """One env's new episode: (task state, visual seed, next key)."""
  key, k_dyn, k_vis = jax.random.split(key, 3)
  if isinstance(seeds, SeedRange):
    seed = seeds.sample(k_vis)
  elif isinstance(seeds, (EnvRanges, SeedBounds)):
    seed = seeds.sample(k_vis, index)
  else:
    seed = seeds[index]
  return task.reset(k_dyn), seed, key


def _reset_where(task: Task, seeds: SeedSource, es: EnvState, mask: jax.Array) -> EnvState:
  """Resets the envs where `mask` is True (all computed, then selected)."""
  n = mask.shape[0]
  fresh, seed, key = jax.vmap(lambda k, i: _reset_one(task, seeds, k, i))(
      es.key, jnp.arange(n))
  pick = lambda new, old: jnp.where(mask.reshape((n,) + (1,) * (new.ndim - 1)), new, old)
  return es.replace(
      task=jax.tree.map(pick, fresh, es.task),
      visual_seed=jnp.where(mask, seed, es.visual_seed),
      key=jnp.where(mask, key, es.key),
      needs_reset=jnp.where(mask, False, es.needs_reset),
      episode=jnp.where(mask, es.episode + 1, es.episode),
      episode_step=jnp.where(mask, 0, es.episode_step),
      episode_return=jnp.where(mask, 0.0, es.episode_return))


def init(task: Task, seeds: SeedSource, key: jax.Array, num_envs: int) -> EnvState:
  """Starts N envs: every env gets its own key and a first episode.

  `key`: one key (split into the N envs' keys) or N keys, shape (N,) (env i's).
  """
  n = int(num_envs)
  keys = key if key.shape == (n,) else jax.random.split(key, n)
  state, seed, keys = jax.vmap(lambda k, i: _reset_one(task, seeds, k, i))(
      keys, jnp.arange(n))
  return EnvState(task=state, visual_seed=seed, key=keys,
                  needs_reset=jnp.zeros((n,), bool), episode=jnp.zeros((n,), jnp.int32),
                  episode_step=jnp.zeros((n,), jnp.int32),
                  episode_return=jnp.zeros((n,), jnp.float32))


def skip_step(task: Task, state: State, action: jax.Array, frame_skip: int):
  """`frame_skip` control steps of one env with one action; (state, summed reward).

  Steps after the time limit are skipped (their reward is not counted), so a
  frame skip that does not divide the episode length ends it on time. (When it
  divides it, as the paper's 2, 4 and 8 divide 1,000, the time limit always
  falls on the last step of a frame skip and no step needs skipping.)
  """
  masked = task.time_limit % frame_skip != 0

  def body(_, carry):
    s, total = carry
    nxt = task.step(s, action)
    if not masked:
      return nxt, total + nxt.reward
    keep = s.done
    s = jax.tree.map(lambda old, new: jnp.where(keep, old, new), s, nxt)
    return s, total + jnp.where(keep, 0.0, nxt.reward)

  return jax.lax.fori_loop(0, frame_skip, body, (state, jnp.zeros((), jnp.float32)))


def step(task: Task, seeds: SeedSource, frame_skip: int, es: EnvState,
         actions: jax.Array) -> tuple[EnvState, jax.Array, jax.Array]:
  """One agent step of N envs (NEXT_STEP auto-reset, see the module docstring).

  Args:
    task: the `Task`.
    seeds: a `SeedSource`: the range(s) to draw each new episode's visual seed
      from, or fixed int32 (N,) seeds.
    frame_skip: control steps per agent step.
    es: the current `EnvState`.
    actions: float (N, action_size).

  Returns:
    (next EnvState, reward float32 (N,), truncated bool (N,)).
  """
  stepped, reward = jax.vmap(lambda s, a: skip_step(task, s, a, frame_skip))(es.task, actions)
  resetting = es.needs_reset
  moved = es.replace(task=stepped, episode_step=es.episode_step + 1,
                     episode_return=es.episode_return + reward)
  # Resets are rare (every few hundred steps): compute them only when needed.
  nxt = jax.lax.cond(jnp.any(resetting),
                     lambda e: _reset_where(task, seeds, e, resetting),
                     lambda e: e, moved)
  reward = jnp.where(resetting, 0.0, reward)
  truncated = jnp.where(resetting, False, stepped.done)
  return nxt.replace(needs_reset=truncated), reward, truncated

