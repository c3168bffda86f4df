"""The package's import: light at first, every public name there on first use."""

import subprocess
import sys

import pytest

import dmcr_jax
import dmcr_jax.visuals


def test_import_loads_neither_mjx_nor_the_envs():
  # A fresh interpreter: this one has imported everything already.
  code = ("import sys, dmcr_jax, dmcr_jax.visuals.pool; "
          "print(sorted(m for m in ('mujoco.mjx', 'dmcr_jax.env', 'dmcr_jax.adapters', "
          "'dmcr_jax.visuals.render_model') if m in sys.modules))")
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, check=True).stdout
  assert out.strip().splitlines()[-1] == "[]"


@pytest.mark.parametrize("package", [dmcr_jax, dmcr_jax.visuals], ids=lambda p: p.__name__)
def test_every_public_name_resolves_to_its_modules_object(package):
  import importlib
  for name in package.__all__:
    value = getattr(package, name)
    assert name in dir(package)
    module = package._LAZY.get(name)
    if module is not None:
      assert value is getattr(importlib.import_module(module), name)
  with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
    getattr(package, "no_such_name")
