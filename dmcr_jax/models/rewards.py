"""A JAX port of `dm_control.utils.rewards.tolerance`.

Every DMC reward is built from `tolerance`: 1 inside `bounds`, falling off with a
sigmoid of the distance to the nearest bound, scaled so that it equals
`value_at_margin` at distance `margin`. The port keeps dm_control's arguments,
defaults and sigmoid names, so a task's reward reads line for line like the
original; `tests/test_rewards.py` checks it against dm_control on random inputs.
Bounds, margin, sigmoid and value_at_margin are static (Python floats/strings);
`x` may be any traced array.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

SIGMOIDS = ("gaussian", "hyperbolic", "long_tail", "reciprocal", "cosine",
            "linear", "quadratic", "tanh_squared")

_DEFAULT_VALUE_AT_MARGIN = 0.1


def _sigmoid(x, value_at_1: float, sigmoid: str):
  """Maps a normalised distance `x` (value 1 at `margin`) to (0, 1]."""
  if sigmoid in ("cosine", "linear", "quadratic"):
    if not 0 <= value_at_1 < 1:
      raise ValueError(f"`value_at_1` must be in [0, 1), got {value_at_1}.")
  elif not 0 < value_at_1 < 1:
    raise ValueError(f"`value_at_1` must be in (0, 1), got {value_at_1}.")

  if sigmoid == "gaussian":
    scale = math.sqrt(-2 * math.log(value_at_1))
    return jnp.exp(-0.5 * (x * scale) ** 2)
  if sigmoid == "hyperbolic":
    scale = math.acosh(1 / value_at_1)
    return 1 / jnp.cosh(x * scale)
  if sigmoid == "long_tail":
    scale = math.sqrt(1 / value_at_1 - 1)
    return 1 / ((x * scale) ** 2 + 1)
  if sigmoid == "reciprocal":
    scale = 1 / value_at_1 - 1
    return 1 / (jnp.abs(x) * scale + 1)
  if sigmoid == "cosine":
    scale = math.acos(2 * value_at_1 - 1) / math.pi
    scaled = x * scale
    return jnp.where(jnp.abs(scaled) < 1, (1 + jnp.cos(jnp.pi * scaled)) / 2, 0.0)
  if sigmoid == "linear":
    scaled = x * (1 - value_at_1)
    return jnp.where(jnp.abs(scaled) < 1, 1 - scaled, 0.0)
  if sigmoid == "quadratic":
    scaled = x * math.sqrt(1 - value_at_1)
    return jnp.where(jnp.abs(scaled) < 1, 1 - scaled ** 2, 0.0)
  if sigmoid == "tanh_squared":
    scale = math.atanh(math.sqrt(1 - value_at_1))
    return 1 - jnp.tanh(x * scale) ** 2
  raise ValueError(f"Unknown sigmoid {sigmoid!r}; valid: {', '.join(SIGMOIDS)}.")


def tolerance(x, bounds=(0.0, 0.0), margin: float = 0.0,
              sigmoid: str = "gaussian",
              value_at_margin: float = _DEFAULT_VALUE_AT_MARGIN):
  """Returns 1 where `x` lies inside `bounds`, a sigmoid falloff outside.

  Args:
    x: array of any shape (traced or concrete).
    bounds: inclusive `(lower, upper)`; may be infinite or equal.
    margin: distance at which the output has fallen to `value_at_margin`;
      0 makes the output a hard 0/1 indicator of `bounds`.
    sigmoid: one of `SIGMOIDS`.
    value_at_margin: output at distance `margin` from the nearest bound.

  Returns:
    An array like `x` with values in [0, 1].
  """
  lower, upper = bounds
  if lower > upper:
    raise ValueError("Lower bound must be <= upper bound.")
  if margin < 0:
    raise ValueError("`margin` must be non-negative.")
  x = jnp.asarray(x)
  in_bounds = (lower <= x) & (x <= upper)
  if margin == 0:
    return jnp.where(in_bounds, 1.0, 0.0)
  d = jnp.where(x < lower, lower - x, x - upper) / margin
  return jnp.where(in_bounds, 1.0, _sigmoid(d, value_at_margin, sigmoid))
