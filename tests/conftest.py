"""Shared test setup: headless GL for any MuJoCo rendering, quiet JAX on CPU.

Tiers: `pytest -m "not slow"` skips the tests marked slow (each over ~12 s on a
2-core CPU) for a fast developer run; CI runs every test. Tests marked full run a
whole command at its defaults and only with `--run-full`."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("JAX_PLATFORMS", "cpu")


def pytest_addoption(parser):
  parser.addoption("--run-full", action="store_true",
                   help="also run the tests marked full (a whole command at its "
                        "defaults, minutes each)")


def pytest_collection_modifyitems(config, items):
  if config.getoption("--run-full"):
    return
  import pytest
  skip = pytest.mark.skip(reason="a whole command at its defaults (minutes): pass "
                                 "--run-full to run it")
  for item in items:
    if "full" in item.keywords:
      item.add_marker(skip)
