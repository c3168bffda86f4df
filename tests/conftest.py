"""Shared test setup: headless GL for any MuJoCo rendering, quiet JAX on CPU.

Tiers: `pytest -m "not slow"` skips the tests marked slow (each over ~7 s on a
2-core CPU, or needing a module fixture that is) for a fast developer run; CI
runs every test. Tests marked full run a whole command at its defaults and only
with `--run-full`. One JAX compilation cache serves the whole session
(`share_compilations`)."""

import atexit
import gc
import os
import shutil
import sys
import tempfile

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("JAX_PLATFORMS", "cpu")


def share_compilations() -> None:
  """Points JAX's persistent compilation cache at one folder for the whole session.

  Many tests compile the same physics, renderer and learner (same task, sizes and
  flags) in different modules, xdist workers and subprocesses; with one cache an
  identical XLA program compiles once. Set before JAX is imported and inherited
  through the environment by xdist workers and subprocesses. A folder the user
  set (JAX_COMPILATION_CACHE_DIR) is kept; else a fresh one, removed at exit by
  the process that made it. Only programs that take a second or more to compile
  are written: the thousands of small eager-op programs recompile faster than
  they serialize, and each write is a call into XLA's executable serializer.
  """
  if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    folder = tempfile.mkdtemp(prefix="dmcr-jax-tests-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
  os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")


share_compilations()


def pytest_addoption(parser):
  parser.addoption("--run-full", action="store_true",
                   help="also run the tests marked full (a whole command at its "
                        "defaults, minutes each)")


def _scope(item):
  """An item's module and xdist group: the tests that share compiled programs."""
  mark = item.get_closest_marker("xdist_group")
  return item.nodeid.split("::", 1)[0], mark.args[0] if mark and mark.args else None


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
  """After the last test of a module or xdist group (its fixtures finalized), drops
  JAX's in-memory compilations: a worker would otherwise keep every program the
  suite compiled (gigabytes by the end). Later tests that need one again load it
  from the session's compilation cache."""
  yield
  if "jax" in sys.modules and (nextitem is None or _scope(item) != _scope(nextitem)):
    sys.modules["jax"].clear_caches()
    gc.collect()


def pytest_collection_modifyitems(config, items):
  if config.getoption("--run-full"):
    return
  skip = pytest.mark.skip(reason="a whole command at its defaults (minutes): pass "
                                 "--run-full to run it")
  for item in items:
    if "full" in item.keywords:
      item.add_marker(skip)
