"""WorkerPool: slices, shared memory, killed/hung/raising workers, clean shutdown."""

import contextlib
import os
import signal
import time

import numpy as np
import pytest

from dmcr_jax.visuals.pool import (DEFAULT_TIMEOUT, ArraySpec, WorkerError, WorkerPool,
                                   default_timeout)
from tests import pool_fixtures as fx

IN = {"value": ArraySpec((), "float64"), "mode": ArraySpec((), "int32")}
OUT = ArraySpec((2, 3), "float32")


def make_pool(tmp_path, workers=2, timeout=20.0, max_batch=64, **kwargs):
  marker = str(tmp_path / "fault")
  return WorkerPool(fx.ToyRenderer, (marker,), IN, OUT, max_batch=max_batch,
                    workers=workers, timeout=timeout, **kwargs), marker


def fill(pool, n, mode=None):
  pool.inputs["value"][:n] = np.arange(n) * 10.0
  pool.inputs["mode"][:n] = 0 if mode is None else mode
  pool.output[:n] = -1


def expected(n):
  return np.broadcast_to((np.arange(n) * 10.0 + 1)[:, None, None], (n, 2, 3))


def arm(pool, tmp_path, n, row, mode):
  """Fills `n` inputs with row `row` in fault `mode`, and arms the fault (its marker file)."""
  fill(pool, n)
  pool.inputs["mode"][row] = mode
  open(tmp_path / "fault", "w").close()


def alive(pid):
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  # A zombie is dead for our purposes.
  try:
    with open(f"/proc/{pid}/stat") as f:
      return f.read().split()[2] != "Z"
  except FileNotFoundError:
    return False


@pytest.mark.parametrize("workers,n", [(1, 1), (2, 5), (3, 64), (3, 2)])
def test_every_slice_rendered_once(tmp_path, workers, n):
  pool, _ = make_pool(tmp_path, workers=workers)
  with pool:
    fill(pool, n)
    np.testing.assert_array_equal(pool.run(n), expected(n))
    assert sum(b - a for a, b in pool.slices(n)) == n


def test_killed_worker_is_restarted_and_slice_rerendered(tmp_path):
  with make_pool(tmp_path, workers=2)[0] as pool:
    marker = str(tmp_path / "fault")
    n = 20
    fill(pool, n)
    pool.inputs["mode"][15] = fx.KILL   # in worker 1's slice
    open(marker, "w").close()
    old = pool.pids
    np.testing.assert_array_equal(pool.run(n), expected(n))
    assert pool.restarts == 1
    assert pool.pids[0] == old[0] and pool.pids[1] != old[1]
    assert not alive(old[1])
    fill(pool, n)  # and the pool keeps working
    np.testing.assert_array_equal(pool.run(n), expected(n))


def test_workers_leave_sigint_and_sigterm_to_the_parent(tmp_path):
  # Ctrl-C and `timeout` signal the whole process group; the parent decides what
  # happens (train checkpoints first), so the workers must survive the signal.
  with make_pool(tmp_path, workers=2)[0] as pool:
    fill(pool, 8)
    pool.run(8)
    old = pool.pids
    for pid, sig in zip(old, (signal.SIGINT, signal.SIGTERM)):
      os.kill(pid, sig)
    time.sleep(0.5)
    assert all(alive(pid) for pid in old)
    fill(pool, 8)
    np.testing.assert_array_equal(pool.run(8), expected(8))
    assert pool.restarts == 0 and pool.pids == old


@pytest.mark.slow
def test_worker_busy_past_the_call_timeout_is_replaced(tmp_path, capfd):
  # Its heartbeat goes on (the thread that sends it is not the one that hangs).
  with make_pool(tmp_path, workers=2, call_timeout=3.0)[0] as pool:
    n = 8
    arm(pool, tmp_path, n, 1, fx.HANG)
    np.testing.assert_array_equal(pool.run(n), expected(n))
    assert pool.restarts == 1
  err = capfd.readouterr().err
  assert "render worker 0 (pid " in err and "still busy after 3 s; replacing it" in err


def test_stopped_worker_is_announced_and_replaced_after_the_timeout(tmp_path, capfd):
  with make_pool(tmp_path, workers=2, timeout=1.0)[0] as pool:
    n = 8
    fill(pool, n)
    pool.run(n)
    victim = pool.pids[1]
    os.kill(victim, signal.SIGSTOP)
    try:
      fill(pool, n)
      t0 = time.monotonic()
      np.testing.assert_array_equal(pool.run(n), expected(n))
      took = time.monotonic() - t0
    finally:
      with contextlib.suppress(ProcessLookupError):   # the pool killed it already
        os.kill(victim, signal.SIGKILL)
    assert pool.restarts == 1 and victim not in pool.pids
    assert 1.0 <= took < 10.0
  assert f"render worker 1 (pid {victim}) unresponsive for 1 s; replacing it" in capfd.readouterr().err


