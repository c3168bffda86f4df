"""The zero-shot protocol's plan, on the host: conditions, held-out looks, seeds, episodes.

`make_plan` lists every agent's episodes as NumPy arrays (each episode's visual
seed, factor mask, reset seed and key index), one segment per condition and, where
an agent needs them, the train episodes; `dmcr_jax.protocol` runs them. Episode i
of every condition has the same reset seed (`reset_seeds`) and key index, so
conditions differ only in their looks. Condition names (`check_conditions`,
`parse_condition`): the static ones of `conditions_for` and the moving ones
``moving-<factor>@<intensity>``, whose segments carry their `moving` and `intensity`
(`Segment.motion`, `Plan.motion_arrays`). Also the progress files of an interrupted
pass (`load_progress`, `save_progress`). NumPy only: nothing here touches a device.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from typing import Sequence

import numpy as np

from dmcr_jax._files import write_atomic
from dmcr_jax.visuals.levels import SeedRange

FACTOR_CONDITIONS: tuple[str, ...] = ("light", "camera", "body", "floor", "background",
                                      "target", "reflectance")
"""Single-factor conditions in table order (those that apply to a domain are used)."""

PROGRESS_FILE = "progress.npz"
"""The usual name of a pass's progress file (`Protocol.__call__(progress_file=…)`)."""


# --------------------------------------------------------------------------- #
# Conditions, looks and seeds.
# --------------------------------------------------------------------------- #


def conditions_for(task: str) -> tuple[str, ...]:
  """The conditions evaluated for `task`: none, each applicable factor, all."""
  from dmcr_jax.visuals.factors import active_factors
  domain = task.split("-", 1)[0]
  factors = active_factors(domain, "all")
  return ("none",) + tuple(f for f in FACTOR_CONDITIONS if f in factors) + ("all",)


MOVING_PREFIX = "moving-"
"""Moving conditions are named ``moving-<factor>@<intensity>`` (`moving_condition`)."""


def moving_condition(factor: str, intensity: float) -> str:
  """The name of a moving condition: ``moving-camera@0.2``, ``moving-all@0.1``."""
  return f"{MOVING_PREFIX}{factor}@{float(intensity):g}"


def moving_factors_for(task: str) -> tuple[str, ...]:
  """The moving factors that apply to `task`'s domain, then "all"."""
  from dmcr_jax.visuals.factors import APPLICABLE
  from dmcr_jax.visuals.moving import MOVING_FACTORS
  domain = task.split("-", 1)[0]
  return tuple(f for f in MOVING_FACTORS if f in APPLICABLE[domain]) + ("all",)


def moving_conditions_for(task: str, intensities: Sequence[float]) -> tuple[str, ...]:
  """Every moving condition of `task` at each intensity: per intensity, each moving
  factor that applies to the domain, then "all" (`moving_factors_for`)."""
  return tuple(moving_condition(f, i) for i in intensities for f in moving_factors_for(task))


def parse_condition(task: str, name: str) -> tuple[str, str, tuple[str, ...], float]:
  """A condition's name checked for `task`, and what it shows.

  Static conditions (`conditions_for`) vary their factors of each held-out seed's
  look for the whole episode. A moving condition ``moving-<factor>@<intensity>``
  (factor: a moving factor of the domain or "all"; intensity in [0, 1]) shows
  dm_control's look (as "none") with that factor moving within the episode
  (`visuals.moving`), the held-out seed picking its motion: what
  ``dmcr_jax.make(task, visual_seeds=seeds, vary="none", moving=factor,
  intensity=intensity)`` draws. At intensity 0 it is "none".

  Args:
    task: the task.
    name: e.g. "floor", "all", "moving-camera@0.2", "moving-all@.1".

  Returns:
    (canonical name, vary, moving factors (`moving.check_moving`'s), intensity).

  Raises:
    ValueError: an unknown condition, moving factor or malformed intensity (the
      message names the valid choices).
  """
  from dmcr_jax.visuals.moving import check_moving
  static = conditions_for(task)
  factors = moving_factors_for(task)
  if not isinstance(name, str):
    raise ValueError(f"a condition is a name (str), got {name!r}")
  if name in static:
    return name, name, (), 0.0
  spelling = _spelling(task)
  if not name.startswith(MOVING_PREFIX) or name.count("@") != 1:
    raise ValueError(f"conditions {[name]!r} are not valid for {task}; {spelling}")
  factor, _, level = name[len(MOVING_PREFIX):].partition("@")
  if factor not in factors:
    raise ValueError(f"condition {name!r}: {factor!r} is not a moving factor of {task}; "
                     f"{spelling}")
  try:
    intensity = float(level)
  except ValueError:
    intensity = float("nan")
  if not 0.0 <= intensity <= 1.0:
    raise ValueError(f"condition {name!r}: the intensity must be a number in [0, 1], got "
                     f"{level!r}; {spelling}")
  moving, intensity = check_moving(task.split("-", 1)[0], factor, intensity)
  return moving_condition(factor, intensity), "none", moving, intensity


