"""Names of a package imported from their modules on first use (PEP 562).

A package lists where each of its public names lives and binds the two functions
`lazy_names` returns as its module-level ``__getattr__`` and ``__dir__``: importing
the package stays light (a render-pool worker process imports `dmcr_jax` to reach
its own modules without loading MJX, the envs or JAX), and a name's module is
imported the first time the name is read.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable


def lazy_names(package: str, where: dict[str, str], namespace: dict[str, Any]
               ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
  """The ``__getattr__`` and ``__dir__`` of a package whose names load on first use.

  Args:
    package: the package's ``__name__`` (for the AttributeError's message).
    where: each lazily imported name → the module it lives in.
    namespace: the package's ``globals()``; a name read once is stored there, so
      later reads do not come back here.

  Returns:
    (__getattr__, __dir__): ``__getattr__(name)`` imports ``where[name]`` and
    returns its attribute (AttributeError for a name not in `where`);
    ``__dir__()`` lists the package's globals and the lazy names.
  """
  def __getattr__(name: str) -> Any:
    module = where.get(name)
    if module is None:
      raise AttributeError(f"module {package!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    namespace[name] = value
    return value

  def __dir__() -> list[str]:
    return sorted(set(namespace) | set(where))

  return __getattr__, __dir__
