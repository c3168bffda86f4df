"""Visual-seed ranges: where training levels may come from, and the held-out test range.

The space of visual seeds [0, 2**31) is split in two halves that never overlap:

- `TRAIN_SEEDS` = [0, 2**30): every training range lies here. Seed 0 is
  dm_control's look (the classic setting trains on it alone); `levels(n)` is the
  few-shot range [0, n) of the first n seeds.
- `TEST_SEEDS` = [2**30, 2**31 − 1): evaluation draws only from here, so a test
  look is never a look some agent trained on, whatever training range it used.
  (The original DMCR drew test seeds that could coincide with training levels.)

A `SeedRange` is a half-open interval [start, stop) of seeds; `sample(key, shape)`
draws from it uniformly inside `jit`, and `first(n)` lists its first n seeds (a
fixed, documented evaluation set). `EnvRanges` gives each env of a batch its own
range (agents with different training ranges in one run). Both are static under
`jit` (hashable); `SeedBounds` holds a batch's ranges as arrays instead, so one
compilation serves any ranges.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from dmcr_jax.checks import positive_int
from dmcr_jax.visuals.params import MAX_SEED

_SPLIT = 2**30


@dataclasses.dataclass(frozen=True)
class SeedRange:
  """The visual seeds start, start + 1, …, stop − 1.

  Attributes:
    start: first seed (≥ 0).
    stop: one past the last seed (≤ 2**31 − 1, > start).
  """
  start: int
  stop: int

  def __post_init__(self):
    for name in ("start", "stop"):
      v = getattr(self, name)
      if not isinstance(v, (int, np.integer)) or isinstance(v, bool):
        raise TypeError(f"SeedRange.{name} must be an int, got {v!r}")
    if not 0 <= self.start < self.stop <= MAX_SEED:
      raise ValueError(f"SeedRange needs 0 <= start < stop <= 2**31 - 1, got "
                       f"[{self.start}, {self.stop})")
    object.__setattr__(self, "start", int(self.start))
    object.__setattr__(self, "stop", int(self.stop))

  def __len__(self) -> int:
    return self.stop - self.start

  def __contains__(self, seed) -> bool:
    return self.start <= int(seed) < self.stop

  def overlaps(self, other: "SeedRange") -> bool:
    return self.start < other.stop and other.start < self.stop

  def contains_all(self, seeds) -> bool:
    """Whether every seed of an int array lies in the range."""
    seeds = np.asarray(seeds)
    return bool(np.all((seeds >= self.start) & (seeds < self.stop)))

  def sample(self, key: jax.Array, shape: tuple[int, ...] = ()) -> jax.Array:
    """Uniform int32 seeds from the range (jittable)."""
    return jax.random.randint(key, shape, self.start, self.stop, dtype=jnp.int32)

  def first(self, n: int) -> np.ndarray:
    """The range's first `n` seeds, int32 (n,)."""
    if not 0 < n <= len(self):
      raise ValueError(f"need 0 < n <= {len(self)}, got {n}")
    return np.arange(self.start, self.start + n, dtype=np.int32)

  def __repr__(self):
    return f"SeedRange({self.start}, {self.stop})"


@dataclasses.dataclass(frozen=True)
class EnvRanges:
  """One `SeedRange` per env: env i draws every episode's seed from `ranges[i]`
  (several few-shot ranges in one batch, e.g. one per agent of a training run).

  Attributes:
    ranges: N `SeedRange`s (a tuple: the object is hashable, static under `jit`).
  """
  ranges: tuple[SeedRange, ...]

  def __post_init__(self):
    ranges = tuple(self.ranges)
    if not ranges or not all(isinstance(r, SeedRange) for r in ranges):
      raise TypeError(f"EnvRanges needs one or more SeedRanges, got {self.ranges!r}")
    object.__setattr__(self, "ranges", ranges)

  def __len__(self) -> int:
    return len(self.ranges)

  def sample(self, key: jax.Array, index: jax.Array) -> jax.Array:
    """A uniform int32 seed from env `index`'s range (jittable; `index` may be
    traced). Draws what `ranges[index].sample(key)` draws."""
    return SeedBounds.of(self, len(self)).sample(key, index)

  def contains_all(self, seeds) -> bool:
    """Whether every row of an int array (…, N) lies in its env's range."""
    seeds = np.asarray(seeds)
    start = np.asarray([r.start for r in self.ranges])
    stop = np.asarray([r.stop for r in self.ranges])
    return bool(np.all((seeds >= start) & (seeds < stop)))

  def __repr__(self):
    distinct = list(dict.fromkeys(self.ranges))
    return f"EnvRanges({len(self)} envs: {', '.join(map(repr, distinct))})"


@struct.dataclass
class SeedBounds:
  """N envs' seed ranges as int32 arrays: env i draws from [start[i], stop[i]).

  The arrays are traced under `jit`, so a function taking `SeedBounds` compiles
  once for every range of a batch size (a `SeedRange` or `EnvRanges` is static:
  each new range compiles anew).

  Attributes:
    start, stop: int32 (N,), start < stop.
  """
  start: jax.Array
  stop: jax.Array

  @classmethod
  def of(cls, ranges: "SeedRange | EnvRanges", num_envs: int) -> "SeedBounds":
    """The bounds of one range for all `num_envs` envs, or of an `EnvRanges`
    (one range per env; its length must be `num_envs`)."""
    rs = ranges.ranges if isinstance(ranges, EnvRanges) else (ranges,) * int(num_envs)
    if len(rs) != num_envs:
      raise ValueError(f"{ranges!r} holds {len(rs)} ranges for {num_envs} envs")
    return cls(start=np.asarray([r.start for r in rs], np.int32),
               stop=np.asarray([r.stop for r in rs], np.int32))

  def sample(self, key: jax.Array, index: jax.Array) -> jax.Array:
    """A uniform int32 seed from env `index`'s range (jittable); for the bounds
    of a `SeedRange` r, the seed `r.sample(key)` draws."""
    return jax.random.randint(key, (), jnp.asarray(self.start)[index],
                              jnp.asarray(self.stop)[index], dtype=jnp.int32)


TRAIN_SEEDS = SeedRange(0, _SPLIT)
TEST_SEEDS = SeedRange(_SPLIT, MAX_SEED)


def levels(num_levels: int, start: int = 0) -> SeedRange:
  """A few-shot training range: `num_levels` seeds from `start` (default [0, n)).

  Raises:
    ValueError: if the range would leave `TRAIN_SEEDS` (reach the test range).
  """
  num_levels = positive_int("num_levels", num_levels)
  return check_training_range(SeedRange(start, start + num_levels))


def check_training_range(r: SeedRange) -> SeedRange:
  """Returns `r` if it lies inside `TRAIN_SEEDS`, else raises ValueError."""
  if r.overlaps(TEST_SEEDS):
    raise ValueError(f"training range {r} overlaps the held-out test range {TEST_SEEDS}; "
                     f"training seeds must lie in {TRAIN_SEEDS}")
  return r
