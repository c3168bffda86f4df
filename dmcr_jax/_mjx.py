"""`mujoco.mjx` without the notices it prints to stdout (`dmcr_jax`'s docstring).

mujoco-mjx prints "Failed to import warp: No module named 'warp'" to stdout when
the optional `warp` package is absent. The package's modules import `mjx` from
here: the first import runs with stdout captured, the warp notices are dropped and
any other line goes to stderr.
"""

import contextlib
import io
import sys

if "mujoco.mjx" not in sys.modules:
  _captured = io.StringIO()
  with contextlib.redirect_stdout(_captured):
    import mujoco.mjx  # noqa: F401
  for _line in _captured.getvalue().splitlines():
    if "No module named 'warp'" not in _line:
      print(_line, file=sys.stderr)

from mujoco import mjx  # noqa: E402

__all__ = ["mjx"]
