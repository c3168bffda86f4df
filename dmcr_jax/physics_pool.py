"""`PhysicsPool`: the physics of N envs stepped by W worker processes on the host CPU.

MJX on XLA:CPU runs a small batch one operation after another, latency-bound, so
one process uses little of a many-core host. Here each of W worker processes
(a `visuals.pool.WorkerPool`, `JAX_PLATFORMS=cpu`) owns a fixed contiguous slice
of the envs and runs `physics_env.init` and `physics_env.step` on it with its
own XLA:CPU; the slices step at the same time (measurements:
`benchmarks/results/physics_processes_h200host.md`).

The constructor returns once the workers are launched (the first call waits for
their start). Each worker compiles its `init` and `step` in a background thread as
soon as it has started, for its slice's size and the seed argument's kind the env
starts with, so that the start and the compilation overlap whatever the training
process does before its first physics call instead of following it. The workers
share a persistent compilation cache (JAX's, the folder this process's JAX config or
`JAX_COMPILATION_CACHE_DIR` names, with this process's size bound and minimum
compile time, e.g. a CLI's `--compile-cache`; else a folder of the pool's own):
worker 0 compiles first and the others then load what it compiled, instead of W
processes compiling the same programs at once.

State lives in shared memory, one record per env (every leaf of the env's
`physics_env.EnvState`, its key as key data, the step's reward and truncation),
double-buffered: a call reads each env's previous record and writes the new one,
so a worker that dies or hangs is replaced and its slice stepped again from the
same records (`WorkerPool`'s fault handling), with nothing lost.

Results are those of the in-process `physics_env` functions up to float32
rounding: every env's key comes from the same split (`physics_env.init` with N
keys) and each worker steps its envs with their own keys, seeds and ranges, but
XLA compiles a slice's smaller batch differently, so the last bits of a state
can differ and, in chaotic stretches of an episode, grow
(`tests/test_physics_pool.py` compares both across episode ends).
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
import shutil
import tempfile
import threading

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax import physics_env
from dmcr_jax.checks import positive_int
from dmcr_jax.visuals.levels import SeedBounds
from dmcr_jax.visuals.pool import ArraySpec, OwnsWorkerPool, WorkerPool, slice_bounds


def _is_key(leaf) -> bool:
  return jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)


def _layout(task):
  """(treedef, record dtype, index of the key leaf) of one env's EnvState."""
  es = jax.eval_shape(lambda k: physics_env.init(task, jnp.zeros((1,), jnp.int32), k, 1),
                      jax.random.key(0))
  leaves, treedef = jax.tree.flatten(es)
  fields, key_leaf = [], None
  for i, leaf in enumerate(leaves):
    if _is_key(leaf):
      key_leaf = i
      data = jax.eval_shape(jax.random.key_data, leaf)
      fields.append((f"l{i}", data.dtype, data.shape[1:]))
    else:
      fields.append((f"l{i}", leaf.dtype, leaf.shape[1:]))
  fields += [("reward", np.float32, ()), ("truncated", np.bool_, ())]
  return treedef, np.dtype(fields, align=True), key_leaf


def _unpack(records: np.ndarray, treedef, key_leaf: int, copy: bool):
  """The EnvState stored in `records` (leaves: NumPy arrays, copies or views; the
  key a `jax.Array` of keys on the CPU)."""
  leaves = []
  for i in range(treedef.num_leaves):
    x = records[f"l{i}"]
    if i == key_leaf:
      x = jax.random.wrap_key_data(jax.device_put(np.ascontiguousarray(x), jax.devices("cpu")[0]))
    elif copy:
      x = np.ascontiguousarray(x)
    leaves.append(x)
  return jax.tree.unflatten(treedef, leaves)


def _pack(es, records: np.ndarray, key_leaf: int) -> None:
  """Writes an EnvState's leaves into `records` (one record per env)."""
  for i, x in enumerate(jax.tree.leaves(es)):
    records[f"l{i}"] = np.asarray(jax.random.key_data(x) if i == key_leaf else x)


def _seed_inputs(seeds, n: int) -> dict[str, np.ndarray]:
  """The workers' per-env seed inputs ("ranged", "seed", "start", "stop") of a seed
  argument for n envs (`physics_env.seed_argument`: fixed seeds or `SeedBounds`)."""
  ranged = isinstance(seeds, SeedBounds)
  each = lambda x: np.broadcast_to(np.asarray(x, np.int32), (n,))
  unused = each(0)
  return {"ranged": np.full(n, ranged),
          "seed": unused if ranged else each(seeds),
          "start": each(seeds.start) if ranged else unused,
          "stop": each(seeds.stop) if ranged else unused}


def _user_cache_dir() -> str | None:
  """JAX's persistent compilation cache folder, if the user set one (`jax.config`,
  which JAX_COMPILATION_CACHE_DIR sets at import, else that variable)."""
  return jax.config.jax_compilation_cache_dir or os.environ.get("JAX_COMPILATION_CACHE_DIR")