def test_slow_worker_that_keeps_its_heartbeat_is_not_replaced(tmp_path, capfd):
  # A call longer than the timeout (a big slice, a first compilation) is no hang.
  with make_pool(tmp_path, workers=2, timeout=1.0)[0] as pool:
    n = 4
    arm(pool, tmp_path, n, 3, fx.SLOW)
    t0 = time.monotonic()
    np.testing.assert_array_equal(pool.run(n), expected(n))
    assert time.monotonic() - t0 >= fx.SLOW_S
    assert pool.restarts == 0
  assert "unresponsive" not in capfd.readouterr().err


def test_timeouts_are_checked(monkeypatch):
  for bad in (0, -2.0, "x", True):
    with pytest.raises(ValueError, match="timeout must be a number of seconds > 0"):
      WorkerPool(fx.ToyRenderer, ("x",), IN, OUT, max_batch=1, workers=1, timeout=bad)
  monkeypatch.setenv("DMCR_WORKER_TIMEOUT", "2.5")
  assert default_timeout() == 2.5
  monkeypatch.setenv("DMCR_WORKER_TIMEOUT", "0")
  with pytest.raises(ValueError, match="DMCR_WORKER_TIMEOUT must be a number of seconds > 0"):
    default_timeout()
  monkeypatch.delenv("DMCR_WORKER_TIMEOUT")
  assert default_timeout() == DEFAULT_TIMEOUT


def test_worker_exception_surfaces_with_traceback(tmp_path):
  with make_pool(tmp_path, workers=2)[0] as pool:
    n = 6
    fill(pool, n)
    pool.inputs["mode"][4] = fx.RAISE
    with pytest.raises(WorkerError, match=r"(?s)Traceback.*ValueError: bad env value 40"):
      pool.run(n)
    fill(pool, n)
    np.testing.assert_array_equal(pool.run(n), expected(n))


def test_close_leaves_no_processes_or_shared_memory(tmp_path):
  pool, _ = make_pool(tmp_path, workers=3)
  names = [s.name for s in pool._segments]
  pids = pool.pids
  assert all(os.path.exists(f"/dev/shm/{n}") for n in names)
  pool.close()
  pool.close()  # idempotent
  assert not any(alive(p) for p in pids)
  assert not any(os.path.exists(f"/dev/shm/{n}") for n in names)
  with pytest.raises(RuntimeError, match="closed"):
    pool.run(1)


def test_context_manager_cleans_up_after_error(tmp_path):
  with pytest.raises(KeyError):
    with make_pool(tmp_path, workers=2)[0] as pool:
      names = [s.name for s in pool._segments]
      pids = pool.pids
      raise KeyError("boom")
  assert not any(alive(p) for p in pids)
  assert not any(os.path.exists(f"/dev/shm/{n}") for n in names)


def test_bad_arguments(tmp_path):
  with pytest.raises(ValueError, match="workers"):
    WorkerPool(fx.ToyRenderer, ("x",), IN, OUT, max_batch=4, workers=0)
  with pytest.raises(ValueError, match="max_batch"):
    WorkerPool(fx.ToyRenderer, ("x",), IN, OUT, max_batch=0, workers=1)
  with make_pool(tmp_path, workers=1, max_batch=4)[0] as pool:
    for bad in (0, 5, -1):
      with pytest.raises(ValueError, match=r"batch must be in \[1, 4\]"):
        pool.run(bad)


def test_worker_env_is_set_before_the_worker_imports_anything():
  # MuJoCo and PyOpenGL read MUJOCO_GL / PYOPENGL_PLATFORM once, when the worker
  # unpickles its factory; gl="osmesa" failed unless the caller had exported them.
  assert "DMCR_POOL_TEST_VAR" not in os.environ
  pool = WorkerPool(fx.ImportEnvRenderer, (), IN, OUT, max_batch=2, workers=1,
                    env={"DMCR_POOL_TEST_VAR": "set"})
  try:
    assert "DMCR_POOL_TEST_VAR" not in os.environ  # the caller's env is restored
    fill(pool, 2)
    assert (pool.run(2) == 1).all()
  finally:
    pool.close()



def test_worker_env_adds_per_worker_variables_round_robin():
  # RenderPool's egl_devices: worker w gets worker_env[w % len], over the shared env,
  # and a replaced worker keeps its own.
  pool = WorkerPool(fx.EnvValueRenderer, (), IN, OUT, max_batch=6, workers=3,
                    env={"DMCR_POOL_TEST_VAR": "0"},
                    worker_env=[{"DMCR_POOL_TEST_VAR": "10"}, {"DMCR_POOL_TEST_VAR": "20"}])
  try:
    assert "DMCR_POOL_TEST_VAR" not in os.environ
    fill(pool, 6)
    got = pool.run(6)[:, 0, 0]
    want = np.concatenate([np.full(b - a, (10.0, 20.0, 10.0)[w])
                           for w, (a, b) in enumerate(pool.slices(6))])
    np.testing.assert_array_equal(got, want)
    os.kill(pool.pids[1], signal.SIGKILL)
    fill(pool, 6)
    np.testing.assert_array_equal(pool.run(6)[:, 0, 0], want)
  finally:
    pool.close()

