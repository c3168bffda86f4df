"""A fault-tolerant pool of worker processes that compute batches in shared memory.

`WorkerPool` is the process machinery under `RenderPool` (frames) and
`dmcr_jax.physics_pool.PhysicsPool` (physics): W worker processes, each
owning a fixed contiguous slice of the batch, read their inputs from shared-memory
arrays and write their outputs into a shared-memory array (no pickling of pixels).
Each worker builds its renderer once, from a picklable factory, in its own process
(and so its own GL context).

Faults are handled per call: a worker that dies (e.g. SIGKILL) is restarted and
its slice re-rendered; a worker that does not answer within `timeout` seconds is
killed, replaced and its slice re-rendered; a Python exception inside a worker is
raised in the caller as `WorkerError` carrying the worker's traceback. Since each
slice is written whole by exactly one successful worker run, a call returns
complete outputs with nothing lost or duplicated. `close()` (or leaving the
`with` block) stops every worker and unlinks every shared-memory segment.

Protocol of a worker's renderer (built by `factory(*args)` in the worker):
`renderer(inputs: dict[str, np.ndarray], out: np.ndarray) -> None` renders
`inputs[k][i]` into `out[i]` for every i of its slice. With `buffers=2` the
output is double-buffered: calls alternate between two output arrays and the
renderer is called as `renderer(inputs, out, prev)`, where `prev` holds the
previous call's output of the same rows. A renderer that reads only `prev` and
`inputs` stays idempotent, so a re-rendered slice (after a fault) gives the
same result — this is how frame stacks are built in the workers, and how the
physics workers keep their envs' state (each call steps `prev`'s state into `out`).

A call is `run(batch)`, or `submit(batch)` (returns at once) and later `wait()`,
so that the caller can work while the workers do.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing as mp
import os
import sys
import signal
import time
import traceback
from multiprocessing import connection, shared_memory
from typing import Any, Callable, Mapping, Sequence

import numpy as np


class WorkerError(RuntimeError):
  """An exception raised inside a worker (its traceback is in the message), or a
  worker that failed too often."""


@dataclasses.dataclass(frozen=True)
class ArraySpec:
  """Shape (without the batch axis) and dtype of one shared array."""
  shape: tuple[int, ...]
  dtype: str

  def nbytes(self, batch: int) -> int:
    return int(batch * np.prod(self.shape, dtype=np.int64) * np.dtype(self.dtype).itemsize)


def _attach(name: str, spec: ArraySpec, batch: int):
  # Spawned workers share the parent's resource tracker, so registering the
  # attached segment again is harmless; the parent alone unlinks it.
  shm = shared_memory.SharedMemory(name=name)
  return shm, np.ndarray((batch,) + spec.shape, spec.dtype, buffer=shm.buf)


@contextlib.contextmanager
def _main_module_hidden():
  """Starts spawned workers without re-running the caller's `__main__`.

  A spawned child normally re-imports the parent's main script, which would run
  a script's top level (e.g. `env = dmcr_jax.make(...)`) again in every worker
  unless it sits under `if __name__ == "__main__":`. The workers need nothing
  from `__main__` (their target and factory live in this package), so the
  script's path and module spec are hidden while a worker process is launched
  (the spawn preparation data is built synchronously inside `start()`).
  """
  main = sys.modules.get("__main__")
  if main is None:
    yield
    return
  saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if k in main.__dict__}
  main.__dict__.pop("__file__", None)
  main.__dict__["__spec__"] = None
  try:
    yield
  finally:
    main.__dict__.pop("__spec__", None)
    main.__dict__.update(saved)


@contextlib.contextmanager
def _environ(env: Mapping[str, str]):
  """`os.environ` updated with `env` while a worker is launched, so the spawned
  interpreter starts with them: MuJoCo and PyOpenGL pick their GL platform once, at
  import, and unpickling the worker's arguments imports them before
  `_worker_main` runs."""
  saved = {k: os.environ.get(k) for k in env}
  os.environ.update(env)
  try:
    yield
  finally:
    for k, v in saved.items():
      if v is None:
        os.environ.pop(k, None)
      else:
        os.environ[k] = v


def _worker_main(conn, factory, factory_args, in_names, in_specs, out_names, out_spec,
                 batch, env):
  """Entry point of a worker process: build the renderer, then serve calls.

  Workers ignore SIGINT and SIGTERM: Ctrl-C and `timeout` signal the whole process
  group, and the parent must be the one that decides (e.g. checkpoint, then close
  the pool). A worker still exits when its parent goes (its pipe reads EOF).
  """
  for sig in (signal.SIGINT, signal.SIGTERM):
    signal.signal(sig, signal.SIG_IGN)
  os.environ.update(env)
  segments = []
  try:
    inputs = {}
    for key, name in in_names.items():
      shm, arr = _attach(name, in_specs[key], batch)
      segments.append(shm)
      inputs[key] = arr
    outs = []
    for name in out_names:
      shm, arr = _attach(name, out_spec, batch)
      segments.append(shm)
      outs.append(arr)
    renderer = factory(*factory_args)
    conn.send(("ready", os.getpid()))
  except BaseException:  # noqa: BLE001 - reported to the parent
    conn.send(("error", traceback.format_exc()))
    return
  while True:
    try:
      msg = conn.recv()
    except EOFError:
      break
    if msg[0] == "stop":
      break
    _, call_id, start, stop, cur = msg
    try:
      args = [outs[cur][start:stop]]
      if len(outs) == 2:
        args.append(outs[1 - cur][start:stop])
      renderer({k: v[start:stop] for k, v in inputs.items()}, *args)
      conn.send(("done", call_id))
    except BaseException:  # noqa: BLE001 - reported to the parent
      conn.send(("error", traceback.format_exc()))
  del inputs, outs
  for s in segments:
    s.close()


def slice_bounds(batch: int, workers: int) -> list[tuple[int, int]]:
  """[start, stop) of the contiguous slice of `batch` rows that each of `workers`
  workers owns (`WorkerPool.slices`): sizes differ by at most one."""
  bounds = np.linspace(0, batch, workers + 1).round().astype(int)
  return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


class WorkerPool:
  """W processes rendering fixed slices of a batch into shared memory.

  Args:
    factory: picklable callable building the per-worker renderer.
    factory_args: its arguments (picklable).
    inputs: name -> `ArraySpec` of each per-env input.
    output: `ArraySpec` of one env's output.
    max_batch: the largest batch a call may pass.
    workers: number of processes (≥ 1).
    timeout: seconds a worker may take for one slice before it is replaced.
    start_timeout: seconds a worker may take to start (imports, GL context,
      building its renderer).
    max_retries: restarts per slice within one call before the call fails.
    env: environment variables set in each worker before the factory runs.
    worker_env: per-worker additions to `env`: worker w (and its replacements)
      also gets `worker_env[w % len(worker_env)]`.
    worker_args: per-worker factory arguments after `factory_args`: worker w
      (and its replacements) is built by `factory(*factory_args, *worker_args[w])`.
    buffers: 1, or 2 for double-buffered outputs (see the module docstring).
    kind: what the workers do, for process names and error messages ("render",
      "physics").
  """

  def __init__(self, factory: Callable[..., Any], factory_args: Sequence[Any],
               inputs: Mapping[str, ArraySpec], output: ArraySpec, max_batch: int,
               workers: int, timeout: float = 120.0, start_timeout: float = 600.0,
               max_retries: int = 3,
               env: Mapping[str, str] | None = None, buffers: int = 1,
               kind: str = "render", worker_env: Sequence[Mapping[str, str]] = (),
               worker_args: Sequence[Sequence[Any]] = ()):
    if int(workers) < 1:
      raise ValueError(f"workers must be >= 1, got {workers}")
    if int(max_batch) < 1:
      raise ValueError(f"max_batch must be >= 1, got {max_batch}")
    if buffers not in (1, 2):
      raise ValueError(f"buffers must be 1 or 2, got {buffers}")
    if worker_args and len(worker_args) != int(workers):
      raise ValueError(f"worker_args must have one entry per worker ({workers}), got "
                       f"{len(worker_args)}")
    self._factory, self._factory_args = factory, tuple(factory_args)
    self._in_specs = dict(inputs)
    self._out_spec = output
    self.max_batch = int(max_batch)
    self.num_workers = int(workers)
    self.timeout = float(timeout)
    self.start_timeout = float(start_timeout)
    self.max_retries = int(max_retries)
    self._env = dict(env or {})
    self._worker_env = [dict(e) for e in worker_env]
    self._worker_args = [tuple(a) for a in worker_args]
    self._ctx = mp.get_context("spawn")
    self._segments: list[shared_memory.SharedMemory] = []
    self._procs: list[Any] = [None] * self.num_workers
    self._conns: list[Any] = [None] * self.num_workers
    self._call_id = 0
    self._pending = None
    self.kind = kind
    self.restarts = 0
    self._closed = False
    try:
      self.inputs = {k: self._alloc(s) for k, s in self._in_specs.items()}
      self._in_names = {k: self._segments[i].name for i, k in enumerate(self._in_specs)}
      self._outputs = [self._alloc(output) for _ in range(buffers)]
      self._out_names = [shm.name for shm in self._segments[-buffers:]]
      self._cur = 0
      for w in range(self.num_workers):
        self._start(w)
      for w in range(self.num_workers):
        self._await_ready(w)
    except BaseException:
      self.close()
      raise

  # Lifecycle -------------------------------------------------------------------

  def _alloc(self, spec: ArraySpec) -> np.ndarray:
    shm = shared_memory.SharedMemory(create=True, size=max(1, spec.nbytes(self.max_batch)))
    self._segments.append(shm)
    return np.ndarray((self.max_batch,) + spec.shape, spec.dtype, buffer=shm.buf)

  def _start(self, w: int) -> None:
    parent, child = self._ctx.Pipe()
    env = dict(self._env)
    if self._worker_env:
      env.update(self._worker_env[w % len(self._worker_env)])
    proc = self._ctx.Process(
        target=_worker_main, daemon=True, name=f"dmcr-{self.kind}-{w}",
        args=(child, self._factory,
              self._factory_args + (self._worker_args[w] if self._worker_args else ()),
              self._in_names, self._in_specs,
              self._out_names, self._out_spec, self.max_batch, env))
    with _main_module_hidden(), _environ(env):
      proc.start()
    child.close()
    self._procs[w], self._conns[w] = proc, parent

  def _await_ready(self, w: int) -> None:
    conn, proc = self._conns[w], self._procs[w]
    ready = connection.wait([conn, proc.sentinel], timeout=self.start_timeout)
    if conn in ready:
      try:
        msg = conn.recv()
      except EOFError:
        msg = ("error", f"worker {w} exited during start-up (code {proc.exitcode})")
      if msg[0] == "ready":
        return
      raise WorkerError(f"{self.kind} worker {w} failed to start:\n{msg[1]}")
    if not ready:
      raise WorkerError(f"{self.kind} worker {w} did not start within {self.start_timeout} s")
    raise WorkerError(f"{self.kind} worker {w} exited during start-up (code {proc.exitcode})")

  def _kill(self, w: int) -> None:
    proc, conn = self._procs[w], self._conns[w]
    if conn is not None:
      conn.close()
    if proc is not None:
      if proc.is_alive():
        proc.kill()
      proc.join(5)
    self._procs[w] = self._conns[w] = None

  def _replace(self, w: int) -> None:
    self._kill(w)
    self._start(w)
    self._await_ready(w)
    self.restarts += 1

  @property
  def pids(self) -> list[int]:
    """Process ids of the current workers."""
    return [p.pid for p in self._procs if p is not None]

  def close(self) -> None:
    """Stops every worker and unlinks every shared-memory segment (idempotent)."""
    if self._closed:
      return
    self._closed = True
    for w, conn in enumerate(self._conns):
      if conn is not None:
        try:
          conn.send(("stop",))
        except (OSError, BrokenPipeError):
          pass
    for w, proc in enumerate(self._procs):
      if proc is not None:
        proc.join(2)
      self._kill(w)
    self.inputs = {}
    self._outputs = []
    for shm in self._segments:
      try:
        shm.close()
        shm.unlink()
      except FileNotFoundError:
        pass
    self._segments = []

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def __del__(self):
    try:
      self.close()
    except Exception:  # noqa: BLE001 - interpreter shutdown
      pass

  @property
  def output(self) -> np.ndarray | None:
    """The output array of the current call (None once closed)."""
    return self._outputs[self._cur] if self._outputs else None

  # Calls -------------------------------------------------------------------------

  def slices(self, batch: int) -> list[tuple[int, int]]:
    """The fixed contiguous slice of a `batch` that each worker owns."""
    return slice_bounds(batch, self.num_workers)

  def run(self, batch: int) -> np.ndarray:
    """Renders envs [0, batch) from `self.inputs` into `self.output[:batch]`
    (`submit`, then `wait`).

    Returns:
      A view of the output rows (valid until the next call; with two buffers,
      until the call after next, whose `prev` it is).
    """
    self.submit(batch)
    return self.wait()

  def submit(self, batch: int) -> None:
    """Sends every worker its slice of envs [0, batch) and returns at once; `wait`
    completes the call. `self.inputs` must not change in between."""
    if self._closed:
      raise RuntimeError("the pool is closed")
    if self._pending is not None:
      raise RuntimeError("submit() called twice: call wait() first")
    if not 1 <= batch <= self.max_batch:
      raise ValueError(f"batch must be in [1, {self.max_batch}], got {batch}")
    self._call_id += 1
    self._cur = (self._call_id - 1) % len(self._outputs)
    pending = {w: s for w, s in enumerate(self.slices(batch)) if s[1] > s[0]}
    for w, (a, b) in pending.items():
      self._send(w, a, b)
    self._pending = (batch, pending)

  def wait(self) -> np.ndarray:
    """Waits for the call `submit` began (replacing dead or hung workers and
    resending their slices); returns `run`'s view of the output rows.

    Raises:
      WorkerError: a worker raised, or failed more than `max_retries` times.
    """
    if self._pending is None:
      raise RuntimeError("wait() without a submitted call")
    (batch, pending), self._pending = self._pending, None
    tries = {w: 0 for w in pending}
    deadline = {w: time.monotonic() + self.timeout for w in pending}
    while pending:
      waitables = {self._conns[w]: w for w in pending}
      waitables.update({self._procs[w].sentinel: w for w in pending})
      left = min(deadline[w] for w in pending) - time.monotonic()
      ready = connection.wait(list(waitables), timeout=max(0.0, left))
      now = time.monotonic()
      for w in [w for w in pending if deadline[w] <= now and
                self._conns[w] not in ready and self._procs[w].sentinel not in ready]:
        self._retry(w, pending, tries, "timed out")  # hung: replace and resend
        deadline[w] = time.monotonic() + self.timeout
      seen = set()
      for obj in ready:
        w = waitables[obj]
        current = (self._conns[w], self._procs[w].sentinel) if w in pending else ()
        if w in seen or obj not in current:
          continue  # finished, handled this round, or a replaced worker's handle
        seen.add(w)
        conn = self._conns[w]
        msg = None
        if conn.poll():
          try:
            msg = conn.recv()
          except (EOFError, OSError):
            msg = None
        if msg is None:
          self._retry(w, pending, tries, "died")
          deadline[w] = time.monotonic() + self.timeout
        elif msg[0] == "done" and msg[1] == self._call_id:
          del pending[w]
        elif msg[0] == "error":
          for v in pending:  # let the others finish so the pool stays consistent
            if v != w:
              self._drain(v)
          raise WorkerError(f"{self.kind} worker {w} raised:\n{msg[1]}")
    return self.output[:batch]

  def _send(self, w: int, a: int, b: int) -> None:
    try:
      self._conns[w].send(("render", self._call_id, a, b, self._cur))
    except (BrokenPipeError, ConnectionResetError):
      pass  # the worker died before this call: its sentinel triggers the retry

  def _retry(self, w: int, pending: dict, tries: dict, why: str) -> None:
    tries[w] += 1
    if tries[w] > self.max_retries:
      raise WorkerError(f"{self.kind} worker {w} {why} {tries[w]} times in one call")
    self._replace(w)
    self._send(w, *pending[w])

  def _drain(self, w: int) -> None:
    """Waits for worker w's reply to the current call (or replaces it)."""
    conn, proc = self._conns[w], self._procs[w]
    ready = connection.wait([conn, proc.sentinel], timeout=self.timeout)
    if conn in ready:
      try:
        conn.recv()
        return
      except (EOFError, OSError):
        pass
    self._replace(w)


class OwnsWorkerPool:
  """What a class built on a `WorkerPool` (kept as `self._pool`) exposes of it:
  `restarts`, `pids`, `close()` and the `with` block."""

  _pool: WorkerPool

  @property
  def restarts(self) -> int:
    """Workers replaced so far (killed or hung)."""
    return self._pool.restarts

  @property
  def pids(self) -> list[int]:
    """Process ids of the current workers."""
    return self._pool.pids

  def close(self) -> None:
    """Stops the workers and frees shared memory (idempotent)."""
    self._pool.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()
