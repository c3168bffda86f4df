"""A functional replay buffer on the JAX device for pixel SAC with frame stacks.

Each of the N envs of a `dmcr_jax.make` batch owns a ring of T = capacity // N
rows; a row is one agent step: the newest frame of the observation (stored once:
no stacks, no second copy for o′), the action taken from it, the reward that
followed and whether the frame starts an episode. Stacks are rebuilt when a batch
is sampled, exactly as the env builds them (oldest frame first; frames before an
episode start are replaced by the episode's first frame), so o and o′ share their
frames (DESIGN.md style rule 6). Three pure functions: `init`, `add` (one agent
step of all N envs, jittable; donate the buffer) and `sample` (jittable, uniform
over the valid transitions, see `valid_mask`). Every stored transition
bootstraps (discount 1): DMC episodes are only truncated, never terminated.

Memory: N·T·(H·W·C + 4·A + 4 + 1) bytes (frames uint8, actions and rewards
float32, start flags bool), i.e. about capacity·H·W·C bytes of frames; e.g.
capacity 100,000 at 84×84×3 holds 100,000 × 21,168 B ≈ 2.1 GB of frames plus
100,000 × (4·6 + 5) B ≈ 2.9 MB for a 6-dim action. `sample` also builds an
(N, T) mask and its running sum per call (≈ 5·N·T bytes of temporaries).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from dmcr_jax.checks import positive_int


class Batch(NamedTuple):
  """A batch of B transitions (o, a, r, γ, o′), as the SAC update consumes it.

  Attributes:
    obs: uint8 (B, H, W, C·frame_stack), channels-last, oldest frame first.
    action: float32 (B, A), the action taken from ``obs``.
    reward: float32 (B,), the reward the env returned for it.
    discount: float32 (B,), 1 for every sampled transition (0 only for the
      filler rows `sample` returns when no transition is valid).
    next_obs: uint8 (B, H, W, C·frame_stack), the observation that followed.
  """
  obs: jax.Array
  action: jax.Array
  reward: jax.Array
  discount: jax.Array
  next_obs: jax.Array


@struct.dataclass
class ReplayBuffer:
  """Per-env rings of agent steps; a frozen pytree (update with `add`).

  Row t of env n (one slot of its ring) holds the newest frame of an
  observation, the action taken from it, the reward that followed and whether
  the frame starts an episode. Each env's ring has its own write position and
  count: the k-th row `add` writes for env n goes to its slot k mod T.

  Attributes:
    frames: uint8 (N, T, H, W, C), each frame stored once.
    action: float32 (N, T, A), the action taken at that frame.
    reward: float32 (N, T), the reward that followed it.
    first: bool (N, T), the frame is an episode's first observation.
    pos: int32 (N,), the slot each env's next row goes to.
    count: int32 (N,), rows written per env, at most T.
    frame_stack: static; frames per observation.
  """
  frames: jax.Array
  action: jax.Array
  reward: jax.Array
  first: jax.Array
  pos: jax.Array
  count: jax.Array
  frame_stack: int = struct.field(pytree_node=False, default=1)

  @property
  def num_envs(self) -> int:
    """N, the number of envs (static)."""
    return self.frames.shape[0]

  @property
  def ring_size(self) -> int:
    """T, the rows each env's ring holds (static)."""
    return self.frames.shape[1]


