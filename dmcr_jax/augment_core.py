"""The augmentation types: one augmentation, a composition, and their batching.

An `Augmentation` is a per-sample parameter draw and a per-sample transform of one
uint8 (H, W, 3·stack) image; calling it checks a batch (or a pytree of batches),
draws sample i's parameters from ``fold_in(key, i)`` (`sample_keys`) and applies
them under `jax.vmap`. `Composed` applies augmentations in order; `identity` is the
augmentation that changes nothing.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp

Params = Any
Images = Any  # a uint8 array (B, H, W, 3·stack) or a pytree of such arrays
SampleFn = Callable[[jax.Array, tuple[int, int]], Params]
ApplyFn = Callable[[Params, jax.Array], jax.Array]


# --------------------------------------------------------------------------- #
# The two types: one augmentation, and a composition of augmentations.
# --------------------------------------------------------------------------- #


@dataclasses.dataclass(frozen=True, eq=False)
class Augmentation:
  """One augmentation: a per-sample parameter draw and a per-sample transform.

  Calling it augments a batch (see `__call__`); `one` augments a single image;
  `params` returns the parameters a batch call would draw (for logging and tests).

  Attributes:
    name: the registry name (e.g. ``"drq"``).
    sample: ``sample(key, (H, W)) -> params``, the random draw for one sample.
    apply: ``apply(params, image) -> image`` for one uint8 image (H, W, C), C a
      multiple of 3 (frames stacked on channels); deterministic given params.
    per_batch: if True, one draw from ``key`` is shared by the whole batch
      (Network Randomization); otherwise sample ``i`` draws from
      ``fold_in(key, i)``.
  """
  name: str
  sample: SampleFn
  apply: ApplyFn
  per_batch: bool = False

  def __post_init__(self):
    object.__setattr__(self, "_jitted", jax.jit(functools.partial(_augment, self)))
    object.__setattr__(self, "_jitted_params", jax.jit(
        functools.partial(_draw_params, self), static_argnums=1))

  def __call__(self, key: jax.Array, images: Images) -> Images:
    """Augments a batch (jit-compiled; also callable inside an outer `jit`).

    Two compiled steps: `sample_keys` (shared by all augmentations, so compiled
    once per batch size) and the augmentation itself; inside an outer `jit` both
    are traced into one program.

    Args:
      key: a `jax.random` key (typed or raw uint32).
      images: a uint8 array (B, H, W, 3·stack), or a pytree (tuple, dict, …) of
        such arrays with the same B, H, W, e.g. ``(obs, next_obs)``; sample ``i``
        of every array gets the same parameters.

    Returns:
      The augmented images: the same structure, shapes and dtype (uint8).
    """
    batch = _check_images(images)[0]
    return self._jitted(key if self.per_batch else sample_keys(key, batch), images)

  def one(self, key: jax.Array, image: jax.Array) -> jax.Array:
    """Augments one uint8 image (H, W, C) with parameters drawn from `key`.

    For a per-sample augmentation, ``aug(key, x)[i] == aug.one(fold_in(key, i),
    x[i])``; for a per-batch one, ``aug(key, x)[i] == aug.one(key, x[i])``.

    Args:
      key: a `jax.random` key.
      image: uint8 (H, W, C), C a multiple of 3.

    Returns:
      uint8 (H, W, C).
    """
    _check_leaf(image, rank=3)
    return self.apply(self.sample(key, tuple(image.shape[:2])), image)

  def params(self, key: jax.Array, batch: int, hw: tuple[int, int]) -> Params:
    """The parameters that ``aug(key, images)`` draws for a (batch, H, W, ·) input.

    Args:
      key: a `jax.random` key.
      batch: the batch size B (static).
      hw: (H, W) (static).

    Returns:
      A pytree of arrays with leading axis B (or unbatched if `per_batch`).
    """
    return self._jitted_params(key if self.per_batch else sample_keys(key, batch),
                               tuple(hw))


@dataclasses.dataclass(frozen=True, eq=False)
class Composed:
  """Augmentations applied in order, e.g. ``"cj+drq"``: Color Jitter, then DrQ.

  Stage ``s`` draws from ``fold_in(key, s)``, so every stage is independent and
  each keeps the o/o′ and frame-stack consistency of `Augmentation`.

  Attributes:
    name: the ``+``-joined name.
    stages: the augmentations, first applied first.
  """
  name: str
  stages: tuple[Augmentation, ...]

  def __call__(self, key: jax.Array, images: Images) -> Images:
    """Augments a batch; same contract as `Augmentation.__call__`.

    Args:
      key: a `jax.random` key.
      images: a uint8 array (B, H, W, 3·stack) or a pytree of such arrays.

    Returns:
      The augmented images, same structure, shapes and dtype.
    """
    for s, stage in enumerate(self.stages):
      images = stage(jax.random.fold_in(key, s), images)
    return images


def _check_leaf(x, rank: int):
  if getattr(x, "dtype", None) != jnp.uint8:
    raise TypeError(f"augmentations take uint8 images, got dtype "
                    f"{getattr(x, 'dtype', type(x))}")
  if x.ndim != rank:
    dims = "B, H, W, 3·stack" if rank == 4 else "H, W, 3·stack"
    raise ValueError(f"expected a rank-{rank} image array ({dims}), got shape "
                     f"{x.shape}")
  if x.shape[-1] % 3:
    raise ValueError(f"channels must be a multiple of 3 (RGB frames stacked on "
                     f"the last axis), got {x.shape[-1]}")


def _check_images(images) -> tuple[int, int, int]:
  """Checks a pytree of uint8 (B, H, W, 3·k) arrays; returns the shared (B, H, W)."""
  leaves = jax.tree_util.tree_leaves(images)
  if not leaves:
    raise ValueError("no images given")
  for leaf in leaves:
    _check_leaf(leaf, rank=4)
  shape = leaves[0].shape[:3]
  for leaf in leaves[1:]:
    if leaf.shape[:3] != shape:
      raise ValueError(f"all arrays must share (B, H, W); got {leaf.shape[:3]} "
                       f"and {shape}")
  return shape


@functools.partial(jax.jit, static_argnums=1)
def sample_keys(key: jax.Array, batch: int) -> jax.Array:
  """The per-sample keys of a batch: ``fold_in(key, i)`` for i = 0 … batch − 1.

  Sample i's draw therefore does not depend on the batch size, and
  ``aug(key, x)[i] == aug.one(sample_keys(key, B)[i], x[i])``.

  Args:
    key: a `jax.random` key (typed or raw uint32).
    batch: the batch size (static).

  Returns:
    `batch` keys, stacked on a leading axis.
  """
  return jax.vmap(jax.random.fold_in, in_axes=(None, 0))(
      key, jnp.arange(batch, dtype=jnp.uint32))


def _draw_params(aug: Augmentation, keys, hw: tuple[int, int]):
  """Per-sample params from per-sample `keys`, or one draw from one key."""
  if aug.per_batch:
    return aug.sample(keys, hw)
  return jax.vmap(aug.sample, in_axes=(0, None))(keys, hw)


def _augment(aug: Augmentation, keys, images):
  """Batches `aug` over a pytree of (B, H, W, C) uint8 arrays (one param draw).

  `keys` holds one key per sample (`sample_keys`), or one key if `aug.per_batch`.
  """
  _, h, w = _check_images(images)
  params = _draw_params(aug, keys, (h, w))
  apply = jax.vmap(aug.apply, in_axes=(None if aug.per_batch else 0, 0))
  return jax.tree_util.tree_map(lambda x: apply(params, x), images)


def identity() -> Augmentation:
  """No augmentation (``"none"``): returns the images unchanged.

  Returns:
    An `Augmentation`.
  """
  return Augmentation("none", lambda key, hw: {}, lambda p, x: x)