def _spelling(task: str) -> str:
  """The valid condition names of `task`, for error messages."""
  factors = moving_factors_for(task)
  return (f"valid: {', '.join(conditions_for(task))}, or {MOVING_PREFIX}<factor>@<intensity> "
          f"with factor one of {', '.join(factors)} and intensity in [0, 1] (e.g. "
          f"{moving_condition(factors[0], 0.2)})")


def check_conditions(task: str, conditions: Sequence[str] | None = None,
                     moving_intensities: Sequence[float] = ()) -> tuple[str, ...]:
  """The conditions to run, checked and named canonically: `conditions` (None: every
  static one, `conditions_for`), then every moving condition at each of
  `moving_intensities` (`moving_conditions_for`) not already among them.

  Raises:
    ValueError: a bad name or intensity (naming the valid choices), a condition
      named twice, or none at all.
  """
  levels = []
  for i in moving_intensities:
    if isinstance(i, bool) or not isinstance(i, (int, float, np.number)) \
        or not 0.0 <= float(i) <= 1.0:
      raise ValueError(f"moving intensities must be numbers in [0, 1] (DCS's difficulties "
                       f"are 0.1, 0.2, 0.3), got {i!r}")
    levels.append(float(i))
  names = conditions_for(task) if conditions is None else tuple(conditions)
  bad = [c for c in names if not isinstance(c, str)
         or (c not in conditions_for(task) and not c.startswith(MOVING_PREFIX))]
  if bad:
    raise ValueError(f"conditions {bad!r} are not valid for {task}; {_spelling(task)}")
  out = tuple(parse_condition(task, c)[0] for c in names)
  if len(set(out)) != len(out):
    raise ValueError(f"conditions {tuple(names)!r} name a condition twice")
  out += tuple(c for c in moving_conditions_for(task, levels) if c not in out)
  if not out:
    raise ValueError(f"conditions () are not valid for {task}: name at least one; "
                     f"{_spelling(task)}")
  return out


def moving_of(name: str) -> tuple[str, float] | None:
  """(factor, intensity) of a moving condition's canonical name; None for a static one."""
  if not name.startswith(MOVING_PREFIX):
    return None
  factor, _, level = name[len(MOVING_PREFIX):].partition("@")
  return factor, float(level)


def held_out_seeds(n: int, seed: int = 0) -> np.ndarray:
  """`n` distinct visual seeds drawn from `dmcr_jax.TEST_SEEDS` (int64, sorted).

  Args:
    n: how many.
    seed: seed of the NumPy generator that draws them.

  Returns:
    (n,) seeds, all in [TEST_SEEDS.start, TEST_SEEDS.stop).
  """
  from dmcr_jax import TEST_SEEDS
  rng = np.random.default_rng(seed)
  size = TEST_SEEDS.stop - TEST_SEEDS.start
  seeds = TEST_SEEDS.start + np.sort(rng.choice(size, size=n, replace=False))
  return seeds.astype(np.int64)


def reset_seeds(n: int, seed: int) -> np.ndarray:
  """The per-env reset seeds of a condition's episodes, (n,) uint32: episode i's
  initial state depends on (`seed`, i) alone, whatever the agents and conditions."""
  return np.random.default_rng((seed, 1)).integers(0, 2**32, n, dtype=np.uint32)


def is_default_look(train_look) -> bool:
  """Whether every training episode showed seed 0's look, which "none" also shows
  (a fixed seed 0, or the range levels:1 = [0, 1))."""
  if isinstance(train_look, SeedRange):
    return train_look == SeedRange(0, 1)
  return bool(np.all(np.asarray(train_look) == 0))