def test_worker_args_build_each_worker_and_its_replacement():
  # PhysicsPool's slice sizes: worker w is built by factory(*factory_args,
  # *worker_args[w]), and a replaced worker is rebuilt with its own.
  pool = WorkerPool(fx.ArgValueRenderer, (), IN, OUT, max_batch=5, workers=3,
                    worker_args=[(10.0,), (20.0,), (30.0,)])
  try:
    want = np.concatenate([np.full(b - a, 10.0 * (w + 1))
                           for w, (a, b) in enumerate(pool.slices(5))])
    fill(pool, 5)
    np.testing.assert_array_equal(pool.run(5)[:, 0, 0], want)
    os.kill(pool.pids[2], signal.SIGKILL)
    fill(pool, 5)
    np.testing.assert_array_equal(pool.run(5)[:, 0, 0], want)
  finally:
    pool.close()
  with pytest.raises(ValueError, match="one entry per worker"):
    WorkerPool(fx.ArgValueRenderer, (), IN, OUT, max_batch=5, workers=3, worker_args=[(1.0,)])


def test_submit_returns_before_wait_and_wait_completes_the_call(tmp_path):
  with make_pool(tmp_path, workers=2)[0] as pool:
    n = 7
    fill(pool, n)
    with pytest.raises(RuntimeError, match="without a submitted call"):
      pool.wait()
    pool.submit(n)
    with pytest.raises(RuntimeError, match="submit\\(\\) called twice"):
      pool.submit(n)
    np.testing.assert_array_equal(pool.wait(), expected(n))
    fill(pool, n)
    np.testing.assert_array_equal(pool.run(n), expected(n))  # the pool is usable again


def test_calls_on_disjoint_rows_queue_and_each_is_collected_by_its_rows(tmp_path):
  with make_pool(tmp_path, workers=2)[0] as pool:
    fill(pool, 20)
    pool.submit(8)             # rows [0, 8)
    pool.submit(12, start=8)   # rows [8, 20), behind it
    with pytest.raises(RuntimeError, match="called twice on rows in flight"):
      pool.submit(4, start=6)
    with pytest.raises(RuntimeError, match="without a submitted call of rows from 3"):
      pool.wait(3)
    np.testing.assert_array_equal(pool.wait(8), expected(20)[8:])  # the later call first
    assert pool.busy
    np.testing.assert_array_equal(pool.wait(), expected(8))
    assert not pool.busy
    fill(pool, 20)
    np.testing.assert_array_equal(pool.run(20), expected(20))


@pytest.mark.parametrize("row", [7, 17])   # worker 1's slice of the first / second call
def test_a_worker_killed_with_calls_queued_redoes_each_of_its_slices(tmp_path, row):
  with make_pool(tmp_path, workers=2)[0] as pool:
    arm(pool, tmp_path, 20, row, fx.KILL)
    old = pool.pids
    pool.submit(10)
    pool.submit(10, start=10)
    np.testing.assert_array_equal(pool.wait(), expected(10))
    np.testing.assert_array_equal(pool.wait(10), expected(20)[10:])
    assert pool.restarts == 1 and pool.pids[0] == old[0] and not alive(old[1])


def test_a_worker_raising_with_calls_queued_drops_them_and_the_pool_goes_on(tmp_path):
  with make_pool(tmp_path, workers=2)[0] as pool:
    fill(pool, 20)
    pool.inputs["mode"][3] = fx.RAISE
    pool.submit(10)
    pool.submit(10, start=10)
    with pytest.raises(WorkerError, match="bad env value 30"):
      pool.wait(10)
    assert not pool.busy and pool.restarts == 0
    fill(pool, 20)
    np.testing.assert_array_equal(pool.run(20), expected(20))


def test_a_pool_not_waiting_for_its_start_returns_at_once_and_its_first_call_waits(tmp_path):
  gate = tmp_path / "gate"
  # Were the start awaited here, the constructor would wait for the gate until the
  # start timeout and fail.
  pool = WorkerPool(fx.GatedRenderer, (str(tmp_path / "fault"), str(gate)), IN, OUT,
                    max_batch=8, workers=2, start_timeout=30.0, wait_start=False)
  with pool:
    assert len(pool.pids) == 2
    gate.touch()
    fill(pool, 5)
    np.testing.assert_array_equal(pool.run(5), expected(5))


@pytest.mark.parametrize("wait_start", [True, False])
def test_a_worker_that_fails_to_start_raises_and_leaves_nothing(wait_start):
  def start():
    return WorkerPool(fx.FailingStartRenderer, (), IN, OUT, max_batch=4, workers=2,
                      wait_start=wait_start)

  if wait_start:
    with pytest.raises(WorkerError, match="(?s)failed to start.*no renderer here"):
      start()
    return
  pool = start()
  pids = pool.pids
  with pytest.raises(WorkerError, match="(?s)failed to start.*no renderer here"):
    fill(pool, 3)
    pool.run(3)
  assert not any(alive(p) for p in pids)
  with pytest.raises(RuntimeError, match="closed"):
    pool.run(1)
