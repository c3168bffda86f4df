"""Toy worker renderers for the WorkerPool tests (imported by spawned workers)."""

import os
import signal
import time


KILL, HANG, RAISE, SLOW = 1, 2, 3, 4
SLOW_S = 3.0
"""Seconds a SLOW env takes (busy, but the worker's heartbeat goes on)."""


class ToyRenderer:
  """Writes `value + 1` into every output element; fault modes keyed by a marker file."""

  def __init__(self, marker: str):
    self.marker = marker

  def _fault_once(self) -> bool:
    try:
      os.remove(self.marker)  # only the first worker to see the marker faults
      return True
    except FileNotFoundError:
      return False

  def __call__(self, inputs, out):
    for i in range(len(out)):
      mode = int(inputs["mode"][i])
      if mode and self._fault_once():
        if mode == KILL:
          os.kill(os.getpid(), signal.SIGKILL)
        elif mode == HANG:
          time.sleep(3600)
        elif mode == SLOW:
          time.sleep(SLOW_S)
      if mode == RAISE:
        raise ValueError(f"bad env value {inputs['value'][i]}")
      out[i] = inputs["value"][i] + 1


IMPORT_ENV = os.environ.get("DMCR_POOL_TEST_VAR")
"""The variable as this module saw it when a worker imported it (unpickling the
factory, before the worker's own code runs)."""


class ImportEnvRenderer:
  """Writes 1 where the worker's imports saw DMCR_POOL_TEST_VAR == "set", else 0."""

  def __call__(self, inputs, out):
    out[:] = float(IMPORT_ENV == "set")


class ArgValueRenderer:
  """Writes the value it was built with (per-worker factory arguments)."""

  def __init__(self, value: float):
    self.value = value

  def __call__(self, inputs, out):
    out[:] = self.value


class EnvValueRenderer:
  """Writes float(DMCR_POOL_TEST_VAR) as the worker sees it (per-worker environments)."""

  def __call__(self, inputs, out):
    out[:] = float(os.environ["DMCR_POOL_TEST_VAR"])


class GatedRenderer(ToyRenderer):
  """A ToyRenderer whose start waits until the file `gate` exists (at most 60 s)."""

  def __init__(self, marker: str, gate: str):
    super().__init__(marker)
    deadline = time.monotonic() + 60
    while not os.path.exists(gate) and time.monotonic() < deadline:
      time.sleep(0.05)


class FailingStartRenderer:
  """A renderer whose construction raises (a worker that cannot start)."""

  def __init__(self):
    raise RuntimeError("no renderer here")

  def __call__(self, inputs, out):  # never reached
    out[:] = 0