def train_look_seeds(train_look, n: int, seed: int) -> np.ndarray:
  """`n` visual seeds of an agent's training looks, one per train episode: the fixed
  seed, or draws from its range with a NumPy generator seeded by `seed`."""
  if isinstance(train_look, SeedRange):
    rng = np.random.default_rng(seed)
    return rng.integers(train_look.start, train_look.stop, n).astype(np.int64)
  return np.full(n, int(train_look), np.int64)


def check_disjoint(test_seeds: np.ndarray, train_look) -> None:
  """RuntimeError if a held-out seed lies in the training looks."""
  if isinstance(train_look, SeedRange):
    inside = (test_seeds >= train_look.start) & (test_seeds < train_look.stop)
  else:
    inside = np.isin(test_seeds, np.atleast_1d(train_look))
  if inside.any():
    raise RuntimeError(f"test visual seeds {test_seeds[inside][:4]} lie in the training "
                       "looks; the held-out range must never overlap them")


def look_label(train_look) -> str:
  """A training look's name in tables: "seed 0", "levels:10", "[2, 3)"."""
  if isinstance(train_look, SeedRange):
    return f"levels:{train_look.stop}" if train_look.start == 0 else str(train_look)
  return f"seed {int(train_look)}"


# --------------------------------------------------------------------------- #
# Progress files: finished blocks of an interrupted pass.
# --------------------------------------------------------------------------- #


def load_progress(path: str, key: dict) -> tuple[dict, float]:
  """The blocks finished by an earlier, interrupted pass of the same protocol.

  Args:
    path: the progress file.
    key: what fixes the episodes (protocol, params digest, caller's identity); a
      file written under another key is ignored.

  Returns:
    ({name: (returns (K, B) float64, wall s)}, wall s spent on them); empty when
    there is no usable file.
  """
  if not os.path.exists(path):
    return {}, 0.0
  try:
    with np.load(path) as f:
      meta = json.loads(str(f["meta"]))
      if meta["key"] != json.loads(json.dumps(key)):
        print(f"evaluate: ignoring {path} (written for another run or protocol)",
              file=sys.stderr, flush=True)
        return {}, 0.0
      done = {name: (f[f"returns/{name}"], wall) for name, wall in meta["walls"].items()}
  except (OSError, ValueError, KeyError) as e:
    print(f"evaluate: ignoring {path} ({e})", file=sys.stderr, flush=True)
    return {}, 0.0
  return done, float(meta["elapsed_s"])


def save_progress(path: str, key: dict, done: dict, elapsed_s: float) -> None:
  """Writes the finished blocks (`load_progress`'s format) atomically: a crash
  while writing leaves the previous file."""
  meta = dict(key=key, walls={name: wall for name, (_, wall) in done.items()},
              elapsed_s=elapsed_s)
  arrays = {f"returns/{name}": returns for name, (returns, _) in done.items()}
  write_atomic(path, lambda f: np.savez(f, meta=json.dumps(meta), **arrays))


# --------------------------------------------------------------------------- #
# The plan: every episode of every agent, as host arrays.
# --------------------------------------------------------------------------- #


@dataclasses.dataclass(frozen=True)
class Segment:
  """A run of consecutive episodes in every agent's episode list.

  Attributes:
    name: the condition, or "train".
    vary: the factors its looks vary (`dmcr_jax.make`'s `vary`).
    start, size: its episodes are [start, start + size) of the list.
    moving, intensity: the factors that move within its episodes and how far
      (`dmcr_jax.make`'s `moving`, `intensity`; () and 0: static looks).
  """
  name: str
  vary: str
  start: int
  size: int
  moving: tuple[str, ...] = ()
  intensity: float = 0.0

  @property
  def motion(self) -> tuple[tuple[str, ...], float]:
    """(moving, intensity) as drawn: ((), 0.0) where nothing moves (no factor, or
    intensity 0, which `dmcr_jax.make` draws as the static look)."""
    return (self.moving, self.intensity) if self.moving and self.intensity > 0 else ((), 0.0)


