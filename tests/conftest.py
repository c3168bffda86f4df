"""Shared test setup: headless GL for any MuJoCo rendering, quiet JAX on CPU."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("JAX_PLATFORMS", "cpu")


def pytest_addoption(parser):
  parser.addoption("--run-slow", action="store_true",
                   help="also run the tests marked slow (minutes each)")


def pytest_collection_modifyitems(config, items):
  if config.getoption("--run-slow"):
    return
  import pytest
  skip = pytest.mark.skip(reason="slow (minutes): pass --run-slow to run it")
  for item in items:
    if "slow" in item.keywords:
      item.add_marker(skip)
