"""The persistent XLA compilation cache of the command-line tools: `--compile-cache DIR`.

`dmcr-train`, `dmcr-evaluate` and `dmcr-sweep` take one shared option
(`add_arguments`): the folder where JAX keeps the executables it compiles, so that
a second process compiling the same program (the same task, sizes, flags, JAX
version and device) loads it instead of compiling it again. Default
(`default_dir`): $JAX_COMPILATION_CACHE_DIR when set, else
$XDG_CACHE_HOME/dmcr_jax/xla (~/.cache/dmcr_jax/xla); `--no-compile-cache` turns
it off. `use` sets it in JAX's config at a command's start, and in the
environment, which the processes the command starts inherit (the physics
workers, whose pool hands them the parent's settings anyway, and a local Ray
instance's workers). Only programs that take `MIN_COMPILE_TIME_S` or more to
compile are written (the many small ones recompile faster than they load), and
the folder is kept under `MAX_SIZE_BYTES` by JAX's least-recently-used eviction
(which needs the `filelock` package; without it the folder is unbounded). A
folder given by $JAX_COMPILATION_CACHE_DIR is the user's own JAX cache, maybe
shared with other programs: its size bound and minimum compile time are JAX's
settings there (JAX_COMPILATION_CACHE_MAX_SIZE,
JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS), not these. Nothing here runs at
import: the library and the benchmarks (which time compilation from empty)
use no cache unless their caller sets one.
"""

from __future__ import annotations

import argparse
import importlib.util
import os

ENV = "JAX_COMPILATION_CACHE_DIR"
"""The environment variable JAX reads its cache folder from (and the default)."""
MIN_COMPILE_TIME_S = 1.0
"""Programs compiled in less than this many seconds are not written."""
MAX_SIZE_BYTES = 10 * 2**30
"""The size the folder is kept under (10 GiB; least recently used entries go)."""


def default_dir(environ=None) -> str:
  """The cache folder when `--compile-cache` is not given: $JAX_COMPILATION_CACHE_DIR,
  else $XDG_CACHE_HOME/dmcr_jax/xla, else ~/.cache/dmcr_jax/xla."""
  environ = os.environ if environ is None else environ
  if environ.get(ENV):
    return environ[ENV]
  base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
  return os.path.join(base, "dmcr_jax", "xla")


def add_arguments(parser: argparse.ArgumentParser) -> None:
  """Adds `--compile-cache DIR` and `--no-compile-cache` (one or the other) to a
  command's parser (dests `compile_cache`, `no_compile_cache`)."""
  group = parser.add_mutually_exclusive_group()
  group.add_argument("--compile-cache", default=None, metavar="DIR",
                     help="persistent XLA compilation cache: a second process compiling "
                          f"the same programs loads them from here (default: ${ENV}, "
                          "else $XDG_CACHE_HOME/dmcr_jax/xla, i.e. ~/.cache/dmcr_jax/xla; "
                          f"programs compiled in {MIN_COMPILE_TIME_S:g} s or more, kept "
                          f"under {MAX_SIZE_BYTES / 2**30:g} GiB)")
  group.add_argument("--no-compile-cache", action="store_true",
                     help="compile everything afresh, writing no cache")


def chosen(args: argparse.Namespace, environ=None) -> str | None:
  """The cache folder a parsed command line asks for (`add_arguments`): None with
  `--no-compile-cache`, else `--compile-cache` or `default_dir`."""
  if getattr(args, "no_compile_cache", False):
    return None
  given = getattr(args, "compile_cache", None)
  return os.path.abspath(os.path.expanduser(given or default_dir(environ)))


def use(path: str | None, environ=None) -> str | None:
  """Points JAX's persistent compilation cache at `path` (None: turns it off) for
  this process and, through `environ` (default `os.environ`), the processes it
  starts; returns `path`.

  The folder is made if missing. Unless `path` is $JAX_COMPILATION_CACHE_DIR's
  (module doc), programs compiled in under `MIN_COMPILE_TIME_S` are not written
  and the folder is kept under `MAX_SIZE_BYTES` (when `filelock` is installed);
  a setting the environment already makes (JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS,
  JAX_COMPILATION_CACHE_MAX_SIZE) is kept. None sets no folder and removes
  $JAX_COMPILATION_CACHE_DIR from `environ`, so that no process started from here
  writes one either.
  """
  import jax
  from jax.experimental.compilation_cache import compilation_cache
  environ = os.environ if environ is None else environ
  compilation_cache.reset_cache()  # a cache opened before (another folder) is let go
  if path is None:
    jax.config.update("jax_compilation_cache_dir", None)
    environ.pop(ENV, None)
    return None
  os.makedirs(path, exist_ok=True)
  users = bool(environ.get(ENV)) and os.path.abspath(environ[ENV]) == os.path.abspath(path)
  if not users:
    settings = {"jax_persistent_cache_min_compile_time_secs":
                    ("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", MIN_COMPILE_TIME_S)}
    if importlib.util.find_spec("filelock") is not None:  # JAX's eviction locks with it
      settings["jax_compilation_cache_max_size"] = ("JAX_COMPILATION_CACHE_MAX_SIZE",
                                                    MAX_SIZE_BYTES)
    for name, (variable, value) in settings.items():
      if not environ.get(variable):
        jax.config.update(name, value)
        environ[variable] = str(value)
  jax.config.update("jax_compilation_cache_dir", path)
  environ[ENV] = path
  return path