@dataclasses.dataclass(frozen=True)
class Plan:
  """Every agent's episodes (E of them, the same E for every agent), as host arrays.

  Attributes:
    segments: the conditions' segments (in order), then "train" if any agent needs
      its own train episodes.
    visual_seed: int32 (K, E) each episode's look, per agent (train looks may differ).
    mask: bool (K, E, 7) the factors each episode's look varies (`factor_mask`).
    vary_index: int32 (K, E) index of its segment's `vary` in `varies` (the pool).
    varies: the distinct `vary` strings, in segment order.
    reset_seed: uint32 (E,) each episode's reset seed (its initial state).
    index: int32 (E,) each episode's index within its segment (its policy keys).
    shares: bool per agent: its train episodes are the first of "none".
    motion_index: int32 (E,) index of its segment's `Segment.motion` in `motions`.
    motions: the distinct motions, ((), 0.0) (static looks) first.
  """
  segments: tuple[Segment, ...]
  visual_seed: np.ndarray
  mask: np.ndarray
  vary_index: np.ndarray
  varies: tuple[str, ...]
  reset_seed: np.ndarray
  index: np.ndarray
  shares: tuple[bool, ...]
  motion_index: np.ndarray
  motions: tuple[tuple[tuple[str, ...], float], ...]

  @property
  def episodes(self) -> int:
    """E, episodes per agent."""
    return int(self.reset_seed.shape[0])

  @property
  def moving(self) -> tuple[str, ...]:
    """The factors any episode moves, in `visuals.moving.MOVING_FACTORS` order."""
    from dmcr_jax.visuals.moving import MOVING_FACTORS
    used = {f for m, _ in self.motions for f in m}
    return tuple(f for f in MOVING_FACTORS if f in used)

  def motion_arrays(self, episodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per episode of `episodes` (int indices) which of `moving` it moves, bool
    (n, len(moving)), and its intensity, float32 (n,) (0 where nothing moves)."""
    moving = self.moving
    on = np.array([[f in m for f in moving] for m, _ in self.motions], bool)
    level = np.array([i for _, i in self.motions], np.float32)
    j = self.motion_index[episodes]
    return on[j].reshape(len(j), len(moving)), level[j]


def make_plan(task: str, conditions: Sequence[str], test_seeds: np.ndarray,
              dynamics_seeds: int, train_episodes: int, train_looks: Sequence,
              train_vary, seed: int) -> Plan:
  """The episodes of the protocol for K agents (K = len(train_looks)).

  Args:
    task: the task.
    conditions: the conditions, in order, checked (`check_conditions`).
    test_seeds: (V,) held-out visual seeds.
    dynamics_seeds: D, initial states per look.
    train_episodes: T.
    train_looks: per agent its training look (an int seed or a `SeedRange`).
    train_vary: the factors the training looks vary.
    seed: the protocol's seed (train-look draws, reset seeds).
  """
  from dmcr_jax.visuals.params import factor_mask
  domain = task.split("-", 1)[0]
  k = len(train_looks)
  per_env = np.repeat(np.asarray(test_seeds, np.int64), dynamics_seeds)
  n = per_env.size
  cond_resets = reset_seeds(n, seed)
  shares = tuple("none" in conditions and is_default_look(look) for look in train_looks)
  segments, seeds, varies, resets, index = [], [], [], [], []
  start = 0
  for c in conditions:
    if moving_of(c) is None:
      segments.append(Segment(c, c, start, n))
    else:
      _, vary, moving, intensity = parse_condition(task, c)
      segments.append(Segment(c, vary, start, n, moving, intensity))
    seeds.append(np.tile(per_env, (k, 1)))
    start += n
  if not all(shares):
    segments.append(Segment("train", train_vary if isinstance(train_vary, str)
                            else ",".join(train_vary), start, train_episodes))
    # Agents that share "none" keep dm_control's look here (their results are unused).
    seeds.append(np.stack([per_env[:train_episodes] if s else
                           train_look_seeds(look, n, seed)[:train_episodes]
                           for look, s in zip(train_looks, shares)]))
  for s in segments:
    resets.append(cond_resets[:s.size])
    index.append(np.arange(s.size, dtype=np.int32))
  names = list(dict.fromkeys(s.vary for s in segments))
  vary_index = np.concatenate([np.full((k, s.size), names.index(s.vary), np.int32)
                               for s in segments], axis=1)
  masks = np.stack([factor_mask(domain, v) for v in names])
  motions = list(dict.fromkeys([((), 0.0)] + [s.motion for s in segments]))
  motion_index = np.concatenate([np.full(s.size, motions.index(s.motion), np.int32)
                                 for s in segments])
  return Plan(segments=tuple(segments), visual_seed=np.concatenate(seeds, 1).astype(np.int32),
              mask=masks[vary_index], vary_index=vary_index, varies=tuple(names),
              reset_seed=np.concatenate(resets), index=np.concatenate(index),
              shares=shares, motion_index=motion_index, motions=tuple(motions))