def _cache_env(folder: str) -> dict[str, str]:
  """The environment that points a worker's JAX at `folder` with this process's
  cache settings (a folder with a size bound needs every writer to keep it: JAX's
  eviction reads each entry's access time, which only bounded writers record)."""
  return {"JAX_COMPILATION_CACHE_DIR": folder,
          "JAX_COMPILATION_CACHE_MAX_SIZE": str(jax.config.jax_compilation_cache_max_size),
          "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS":
              str(jax.config.jax_persistent_cache_min_compile_time_secs)}


_FIRST_COMPILE_TIMEOUT = 300.0
"""Seconds the other physics workers wait for the first one's compilation before
compiling themselves."""


class _Stepper:
  """A physics worker's callable (`WorkerPool` protocol): `init` or one `step`
  of its slice of envs, from `prev`'s records into `out`'s.

  Args:
    task_name, solver_iterations, ls_iterations: the task as `models.load` takes it.
    frame_skip: control steps per agent step.
    warm_rows: slice sizes to compile `init` and `step` for in the background
      (calls wait for it); () compiles on the first call.
    warm_ranged: the seed argument's kind to compile them for (`SeedBounds` or
      fixed seeds).
    compiled: None, or an event the first worker sets once it has compiled
      (`first`), and the others wait for before they compile (from the cache).
    first: whether this worker compiles first.
  """

  def __init__(self, task_name: str, solver_iterations, ls_iterations, frame_skip: int,
               warm_rows: tuple[int, ...] = (), warm_ranged: bool = False,
               compiled=None, first: bool = True):
    from dmcr_jax import models
    from dmcr_jax.models.base import physics_jit
    task = models.load(task_name, solver_iterations, ls_iterations)
    self.treedef, self.record, self.key_leaf = _layout(task)
    self.action_size = task.action_size
    # The seed argument's kind (fixed seeds or `SeedBounds`) is its pytree type:
    # each kind traces once, any values after that.
    self._init = physics_jit(lambda keys, arg: physics_env.init(task, arg, keys, keys.shape[0]))
    self._step = physics_jit(lambda es, a, arg: physics_env.step(task, arg, frame_skip, es, a))
    self._warming = threading.Thread(target=self._warm,
                                     args=(warm_rows, warm_ranged, compiled, first),
                                     name="physics-compile", daemon=True)
    self._warming.start()

  def _warm(self, rows: tuple[int, ...], ranged: bool, compiled, first: bool) -> None:
    """Compiles `init` and `step` for slices of each size in `rows`: one call of
    each on inputs built as `__call__` builds them (same types, so the calls that
    follow find them compiled); results are discarded. With `compiled`, the first
    worker sets it when done and the others wait for it."""
    if compiled is not None and not first:
      compiled.wait(_FIRST_COMPILE_TIMEOUT)
    try:
      for n in rows:
        started, stepped = np.zeros(n, self.record), np.zeros(n, self.record)
        seeds = np.zeros(n, np.int32)
        inputs = {"key": np.asarray(jax.random.key_data(jax.random.split(jax.random.key(0), n))),
                  "action": np.zeros((n, self.action_size), np.float32),
                  **_seed_inputs(SeedBounds(start=seeds, stop=seeds + 1) if ranged else seeds, n)}
        # `_run(inputs, out, prev)`: init into `started`, then a step from it.
        self._run(dict(inputs, init=np.ones(n, bool)), started, stepped)
        self._run(dict(inputs, init=np.zeros(n, bool)), stepped, started)
    except Exception:  # noqa: BLE001 - the call that needs it compiles again and raises
      pass
    finally:
      if compiled is not None and first:
        compiled.set()

  def __call__(self, inputs, out, prev) -> None:
    self._warming.join()
    self._run(inputs, out, prev)

  def _run(self, inputs, out, prev) -> None:
    """`init` or `step` of the slice in `inputs` (module doc)."""
    c = np.ascontiguousarray
    arg = (SeedBounds(start=c(inputs["start"]), stop=c(inputs["stop"])) if inputs["ranged"][0]
           else c(inputs["seed"]))
    if inputs["init"][0]:
      keys = jax.random.wrap_key_data(c(inputs["key"]))
      es = self._init(keys, arg)
      out["reward"], out["truncated"] = 0.0, False
    else:
      es = _unpack(prev, self.treedef, self.key_leaf, copy=True)
      es, reward, truncated = self._step(es, c(inputs["action"]), arg)
      out["reward"], out["truncated"] = np.asarray(reward), np.asarray(truncated)
    _pack(es, out, self.key_leaf)


