"""Files written whole or not at all."""

from __future__ import annotations

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
