"""The augmentation registry: built-in names, user registration and import paths.

`get(name)` returns the augmentation a name means: a built-in (`NAMES`), one added
with `register`, a ``"package.module:function"`` import path (`load`), or a
``+``-joined sequence of them (`Composed`). `from_function` wraps a user's function
of one sample; `check` runs the learner's properties on real observations.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import os
import re
import sys
from typing import Callable

import jax

from dmcr_jax.augment_color import color_jitter, network_randomization
from dmcr_jax.augment_core import Augmentation, Composed, identity
from dmcr_jax.augment_spatial import (cutout_color, drq, rad, rotate, translate,
                                      vertical_flip, window)

# --------------------------------------------------------------------------- #
# The registry.
# --------------------------------------------------------------------------- #

_FACTORIES: dict[str, Callable[[], Augmentation]] = {
    "none": identity,
    "rad": rad,
    "cutout_color": cutout_color,
    "drq": drq,
    "drq_no_noise": lambda: drq(4, 0.0, name="drq_no_noise"),
    "large_drq": lambda: drq(12, name="large_drq"),
    "large_drq_no_noise": lambda: drq(12, 0.0, name="large_drq_no_noise"),
    "translate": translate,
    "large_translate": lambda: translate(12, name="large_translate"),
    "rotate": rotate,
    "vertical_flip": vertical_flip,
    "window": window,
    "cj": color_jitter,
    "nr": network_randomization,
}

NAMES: tuple[str, ...] = tuple(_FACTORIES) + ("cj+drq", "nr+drq")
"""Every registered name: ``"none"``, the appendix's eleven augmentations, Color
Jitter (``"cj"``), Network Randomization (``"nr"``), and the paper's SAC+CJ+AUG and
SAC+NR+AUG pipelines (``"cj+drq"``, ``"nr+drq"``). `get` also accepts any other
``+``-joined sequence of the single names."""


SampleAugFn = Callable[[jax.Array, jax.Array], jax.Array]
"""A user's augmentation of ONE sample: ``fn(key, image) -> image`` (`from_function`)."""

_USER: dict[str, Augmentation | Composed] = {}  # `register`ed names
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*\Z")
_SPEC = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_][\w.]*\Z")


def from_function(fn: SampleAugFn | Augmentation | Composed,
                  name: str | None = None) -> Augmentation | Composed:
  """An augmentation from a function of ONE sample, the built-ins' convention.

  `fn(key, image) -> image`: `key` is a `jax.random` key, `image` ONE uint8
  observation (H, W, 3·stack), RGB frames stacked on the last axis oldest
  first; it returns a uint8 image of the same shape. It must be pure and
  traceable (`jax.numpy` / `jax.lax` operations; no NumPy randomness, no Python
  side effects), draw all its randomness from `key`, and use the same draw for
  every frame of the stack. Like every built-in, the result calls it per
  sample under `jax.vmap`: sample ``i`` of a batch gets ``fold_in(key, i)``,
  and every array of a pytree the same keys, so ``aug(key, (obs, next_obs))``
  gives a sample's o and o′ the same draw by construction. `check` tests the
  rest (dtype, shape, determinism, jit, vmap, frames, range).

  Args:
    fn: the per-sample function; or an `Augmentation` / `Composed` (e.g.
      ``drq(pad=6)``), returned as it is, renamed if `name` is given.
    name: the augmentation's name (default: `fn`'s ``__name__``).

  Returns:
    An `Augmentation` (`Augmentation.one(key, image)` is ``fn(key, image)``).

  Raises:
    TypeError: `fn` is not callable.
  """
  if isinstance(fn, (Augmentation, Composed)):
    return fn if name is None else dataclasses.replace(fn, name=name)
  if not callable(fn):
    raise TypeError(f"an augmentation is a function fn(key, image) -> image, got "
                    f"{type(fn).__name__} {fn!r}")
  name = name or getattr(fn, "__name__", type(fn).__name__)
  return Augmentation(name, lambda key, hw: {"key": key},
                      lambda p, x: fn(p["key"], x))


def register(name: str, fn: SampleAugFn | Augmentation | Composed
             ) -> Augmentation | Composed:
  """Registers `fn` as augmentation `name` for `get`, ``"name+drq"`` and training.

  After ``register("mine", fn)``, ``get("mine")``, ``get("mine+drq")``,
  ``SACConfig(aug="drq,mine+drq")`` and ``dmcr-train --aug mine`` (in a process that
  registered it) accept the name. Registering a name again replaces it for later
  `get` calls (functions already compiled keep the old one).

  Args:
    name: letters, digits, ``_``, ``.`` and ``-``, starting with a letter or
      ``_`` (no ``+``, ``,`` or ``:``, which compose, list and import), not a
      built-in name (`NAMES`).
    fn: ``fn(key, image) -> image`` on ONE uint8 (H, W, 3·stack) sample (see
      `from_function`), or an `Augmentation` / `Composed`.

  Returns:
    The registered augmentation (what ``get(name)`` returns).

  Raises:
    ValueError: a malformed or built-in name.
    TypeError: `fn` is not callable.
  """
  if not isinstance(name, str) or not _NAME.match(name):
    raise ValueError(f"augmentation name {name!r}: use letters, digits, '_', '.' and "
                     "'-', starting with a letter or '_' ('+' composes, ',' lists "
                     "and ':' imports)")
  if name in _FACTORIES or name in NAMES:
    raise ValueError(f"{name!r} is a built-in augmentation; pick another name "
                     f"(built-ins: {', '.join(NAMES)})")
  aug = from_function(fn, name)
  _USER[name] = aug
  get.cache_clear()
  return aug