def init(capacity: int, num_envs: int, frame_shape: tuple[int, int, int],
         action_size: int, frame_stack: int) -> ReplayBuffer:
  """An empty buffer, allocated on the default device.

  Args:
    capacity: total rows (agent steps) over all envs; each env's ring holds
      T = capacity // num_envs of them (the remainder is unused).
    num_envs: N, the envs `add` receives one step of per call.
    frame_shape: (H, W, C) of ONE frame, e.g. (84, 84, 3).
    action_size: A, the action dimension.
    frame_stack: k, frames per observation (the env's `frame_stack`).

  Returns:
    A `ReplayBuffer` with nothing written.

  Raises:
    ValueError: a size is not a positive int, `frame_shape` is not three of
      them, or T < frame_stack + 1 (a ring must hold a stack and its next frame).
  """
  capacity = positive_int("capacity", capacity)
  n = positive_int("num_envs", num_envs)
  a = positive_int("action_size", action_size)
  k = positive_int("frame_stack", frame_stack)
  try:
    shape = tuple(frame_shape)
  except TypeError:
    shape = ()
  if len(shape) != 3:
    raise ValueError(f"frame_shape must be (H, W, C), got {frame_shape!r}")
  shape = tuple(positive_int(f"frame_shape[{i}]", s) for i, s in enumerate(shape))
  t = capacity // n
  if t < k + 1:
    raise ValueError(
        f"capacity {capacity} gives each of the {n} envs a ring of {t} rows; it needs "
        f"at least frame_stack + 1 = {k + 1}, so capacity >= num_envs·(frame_stack+1) "
        f"= {n * (k + 1)}")
  return ReplayBuffer(
      frames=jnp.zeros((n, t) + shape, jnp.uint8),
      action=jnp.zeros((n, t, a), jnp.float32),
      reward=jnp.zeros((n, t), jnp.float32),
      first=jnp.zeros((n, t), bool),
      pos=jnp.zeros((n,), jnp.int32),
      count=jnp.zeros((n,), jnp.int32),
      frame_stack=k)


def _check(name: str, x, shape: tuple[int, ...]) -> None:
  if tuple(jnp.shape(x)) != shape:
    raise ValueError(f"{name} must have shape {shape}, got {tuple(jnp.shape(x))}")


def add(buffer: ReplayBuffer, frame: jax.Array, first: jax.Array, action: jax.Array,
        reward: jax.Array) -> ReplayBuffer:
  """Appends one agent step of every env (jittable; donate `buffer`).

  Call it after each ``env.step(action)`` with the PREVIOUS observation's data:
  ``add(buf, obs[..., -C:], info["episode_step"] == 0, action, reward)``. The
  step after a truncation (NEXT_STEP auto-reset: its action is ignored, its
  reward is 0) is stored like any other and is never sampled, because the frame
  that follows it starts an episode.

  Args:
    buffer: the buffer.
    frame: uint8 (N, H, W, C), the newest frame of each env's observation.
    first: bool (N,), the observation is an episode's first (its stack is that
      frame repeated).
    action: (N, A), the action taken from the observation (stored as float32).
    reward: (N,), the reward the env returned for it (stored as float32).

  Returns:
    The buffer with each env's step written at its `pos`, overwriting its oldest
    row once its ring is full.

  Raises:
    ValueError/TypeError (at trace time): wrong shapes or a frame not uint8.
  """
  n, t, h, w, c = buffer.frames.shape
  _check("frame", frame, (n, h, w, c))
  _check("first", first, (n,))
  _check("action", action, (n, buffer.action.shape[-1]))
  _check("reward", reward, (n,))
  if jnp.result_type(frame) != jnp.uint8:
    raise TypeError(f"frame must be uint8, got {jnp.result_type(frame)}")
  rows, pos = jnp.arange(n), buffer.pos
  return buffer.replace(
      frames=buffer.frames.at[rows, pos].set(frame),
      action=buffer.action.at[rows, pos].set(jnp.asarray(action, jnp.float32)),
      reward=buffer.reward.at[rows, pos].set(jnp.asarray(reward, jnp.float32)),
      first=buffer.first.at[rows, pos].set(jnp.asarray(first, bool)),
      pos=(pos + 1) % t,
      count=jnp.minimum(buffer.count + 1, t))


def valid_mask(buffer: ReplayBuffer) -> jax.Array:
  """Which rows start a transition `sample` may return (jittable).

  Row t (logical index j = rows since the oldest stored one) is valid iff
  1. row t+1 has been written (j + 1 < count);
  2. frame t+1 does not start an episode (no o′ across a boundary; this also
     excludes the NEXT_STEP reset step, whose o′ is the new episode's start);
  3. every frame of o_t's stack is still stored: j >= k-1, or a stored episode start
     lies within rows j-k+2 … j (the frames before it are not needed).
  o′'s stack is then stored too: it is o_t's shifted by one row.

  Args:
    buffer: the buffer.

  Returns:
    bool (N, T), indexed by ring slot.
  """
  t, k = buffer.ring_size, buffer.frame_stack
  oldest = (buffer.pos - buffer.count) % t          # (N,)
  j = (jnp.arange(t)[None] - oldest[:, None]) % t   # (N, T) logical index per slot
  next_first = jnp.roll(buffer.first, -1, axis=1)   # slot s -> first[s+1]
  ok = (j + 1 < buffer.count[:, None]) & ~next_first
  stored = j >= k - 1
  for d in range(k - 1):  # an episode start at row j-d, itself stored
    stored |= jnp.roll(buffer.first, d, axis=1) & (j >= d)
  return ok & stored


