"""dmcr_jax: DeepMind Control Remastered as a massively batched JAX system.

Physics is dm_control's own suite models stepped by vmapped MJX
(`dmcr_jax.models`); visual seeds become batched render parameters
(`dmcr_jax.visuals`); `make` builds N pixel envs as one gymnasium
`VectorEnv` (`dmcr_jax.env`; `renderer="jax"` renders with the JAX ray caster on
the device, `dmcr_jax.jax_env`), and `GymEnv` / `DmEnv` (registered with gymnasium
as `dmcr/<task>-v0`) are single envs for existing pixel-RL code. `ALL_TASKS`
lists the 22 DMCR tasks; `levels(n)` and `TEST_SEEDS` are the few-shot training
and held-out visual-seed ranges.

Importing the package changes the process in two ways only, both environment
variables that a library read once at its own import would otherwise have fixed
too late, each left alone when the user set it (`_process_settings` says what
and why). Besides them it only registers `dmcr/<task>-v0` with gymnasium: no JAX
config, no logging settings, nothing on stdout.

mujoco-mjx prints "Failed to import warp: No module named 'warp'" to stdout when
the optional `warp` package is absent; the package's modules import `mujoco.mjx`
through `dmcr_jax._mjx`, which drops that message (any other message it prints goes
to stderr), so stdout carries only what a command writes (`train ... | jq` works).

The names above (`make`, `levels`, `GymEnv`, ...) import their modules on first
use, so `import dmcr_jax` itself is light: a worker process of the render pool,
which imports the package to reach its own modules, does not load MJX or the envs.
"""

import os as _os

CPU_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
"""Added to `XLA_FLAGS` at import unless the flag is set (`_process_settings`)."""


def _process_settings() -> None:
  """The only settings `import dmcr_jax` makes (each kept as the user set it):

  - `MUJOCO_GL=egl` (and `PYOPENGL_PLATFORM=egl`) when neither `MUJOCO_GL` nor a
    `DISPLAY` is set: MuJoCo reads `MUJOCO_GL` once, at its import, and its default
    (GLFW) needs a display, so on a headless machine every render would fail.
  - `CPU_SCHEDULER_FLAG` in `XLA_FLAGS` unless that flag is there: with XLA's
    default CPU scheduler a jitted MJX step of about a thousand vmapped walkers
    (and the pixel env's step at that size) can stall on a machine with few cores,
    every thread parked on a futex. It affects only XLA's CPU backend, and only if
    the package is imported before JAX's first computation (when XLA reads its
    flags).
  """
  if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "egl"
    _os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
  if "xla_cpu_enable_concurrency_optimized_scheduler" not in _os.environ.get("XLA_FLAGS", ""):
    _os.environ["XLA_FLAGS"] = f"{_os.environ.get('XLA_FLAGS', '')} {CPU_SCHEDULER_FLAG}".strip()


_process_settings()

from dmcr_jax._lazy import lazy_names as _lazy_names
from dmcr_jax.models import ALL_TASKS, DOMAIN_TASKS, load  # names only: light

_LAZY = {
    "TEST_SEEDS": "dmcr_jax.visuals.levels", "TRAIN_SEEDS": "dmcr_jax.visuals.levels",
    "SeedRange": "dmcr_jax.visuals.levels", "levels": "dmcr_jax.visuals.levels",
    "JaxPixelVectorEnv": "dmcr_jax.env", "PixelVectorEnv": "dmcr_jax.env",
    "make": "dmcr_jax.env", "DmEnv": "dmcr_jax.adapters", "GymEnv": "dmcr_jax.adapters",
}
"""The package's names that live in heavier modules, imported on first use."""

__getattr__, __dir__ = _lazy_names(__name__, _LAZY, globals())


_ENV_ID = "dmcr/{task}-v0"
"""The gymnasium id of a task's single env (`dmcr_jax.adapters.ENV_ID`)."""


def _register_envs() -> None:
  """Registers `dmcr/<task>-v0` for every task with gymnasium (idempotent); the
  entry point, `dmcr_jax.adapters.GymEnv`, is imported when an env is made."""
  import gymnasium
  for task in ALL_TASKS:
    env_id = _ENV_ID.format(task=task)
    if env_id not in gymnasium.registry:
      gymnasium.register(id=env_id, entry_point="dmcr_jax.adapters:GymEnv",
                         kwargs={"task": task})


_register_envs()

__version__ = "0.1.0"
__all__ = ["ALL_TASKS", "DOMAIN_TASKS", "DmEnv", "GymEnv", "JaxPixelVectorEnv",
           "PixelVectorEnv", "SeedRange", "TEST_SEEDS", "TRAIN_SEEDS", "levels", "load",
           "make", "__version__"]