def unregister(name: str) -> None:
  """Forgets a `register`ed name (KeyError if it is not one)."""
  del _USER[name]
  get.cache_clear()


def registered() -> tuple[str, ...]:
  """The names added with `register`, in registration order."""
  return tuple(_USER)


def load(spec: str) -> Augmentation | Composed:
  """Imports the augmentation that ``"package.module:function"`` names.

  The module is imported as ``import package.module`` would, with the current
  directory searched first (as ``python -m`` does), so a module beside you, or
  in an installed package, is found. The attribute is a per-sample function
  (`from_function`), or an `Augmentation` / `Composed`; the result is named
  `spec`, so run configs that store it import it again (``--resume``,
  `evaluate`). `get` calls this for every name with a ``:``.

  Args:
    spec: ``module.path:attribute`` (the attribute may be dotted).

  Returns:
    The augmentation, named `spec`.

  Raises:
    ValueError: a one-paragraph message when the module cannot be imported (or
      raises while importing), has no such attribute, or it is not callable.
  """
  module_name, _, attr = spec.partition(":")
  usage = ("The form is package.module:function, e.g. "
           "examples.augmentations:hue_rotation, for a function fn(key, image) -> "
           "image of ONE uint8 (H, W, 3·stack) sample (see dmcr_jax.augment."
           "from_function)")
  if os.getcwd() not in sys.path and "" not in sys.path:
    sys.path.insert(0, os.getcwd())
  try:
    module = importlib.import_module(module_name)
  except Exception as e:  # noqa: BLE001 - the user's module may raise anything
    missing = isinstance(e, ModuleNotFoundError) and (
        e.name and (module_name == e.name or module_name.startswith(e.name + ".")))
    hint = (f"Python searched the current directory ({os.getcwd()}) and sys.path: "
            "run from the folder that holds the module (or its package), put that "
            "folder on PYTHONPATH, or install its package, and check the spelling. "
            if missing else "The module itself failed while importing; fix it (try "
            f"python -c 'import {module_name}'). ")
    raise ValueError(f"augmentation {spec!r}: cannot import module {module_name!r} "
                     f"({type(e).__name__}: {e}). {hint}{usage}.") from None
  obj = module
  for part in attr.split("."):
    if not hasattr(obj, part):
      public = sorted(n for n, v in vars(module).items()
                      if callable(v) and not n.startswith("_")
                      and getattr(v, "__module__", module_name) == module_name)
      raise ValueError(f"augmentation {spec!r}: module {module_name!r} "
                       f"({getattr(module, '__file__', '?')}) has no attribute {attr!r}; "
                       f"its functions: {', '.join(public) or 'none'}. {usage}.")
    obj = getattr(obj, part)
  try:
    return from_function(obj, spec)
  except TypeError as e:
    raise ValueError(f"augmentation {spec!r}: {e}. {usage}.") from None


@functools.lru_cache(maxsize=None)
def get(name: str) -> Augmentation | Composed:
  """The augmentation registered as `name`; ``"a+b"`` composes a then b.

  Results are cached, so repeated calls return the same (already compiled)
  function.

  Args:
    name: one of `NAMES`, a `register`ed name, a ``"package.module:function"``
      import path (`load`), or ``+``-joined such names (e.g. ``"cj+drq"``,
      ``"examples.augmentations:hue_rotation+drq"``).

  Returns:
    A callable ``aug(key, images) -> images`` (`Augmentation` or `Composed`).

  Raises:
    ValueError: for an unknown name, listing the valid ones; for an import path
      that cannot be imported (`load`'s message).
  """
  parts = name.split("+")
  unknown = [p for p in parts
             if p not in _FACTORIES and p not in _USER and not _SPEC.match(p)]
  if unknown:
    mine = f"; registered: {', '.join(_USER)}" if _USER else ""
    raise ValueError(f"unknown augmentation {name!r} (unknown part(s): "
                     f"{', '.join(map(repr, unknown))}); valid names: "
                     f"{', '.join(NAMES)}{mine}; or package.module:function for your "
                     "own (dmcr_jax.augment.load); or '+'-join single names")
  if len(parts) == 1:
    if name in _USER:
      return _USER[name]
    return load(name) if ":" in name else _FACTORIES[name]()
  return Composed(name, tuple(get(p) for p in parts))


def check(aug, **kwargs):
  """Checks an augmentation's properties on real observations; see
  `dmcr_jax.augment_check.check` (its arguments and the properties it runs)."""
  from dmcr_jax import augment_check
  return augment_check.check(aug, **kwargs)
