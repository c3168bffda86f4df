"""A fault-tolerant pool of worker processes that compute batches in shared memory.

`WorkerPool` is the process machinery under `RenderPool` (frames) and
`dmcr_jax.physics_pool.PhysicsPool` (physics): W worker processes, each
owning a fixed contiguous slice of the batch, read their inputs from shared-memory
arrays and write their outputs into a shared-memory array (no pickling of pixels).
Each worker builds its renderer once, from a picklable factory, in its own process
(and so its own GL context).

Faults are handled per call: a worker that dies (e.g. SIGKILL) is restarted and
its slice re-rendered; a worker that is unresponsive — sends no heartbeat for
`timeout` seconds (stopped, frozen, or stuck holding Python's lock) or is still
busy after `call_timeout` seconds — is announced on stderr, killed, replaced and
its slice re-rendered; a Python exception inside a worker is raised in the caller
as `WorkerError` carrying the worker's traceback. Since each slice is written
whole by exactly one successful worker run, a call returns complete outputs with
nothing lost or duplicated. A busy worker's heartbeat comes from a thread of its
own every `heartbeat_interval(timeout)` seconds; `timeout` defaults to
`default_timeout()` (`DMCR_WORKER_TIMEOUT`, else `DEFAULT_TIMEOUT`).

Shutdown: `close()` (or leaving the `with` block) stops every worker and unlinks
every shared-memory segment. A pool that is never closed is closed at
interpreter exit (an `atexit` hook that runs before multiprocessing's own, which
would otherwise wait forever for workers that ignore SIGTERM), so a script that
ends, raises or is interrupted (Ctrl-C) without `close()` exits promptly and
leaves no worker and no segment. A SIGTERM to the main process raises
`SystemExit(143)` in its main thread (installed with the first pool, only where
SIGTERM still has its default action), so `finally` blocks and the exit hook
run; the main thread takes it once it is back in Python (a long native call,
e.g. an XLA compilation, finishes first). Workers leave when their pipe closes,
so a parent killed outright (SIGKILL) leaves no worker either.

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
so that the caller can work while the workers do. Calls on disjoint rows
(`submit(batch, start)`) may be in flight together: each worker takes its slices
in the order they were submitted, so the workers go from one call's rows straight
to the next one's while the caller collects the first (`wait(start)`).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import multiprocessing as mp
import multiprocessing.util  # noqa: F401 - its exit hook must be registered before ours
import os
import sys
import signal
import threading
import time
import traceback
import weakref
from multiprocessing import connection, shared_memory
from typing import Any, Callable, Mapping, Sequence

import numpy as np

DEFAULT_TIMEOUT = 10.0
"""Seconds a busy worker may send no heartbeat before it is replaced (the default
of `default_timeout()`)."""
TIMEOUT_VARIABLE = "DMCR_WORKER_TIMEOUT"
"""Environment variable that sets the default hung-worker timeout, in seconds."""
DEFAULT_CALL_TIMEOUT = 300.0
"""Seconds a worker may stay busy with one call, heartbeat or not, before it is
replaced (a worker blocked in native code, e.g. a GL driver, still beats)."""
CLOSE_GRACE = 2.0
"""Seconds `close()` waits for the workers to stop before it kills them."""


def check_timeout(name: str, value) -> float:
  """`value` as a float number of seconds > 0, else ValueError naming `name`."""
  try:
    seconds = float(value)
  except (TypeError, ValueError):
    seconds = float("nan")
  if isinstance(value, bool) or not seconds > 0 or seconds == float("inf"):
    raise ValueError(f"{name} must be a number of seconds > 0, got {value!r}")
  return seconds


def default_timeout() -> float:
  """The hung-worker timeout in seconds: `DMCR_WORKER_TIMEOUT` if set, else
  `DEFAULT_TIMEOUT`; ValueError when the variable is not a number > 0."""
  value = os.environ.get(TIMEOUT_VARIABLE)
  return DEFAULT_TIMEOUT if value in (None, "") else check_timeout(TIMEOUT_VARIABLE, value)


def heartbeat_interval(timeout: float) -> float:
  """Seconds between a busy worker's heartbeats for a pool's `timeout`: five per
  timeout, at most one a second."""
  return min(1.0, timeout / 5)


def _announce(message: str) -> None:
  print(f"dmcr_jax: {message}", file=sys.stderr, flush=True)


_LIVE: "weakref.WeakSet[WorkerPool]" = weakref.WeakSet()
"""Every pool not yet closed, closed by `_close_live` at exit."""
_EXITING = False


def _close_live() -> None:
  """Closes every live pool (the exit hook; registered after multiprocessing's,
  so it runs first)."""
  global _EXITING
  _EXITING = True
  pools = list(_LIVE)
  for pool in pools:   # every worker stops at once, then each pool is closed
    pool._stop_workers()
  for pool in pools:
    try:
      pool.close()
    except Exception:  # noqa: BLE001 - the others still close
      pass


atexit.register(_close_live)


def _exit_on_sigterm(signum, frame) -> None:
  """SIGTERM handler of a process with pools: `SystemExit(128 + SIGTERM)`, so
  that `finally` blocks and `_close_live` run (nothing once exit has begun)."""
  if not _EXITING:
    raise SystemExit(128 + signal.SIGTERM)


def _handle_sigterm() -> None:
  """Installs `_exit_on_sigterm` where SIGTERM has its default action and this is
  the main thread (a handler the program set is kept)."""
  if (threading.current_thread() is threading.main_thread()
      and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL):
    signal.signal(signal.SIGTERM, _exit_on_sigterm)


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


class _Replies:
  """A worker's side of its pipe: replies from the main thread, and heartbeats
  ("alive", call_id) from a thread of their own every `interval` seconds while a
  call is in progress (one lock orders them: no heartbeat follows a call's reply)."""

  def __init__(self, conn, interval: float):
    self.conn, self.interval = conn, interval
    self.lock = threading.Lock()
    self.call = None
    threading.Thread(target=self._beat, name="heartbeat", daemon=True).start()

  def _beat(self) -> None:
    while True:
      time.sleep(self.interval)
      with self.lock:
        if self.call is not None:
          try:
            self.conn.send(("alive", self.call))
          except OSError:
            return

  def begin(self, call_id: int) -> None:
    with self.lock:
      self.call = call_id

  def send(self, msg) -> None:
    with self.lock:
      self.call = None
      self.conn.send(msg)


def _worker_main(conn, factory, factory_args, in_names, in_specs, out_names, out_spec,
                 batch, env, interval):
  """Entry point of a worker process: build the renderer, then serve calls,
  with heartbeats every `interval` seconds while busy (`_Replies`).

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
  replies = _Replies(conn, interval)
  while True:
    try:
      msg = conn.recv()
    except (EOFError, OSError):
      break
    if msg[0] == "stop":
      break
    _, call_id, start, stop, cur = msg
    replies.begin(call_id)
    try:
      args = [outs[cur][start:stop]]
      if len(outs) == 2:
        args.append(outs[1 - cur][start:stop])
      renderer({k: v[start:stop] for k, v in inputs.items()}, *args)
      replies.send(("done", call_id))
    except BaseException:  # noqa: BLE001 - reported to the parent
      try:
        replies.send(("error", traceback.format_exc()))
      except OSError:
        break
  del inputs, outs
  for s in segments:
    s.close()


def slice_bounds(batch: int, workers: int) -> list[tuple[int, int]]:
  """[start, stop) of the contiguous slice of `batch` rows that each of `workers`
  workers owns (`WorkerPool.slices`): sizes differ by at most one."""
  bounds = np.linspace(0, batch, workers + 1).round().astype(int)
  return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


@dataclasses.dataclass
class _Call:
  """A submitted call: its id, rows [start, start + batch), output buffer `cur`,
  each worker's slice (`slices`) and the workers whose slice is not yet done
  (`pending`; empty once the call is complete, though not yet collected by `wait`)."""
  id: int
  start: int
  batch: int
  cur: int
  slices: dict
  pending: set

  def overlaps(self, start: int, batch: int) -> bool:
    return start < self.start + self.batch and self.start < start + batch


class WorkerPool:
  """W processes rendering fixed slices of a batch into shared memory.

  Args:
    factory: picklable callable building the per-worker renderer.
    factory_args: its arguments (picklable).
    inputs: name -> `ArraySpec` of each per-env input.
    output: `ArraySpec` of one env's output.
    max_batch: the largest batch a call may pass.
    workers: number of processes (≥ 1).
    timeout: seconds a busy worker may send no heartbeat before it is announced
      and replaced (None: `default_timeout()`).
    call_timeout: seconds a worker may stay busy with one call before it is
      announced and replaced, heartbeat or not.
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
    on_close: called once by `close()` after the workers stopped (also at exit
      for a pool never closed), e.g. to remove a folder the workers used.
    wait_start: True waits here for every worker to have started; False returns
      once they are launched, and the first `submit` waits for them (raising, and
      closing the pool, where one failed to start), so that what the caller does
      next (e.g. starting another pool) overlaps their start-up.
  """

  def __init__(self, factory: Callable[..., Any], factory_args: Sequence[Any],
               inputs: Mapping[str, ArraySpec], output: ArraySpec, max_batch: int,
               workers: int, timeout: float | None = None,
               call_timeout: float = DEFAULT_CALL_TIMEOUT, start_timeout: float = 600.0,
               max_retries: int = 3,
               env: Mapping[str, str] | None = None, buffers: int = 1,
               kind: str = "render", worker_env: Sequence[Mapping[str, str]] = (),
               worker_args: Sequence[Sequence[Any]] = (),
               on_close: Callable[[], Any] | None = None, wait_start: bool = True):
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
    self.timeout = default_timeout() if timeout is None else check_timeout("timeout", timeout)
    self.call_timeout = check_timeout("call_timeout", call_timeout)
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
    self._calls: list[_Call] = []    # submitted and not yet collected, oldest first
    self.kind = kind
    self.restarts = 0
    self._closed = False
    self._on_close = on_close
    self._starting: list[int] = []   # workers launched whose "ready" is not yet read
    _handle_sigterm()
    _LIVE.add(self)
    try:
      self.inputs = {k: self._alloc(s) for k, s in self._in_specs.items()}
      self._in_names = {k: self._segments[i].name for i, k in enumerate(self._in_specs)}
      self._outputs = [self._alloc(output) for _ in range(buffers)]
      self._out_names = [shm.name for shm in self._segments[-buffers:]]
      self._cur = 0
      self._latest = np.ones(self.max_batch, np.int8)  # the buffer of each row's output
      for w in range(self.num_workers):
        self._start(w)
      self._starting = list(range(self.num_workers))
      if wait_start:
        self._await_starts()
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
              self._out_names, self._out_spec, self.max_batch, env,
              heartbeat_interval(self.timeout)))
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

  def _await_starts(self) -> None:
    """Waits for every launched worker's "ready"; closes the pool and raises
    `WorkerError` where one failed to start."""
    try:
      while self._starting:
        self._await_ready(self._starting[0])
        self._starting.pop(0)
    except BaseException:
      self.close()
      raise

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
    """Stops every worker and unlinks every shared-memory segment (idempotent):
    workers get `CLOSE_GRACE` seconds to stop, then are killed. A close that an
    exception (e.g. Ctrl-C) cut short is finished by the next, or at exit."""
    self._closed = True
    self._stop_workers()
    deadline = time.monotonic() + CLOSE_GRACE
    for proc in self._procs:
      if proc is not None:
        proc.join(max(0.0, deadline - time.monotonic()))
    for w in range(self.num_workers):
      self._kill(w)
    self.inputs = {}
    self._outputs = []
    while self._segments:
      shm = self._segments.pop()
      try:
        shm.close()
      except BufferError:
        pass  # a buffer exported elsewhere keeps the mapping; the name goes all the same
      try:
        shm.unlink()
      except FileNotFoundError:
        pass
    _LIVE.discard(self)
    on_close, self._on_close = self._on_close, None
    if on_close is not None:
      on_close()

  def _stop_workers(self) -> None:
    """Asks every worker to stop (they leave after their current call)."""
    for conn in self._conns:
      if conn is not None:
        try:
          conn.send(("stop",))
        except (OSError, ValueError):
          pass

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
  def busy(self) -> bool:
    """Whether a `submit` awaits its `wait`."""
    return bool(self._calls)

  @property
  def output(self) -> np.ndarray | None:
    """The output array of the latest call (None once closed)."""
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

  def check_free(self, batch: int, start: int = 0) -> None:
    """Raises unless envs [start, start + batch) lie in the batch and no call in
    flight (submitted, not yet collected by `wait`) holds any of them: their inputs
    may then be written for a `submit`.

    Raises:
      RuntimeError: after `close`, or rows of a call in flight.
      ValueError: rows outside [0, max_batch).
    """
    if self._closed:
      raise RuntimeError("the pool is closed")
    if not 0 <= start < self.max_batch:
      raise ValueError(f"start must be in [0, {self.max_batch}), got {start}")
    if not 1 <= batch <= self.max_batch - start:
      raise ValueError(f"batch must be in [1, {self.max_batch - start}], got {batch}")
    for call in self._calls:
      if call.overlaps(start, batch):
        raise RuntimeError(
            f"submit() called twice on rows in flight: [{start}, {start + batch}) overlaps "
            f"the call of rows [{call.start}, {call.start + call.batch}); call wait() first")

  def submit(self, batch: int, start: int = 0) -> None:
    """Sends every worker its slice of envs [start, start + batch) and returns at
    once; `wait` completes the call. Those rows of `self.inputs` must not change
    until then. Calls on disjoint rows may be in flight together: the workers take
    them in order, each one's slice of a call after its slice of the one before.
    With two buffers, the call writes its rows into the buffer that does not hold
    their previous output (its `prev`): calls over disjoint rows (envs that share
    the workers, `start` apart) each keep their own rows' stacks.

    Raises:
      RuntimeError: rows of a call in flight (`check_free`), or after `close`.
      ValueError: rows outside [0, max_batch).
    """
    self.check_free(batch, start)
    self._await_starts()
    self._call_id += 1
    self._cur = 0 if len(self._outputs) == 1 else 1 - int(self._latest[start])
    self._latest[start:start + batch] = self._cur
    slices = {w: (a + start, b + start) for w, (a, b) in enumerate(self.slices(batch))
              if b > a}
    call = _Call(self._call_id, start, batch, self._cur, slices, set(slices))
    for w in slices:
      self._send(w, call)
    self._calls.append(call)

  def wait(self, start: int | None = None) -> np.ndarray:
    """Waits for a call `submit` began — the oldest in flight, or the one of rows
    from `start` — and for every call submitted before it (replacing dead or hung
    workers and resending their slices); returns `run`'s view of its output rows.
    Calls completed on the way stay for their own `wait`.

    Raises:
      RuntimeError: no such call in flight.
      WorkerError: a worker raised, or failed more than `max_retries` times (every
        call in flight is then dropped).
    """
    if not self._calls:
      raise RuntimeError("wait() without a submitted call")
    if start is None:
      call = self._calls[0]
    else:
      call = next((c for c in self._calls if c.start == start), None)
      if call is None:
        raise RuntimeError(f"wait({start}) without a submitted call of rows from {start}")
    for c in self._calls[:self._calls.index(call) + 1]:
      self._complete(c)
    self._calls.remove(call)
    return self._outputs[call.cur][call.start:call.start + call.batch]

  def _complete(self, call: _Call) -> None:
    """Waits until every worker has done its slice of `call` (every earlier call
    complete): replaces dead or hung workers, resending their slices of this and
    every later call in flight."""
    pending = call.pending
    tries = {w: 0 for w in pending}
    began = dict.fromkeys(pending, time.monotonic())   # the slice was (re)sent
    beat = dict(began)                                 # the worker's last sign of life
    while pending:
      waitables = {self._conns[w]: w for w in pending}
      waitables.update({self._procs[w].sentinel: w for w in pending})
      due = min(min(beat[w] + self.timeout, began[w] + self.call_timeout) for w in pending)
      ready = connection.wait(list(waitables), timeout=max(0.0, due - time.monotonic()))
      now = time.monotonic()
      for w in [w for w in pending if self._conns[w] not in ready
                and self._procs[w].sentinel not in ready]:
        if now - beat[w] >= self.timeout:
          why = f"unresponsive for {now - beat[w]:.0f} s"
        elif now - began[w] >= self.call_timeout:
          why = f"still busy after {now - began[w]:.0f} s"
        else:
          continue
        self._retry(w, call, tries, why)  # hung: replace and resend
        began[w] = beat[w] = time.monotonic()
      seen = set()
      for obj in ready:
        w = waitables[obj]
        current = (self._conns[w], self._procs[w].sentinel) if w in pending else ()
        if w in seen or obj not in current:
          continue  # finished, handled this round, or a replaced worker's handle
        seen.add(w)
        msg = self._receive(w)
        if msg is None:
          self._retry(w, call, tries, "died")
          began[w] = beat[w] = time.monotonic()
        elif msg[0] == "alive":
          beat[w] = now
        elif msg[0] == "done" and msg[1] == call.id:
          pending.discard(w)
        elif msg[0] == "error":
          pending.discard(w)
          self._drop_calls()
          raise WorkerError(f"{self.kind} worker {w} raised:\n{msg[1]}")

  def _drop_calls(self) -> None:
    """Lets every worker finish its slices of the calls in flight (so the pool
    stays consistent) and forgets those calls."""
    replaced = set()
    for call in self._calls:
      for v in call.pending - replaced:
        if not self._drain(v):
          replaced.add(v)
    self._calls = []

  def _receive(self, w: int):
    """Worker w's next message, or None if its pipe closed (it died)."""
    conn = self._conns[w]
    try:
      return conn.recv() if conn.poll() else None
    except (EOFError, OSError):
      return None

  def _send(self, w: int, call: _Call) -> None:
    a, b = call.slices[w]
    try:
      self._conns[w].send(("render", call.id, a, b, call.cur))
    except (BrokenPipeError, ConnectionResetError):
      pass  # the worker died before this call: its sentinel triggers the retry

  def _retry(self, w: int, call: _Call, tries: dict, why: str) -> None:
    """Replaces worker w and sends its replacement w's slices of `call` and of
    every later call in flight (the dead worker's queue)."""
    tries[w] += 1
    if tries[w] > self.max_retries:
      self._drop_calls()
      raise WorkerError(f"{self.kind} worker {w} {why}, {tries[w]} times in one call")
    if why != "died":
      limit = (f"no heartbeat for {self.timeout:g} s: set by make(worker_timeout=...) or "
               f"{TIMEOUT_VARIABLE}" if why.startswith("unresponsive")
               else f"busy over {self.call_timeout:g} s")
      _announce(f"{self.kind} worker {w} (pid {self._procs[w].pid}) {why}; replacing it "
                f"and redoing its slice ({limit})")
    self._replace(w)
    for later in self._calls[self._calls.index(call):]:
      if w in later.pending:
        self._send(w, later)

  def _drain(self, w: int) -> bool:
    """Waits for worker w's reply to its oldest slice in flight; False where it
    died or hung instead (it is replaced, with nothing queued)."""
    began = beat = time.monotonic()
    while True:
      conn, proc = self._conns[w], self._procs[w]
      due = min(beat + self.timeout, began + self.call_timeout)
      ready = connection.wait([conn, proc.sentinel], timeout=max(0.0, due - time.monotonic()))
      msg = self._receive(w) if ready else None
      if msg is not None and msg[0] == "alive":
        beat = time.monotonic()
        continue
      if msg is None:
        self._replace(w)
      return msg is not None


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