class PhysicsPool(OwnsWorkerPool):
  """`physics_env.init` and `physics_env.step` of N envs in W worker processes.

  Args:
    task: the `Task` (`models.load`; its name and solver budget are rebuilt in
      the workers).
    num_envs: N.
    frame_skip: control steps per agent step.
    workers: W ≥ 1 (at most N are used).
    timeout: seconds a busy worker may send no heartbeat before it is announced
      and replaced (None: `visuals.pool.default_timeout()`, `DMCR_WORKER_TIMEOUT`).
    ranged: the seed argument's kind the workers compile for as they start
      (`SeedBounds` if True, else fixed seeds); the other kind compiles when
      first used.

  `init(key, seeds)` and `step(es, actions, seeds)` take and return what the
  jitted `physics_env` functions do, with NumPy leaves (the key on the CPU);
  `seeds` is their seed argument (`physics_env.seed_argument`: fixed int32 (N,)
  seeds or `SeedBounds`), per call, so one pool serves any seeds and ranges;
  `step` returns at once, with a `PendingStep` whose `result()` waits. The
  workers keep stepping the state the pool returned last; `step` of any other
  state (e.g. one changed by the caller) loads it into their records first.
  Use as a context manager or call `close()`.
  """

  def __init__(self, task, num_envs: int, frame_skip: int, workers: int,
               timeout: float | None = None, ranged: bool = False):
    n = positive_int("num_envs", num_envs)
    workers = min(positive_int("physics workers", workers), n)
    self.num_envs = n
    self.treedef, record, self.key_leaf = _layout(task)
    key_shape = record[f"l{self.key_leaf}"].shape
    cache = _user_cache_dir()
    self._own_cache = None if cache else tempfile.mkdtemp(prefix="dmcr-physics-xla-")
    cache = cache or self._own_cache
    compiled = mp.get_context("spawn").Event()
    inputs = {"action": ArraySpec((task.action_size,), "float32"),
              "key": ArraySpec(key_shape, "uint32"),
              "seed": ArraySpec((), "int32"), "start": ArraySpec((), "int32"),
              "stop": ArraySpec((), "int32"), "ranged": ArraySpec((), "bool"),
              "init": ArraySpec((), "bool")}
    try:
      self._pool = WorkerPool(
          _Stepper, (task.name, task.solver_iterations, task.ls_iterations, frame_skip),
          inputs, ArraySpec((), record), max_batch=n, workers=workers, timeout=timeout,
          buffers=2, kind="physics", wait_start=False,
          worker_args=[((b - a,), bool(ranged), compiled, w == 0)
                       for w, (a, b) in enumerate(slice_bounds(n, workers))],
          env={"JAX_PLATFORMS": "cpu", "XLA_PYTHON_CLIENT_PREALLOCATE": "false",
               **_cache_env(cache)},
          # also at exit if the pool is never closed (no reference to self: no cycle)
          on_close=self._own_cache and functools.partial(shutil.rmtree, self._own_cache,
                                                         ignore_errors=True))
    except BaseException:
      self._remove_own_cache()
      raise
    self.num_workers = self._pool.num_workers
    self._current = None

  def _remove_own_cache(self) -> None:
    """Removes the compilation cache folder the pool made, if any (idempotent)."""
    if getattr(self, "_own_cache", None):
      shutil.rmtree(self._own_cache, ignore_errors=True)
      self._own_cache = None

  def _seeds_in(self, seeds) -> None:
    """Writes a call's seed argument into the workers' inputs."""
    for name, value in _seed_inputs(seeds, self.num_envs).items():
      self._pool.inputs[name][:] = value

  def _result(self, records: np.ndarray):
    """The EnvState of a call's records, in the caller's own memory (one copy of
    the records: views of shared memory would outlive `close`); (es, records)."""
    records = records.copy()
    es = _unpack(records, self.treedef, self.key_leaf, copy=False)
    self._current = es
    return es, records

  def init(self, key: jax.Array, seeds):
    """`physics_env.init` of the N envs (waits); `key`: one key or N keys."""
    keys = key if key.shape == (self.num_envs,) else jax.random.split(key, self.num_envs)
    self._pool.inputs["key"][:] = np.asarray(jax.random.key_data(keys))
    self._pool.inputs["init"][:] = True
    self._seeds_in(seeds)
    return self._result(self._pool.run(self.num_envs))[0]

  def step(self, es, actions, seeds) -> "PendingStep":
    """Starts `physics_env.step(es, actions)` of the N envs; returns at once."""
    if es is not self._current:
      _pack(es, self._pool.output, self.key_leaf)  # read as `prev` by this call
    self._pool.inputs["action"][:] = np.asarray(actions, np.float32)
    self._pool.inputs["init"][:] = False
    self._seeds_in(seeds)
    self._pool.submit(self.num_envs)
    return PendingStep(self)

  def close(self) -> None:
    """Stops the workers, frees shared memory and removes the pool's own
    compilation cache (idempotent)."""
    super().close()
    self._current = None
    self._remove_own_cache()


class PendingStep:
  """A `PhysicsPool.step` in flight; `result()` waits and returns
  (EnvState, reward float32 (N,), truncated bool (N,))."""

  def __init__(self, pool: PhysicsPool):
    self._pool = pool

  def result(self):
    es, records = self._pool._result(self._pool._pool.wait())
    return es, records["reward"], records["truncated"]
