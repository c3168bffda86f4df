"""The 22 DMCR tasks as MJX physics with JAX-ported dm_control tasks.

One module per domain; each exposes `TASKS`, a dict from dm_control task name to
`TaskSpec`. `load("walker-walk")` builds (once, cached) the `Task` with the
`reset`/`step` protocol of `dmcr_jax.models.base`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported lazily: this package's names are cheap to import
  from dmcr_jax.models.base import State, Task, TaskSpec

# The DMCR domains and tasks (the paper's release, minus none: 10 domains, 22 tasks).
DOMAIN_TASKS: dict[str, tuple[str, ...]] = {
    "ball_in_cup": ("catch",),
    "cartpole": ("balance", "balance_sparse", "swingup", "swingup_sparse"),
    "cheetah": ("run",),
    "finger": ("spin", "turn_easy", "turn_hard"),
    "fish": ("upright", "swim"),
    "hopper": ("stand", "hop"),
    "humanoid": ("stand", "walk", "run"),
    "pendulum": ("swingup",),
    "reacher": ("easy", "hard"),
    "walker": ("stand", "walk", "run"),
}

ALL_TASKS: tuple[str, ...] = tuple(
    f"{d}-{t}" for d, ts in DOMAIN_TASKS.items() for t in ts)


def split_name(name: str) -> tuple[str, str]:
  """Splits "domain-task" and validates it against `ALL_TASKS`."""
  if not isinstance(name, str) or name not in ALL_TASKS:
    raise ValueError(
        f"Unknown task {name!r}. Valid tasks: {', '.join(ALL_TASKS)}.")
  domain, task = name.split("-", 1)
  return domain, task


def spec(name: str) -> "TaskSpec":
  """The `TaskSpec` of a registered task name like "walker-walk"."""
  domain, task = split_name(name)
  module = importlib.import_module(f"dmcr_jax.models.{domain}")
  return module.TASKS[task]


def load(name: str, solver_iterations: int | None = None,
         ls_iterations: int | None = None) -> "Task":
  """Builds (once per process and arguments, cached) the `Task` called `name`.

  Args:
    name: one of `ALL_TASKS`, e.g. "walker-walk".
    solver_iterations, ls_iterations: override the constraint solver's
      iteration budgets. None keeps dm_control's iterations and caps the line
      search at `base.DEFAULT_LS_ITERATIONS` (which leaves trajectories
      unchanged; the parity tests check these defaults); smaller budgets run
      faster but drift from dm_control (see `dmcr_jax.models.base`).

  Returns:
    A `Task` with pure, jittable `reset(key)` and `step(state, action)`.

  Raises:
    ValueError: if `name` is not a registered task (the message lists them).
  """
  from dmcr_jax.models.base import build_task
  return build_task(spec(name), solver_iterations, ls_iterations)


def __getattr__(name):
  if name in ("State", "Task", "TaskSpec"):
    from dmcr_jax.models import base
    return getattr(base, name)
  raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["ALL_TASKS", "DOMAIN_TASKS", "State", "Task", "TaskSpec", "load",
           "spec", "split_name"]
