"""Files written whole or not at all, and JSON that stays valid."""

from __future__ import annotations

import math
import os
import tempfile
from typing import BinaryIO, Callable


def write_atomic(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> None:
  """Calls `write` on a temporary file beside `path`, then renames it to `path`:
  readers see the previous file or the new one, never a part (a crash while
  writing leaves the previous file and no temporary one). Makes the folder.

  Args:
    path: the file to (re)write.
    write: writes the contents to the binary file object it is given (e.g.
      ``lambda f: np.savez(f, x=x)``).
  """
  folder = os.path.dirname(os.fspath(path)) or "."
  os.makedirs(folder, exist_ok=True)
  fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
  try:
    with os.fdopen(fd, "wb") as f:
      write(f)
    os.replace(tmp, path)
  except BaseException:
    if os.path.exists(tmp):
      os.unlink(tmp)
    raise


def json_safe(tree):
  """`tree` (dicts, lists, numbers) with NaN and ±inf replaced by None, so that
  `json.dump(..., allow_nan=False)` writes valid JSON (null)."""
  if isinstance(tree, dict):
    return {k: json_safe(v) for k, v in tree.items()}
  if isinstance(tree, (list, tuple)):
    return [json_safe(v) for v in tree]
  if isinstance(tree, float) and not math.isfinite(tree):
    return None
  return tree
