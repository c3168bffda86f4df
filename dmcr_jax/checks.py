"""Argument checks shared by the env, the render pool, the seed ranges and the learner.

Each raises a `ValueError` that names the argument and the value it got, so a bad
call fails at the boundary with a message a user can act on.
"""

from __future__ import annotations

import numpy as np


def positive_int(name: str, value) -> int:
  """`value` as an int if it is a positive integer (not a bool), else ValueError."""
  if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
    raise ValueError(f"{name} must be a positive int, got {value!r}")
  return int(value)
