"""The arguments of `dmcr_jax.make` and their defaults: checks that run before anything is built.

Per-task action repeats (the paper's Table 4), the reset seeds' range, the camera,
the visual-seed sources (fixed seeds, a `SeedRange` or one range per env), the
renderer and the options only one renderer takes, the physics device and its
worker count. Each check raises a `ValueError` of one sentence naming the valid
choices; none loads a model or starts a worker.
"""

from __future__ import annotations

import numpy as np

from dmcr_jax import models
from dmcr_jax.visuals.levels import TEST_SEEDS, TRAIN_SEEDS, EnvRanges, SeedRange
from dmcr_jax.visuals.params import check_seeds

# Action repeat of the paper's Table 4; other tasks take their domain's value and
# domains the table does not list take 4 (PlaNet/DrQ's default).
ACTION_REPEAT = {"walker-walk": 2, "cheetah-run": 4, "hopper-stand": 4, "finger-spin": 2,
                 "ball_in_cup-catch": 4, "cartpole-balance": 8}
_DOMAIN_REPEAT = {"walker": 2, "cheetah": 4, "hopper": 4, "finger": 2, "ball_in_cup": 4,
                  "cartpole": 8}
MAX_RESET_SEED = 2**32
"""`reset(seed=…)` and `make(seed=…)` take ints in [0, MAX_RESET_SEED): a JAX key
holds 32 bits of an int seed, so larger ones would repeat smaller ones' episodes."""
RENDERERS = ("pool", "jax")
"""What `make(renderer=...)` accepts: the CPU render pool (MuJoCo's own pixels) or
the JAX ray caster (physics, rendering and stacking in one jitted call)."""
POOL_ONLY = ("workers", "quality", "gl", "egl_devices", "copy_obs", "render_pool")
"""The keyword arguments of `make` that only renderer="pool" takes."""
JAX_ONLY = ("shadows", "reflection", "render_chunk", "render_kernel", "obs_on_device")
"""The keyword arguments of `make` that only renderer="jax" takes."""
PHYSICS_DEVICES = (None, "cpu")
"""What `make(physics_device=...)` accepts: JAX's default device, or the host CPU."""


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


def seed_source(visual_seeds, num_envs: int) -> SeedRange | EnvRanges | np.ndarray:
  """`make(visual_seeds=...)` checked, in the form the physics draws from.

  Args:
    visual_seeds: one int (every env), `num_envs` ints, a `SeedRange`, or
      `num_envs` `SeedRange`s (a list or an `EnvRanges`).
    num_envs: N.

  Returns:
    The `SeedRange` or `EnvRanges` itself, or fixed seeds as int (N,).

  Raises:
    ValueError: a seed count other than 1 or N, ranges mixed with fixed seeds, a
      range straddling `TRAIN_SEEDS` and `TEST_SEEDS`, or a bad seed.
  """
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


def check_renderer_name(renderer: str) -> str:
  """`renderer` if it is one of `RENDERERS`, else a ValueError naming them."""
  if renderer not in RENDERERS:
    raise ValueError(f"Unknown renderer {renderer!r}; valid: {', '.join(RENDERERS)}.")
  return renderer


def check_renderer_options(renderer: str, kwargs) -> None:
  """ValueError unless `renderer` is one of `RENDERERS` and none of the keyword
  names `kwargs` holds is an option only the other renderer takes (`POOL_ONLY`,
  `JAX_ONLY`)."""
  check_renderer_name(renderer)
  other = JAX_ONLY if renderer == "pool" else POOL_ONLY
  wrong = sorted(set(kwargs) & set(other))
  if wrong:
    owner = "jax" if renderer == "pool" else "pool"
    raise ValueError(f"{', '.join(wrong)} apply only to renderer={owner!r}, not "
                     f"renderer={renderer!r}")


def check_physics_device(physics_device) -> str | None:
  """`physics_device` if it is one of `PHYSICS_DEVICES`, else a ValueError."""
  if physics_device not in PHYSICS_DEVICES:
    raise ValueError(f"physics_device must be None (JAX's default device) or 'cpu', "
                     f"got {physics_device!r}")
  return physics_device


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