def num_valid(buffer: ReplayBuffer) -> jax.Array:
  """The number of transitions `sample` draws from (int32 scalar; jittable).

  Check it on the host before the first sample, e.g. ``int(num_valid(buf)) > 0``
  (`sample` cannot raise inside jit).
  """
  return jnp.sum(valid_mask(buffer), dtype=jnp.int32)


def sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> Batch:
  """Draws `batch_size` valid transitions uniformly, with replacement (jittable).

  Every valid transition (see `valid_mask`) of every env is equally likely:
  an integer r ~ U{0, …, V−1} picks the r-th valid row through a running count
  of the mask (exact; no float probabilities). Stacks are built as the env
  builds them: going back from a frame, an episode's first frame repeats.

  If no transition is valid yet (V = 0: too few steps, e.g. fewer than two
  `add` calls), the batch is filler from arbitrary rows and its `discount` is 0;
  check `num_valid` on the host (or `check_can_sample`) before sampling.

  Args:
    buffer: the buffer.
    key: a `jax.random` key.
    batch_size: B, a positive int (static under jit).

  Returns:
    A `Batch`: obs/next_obs uint8 (B, H, W, C·k), action float32 (B, A),
    reward float32 (B,), discount float32 (B,) (1 for valid transitions).
  """
  b = positive_int("batch_size", batch_size)
  n, t, h, w, c = buffer.frames.shape
  k = buffer.frame_stack
  valid = valid_mask(buffer).reshape(-1)
  running = jnp.cumsum(valid, dtype=jnp.int32)
  r = jax.random.randint(key, (b,), 0, jnp.maximum(running[-1], 1))
  flat = jnp.minimum(jnp.searchsorted(running, r, side="right"), n * t - 1)
  env, slot = flat // t, flat % t
  # chain[0] = row t+1, chain[1] = row t, then back: stay on an episode start.
  chain = [(slot + 1) % t, slot]
  for _ in range(k - 1):
    prev = chain[-1]
    chain.append(jnp.where(buffer.first[env, prev], prev, (prev - 1) % t))
  slots = jnp.stack(chain[::-1], axis=1)            # (B, k+1), oldest first
  # Materialised here, so that the fusions that read the frames through them
  # (stacks, augmentations, encoder inputs) read B·(k+1) indices instead of
  # recomputing this arithmetic for every byte they write.
  env, slots = jax.lax.optimization_barrier((env, slots))
  frames = buffer.frames[env[:, None], slots]       # (B, k+1, H, W, C)
  frames = jnp.moveaxis(frames, 1, 3)               # (B, H, W, k+1, C)

  def stack(f):
    return f.reshape(b, h, w, k * c)

  return Batch(obs=stack(frames[..., :k, :]),
               action=buffer.action[env, slot],
               reward=buffer.reward[env, slot],
               discount=valid[flat].astype(jnp.float32),
               next_obs=stack(frames[..., 1:, :]))


def check_can_sample(buffer: ReplayBuffer) -> int:
  """Host-side guard: the number of valid transitions, or a clear error.

  Args:
    buffer: the buffer (concrete, not traced).

  Returns:
    V = `num_valid(buffer)` as a Python int, V > 0.

  Raises:
    ValueError: no transition can be sampled yet.
  """
  v = int(num_valid(buffer))
  if v == 0:
    raise ValueError(
        f"the replay buffer holds no valid transition yet (at most "
        f"{int(jnp.max(buffer.count))} rows per env written); add more steps before sampling (a transition needs its next "
        "frame written and not an episode start)")
  return v
