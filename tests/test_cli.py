"""The commands as a user meets them: clean stdout, help with defaults, one-paragraph
errors that end the process (run in subprocesses with a timeout)."""

import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.xdist_group("cli")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run(args, timeout=240, **env):
  """`python args…` from the repository root; (returncode, stdout, stderr)."""
  out = subprocess.run([sys.executable] + list(args), capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT,
                       env=dict(os.environ, JAX_PLATFORMS="cpu", **env))
  return out.returncode, out.stdout, out.stderr


def test_importing_the_package_prints_nothing_to_stdout():
  # mujoco-mjx prints "Failed to import warp: …" to stdout when warp is absent.
  code, stdout, stderr = run(["-c", "import dmcr_jax, train.loop"])
  assert code == 0, stderr[-2000:]
  assert stdout == ""
  assert "warp" not in stderr
