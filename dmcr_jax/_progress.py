"""Progress on stderr: a tqdm bar on a terminal, plain lines into a log file.

tqdm redraws its bar with carriage returns; written into a redirected stderr
(a log file) every redraw stays there. `progress_bar` gives a bar only when
stderr is a terminal; without one a caller prints a plain line per step of its
own (`dmcr-train` every few percent, `dmcr-evaluate` per block).
"""

from __future__ import annotations

import sys


def progress_bar(progress: bool | None, **tqdm_options):
  """A tqdm bar on stderr when `progress` is true and stderr is a terminal, else None.

  Args:
    progress: whether progress is shown at all.
    **tqdm_options: tqdm's (total, initial, desc, unit, …).
  """
  if not progress or not sys.stderr.isatty():
    return None
  from tqdm.auto import tqdm
  return tqdm(**tqdm_options)
