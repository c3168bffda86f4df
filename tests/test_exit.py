"""A process that made envs exits promptly however it ends (no close(), an exception,
Ctrl-C, SIGTERM), leaving no worker and no shared memory; a hung render worker is
announced and replaced within the configured timeout with unchanged pixels."""

import json
import contextlib
import os
import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import dmcr_jax
from dmcr_jax.visuals.render_pool import RenderPool

pytestmark = pytest.mark.xdist_group("exit")

# Every kind of env with workers, none closed: the pool env with physics workers,
# gymnasium's and dm_env's single envs, reset (all compiled, all workers used) if
# argv[2] says so, else left as made (the physics worker still compiling); then the
# script ends as argv[1] says.
CHILD = r"""
import faulthandler, json, signal, sys, time
faulthandler.register(signal.SIGUSR1, all_threads=True)   # the test's stack dump on a hang
# Ctrl-C raises KeyboardInterrupt, as in a terminal, also where the test runs as a
# background job of a non-interactive shell (which starts it, and so this script, with
# SIGINT ignored).
signal.signal(signal.SIGINT, signal.default_int_handler)
import gymnasium
import dmcr_jax
from dmcr_jax.visuals import pool
small = dict(image_size=16, workers=1, quality="fast", physics_device="cpu", frame_skip=100)
envs = [dmcr_jax.make("pendulum-swingup", num_envs=2, physics_workers=1, **small),
        gymnasium.make("dmcr/pendulum-swingup-v0", **small),
        dmcr_jax.DmEnv("pendulum-swingup", **small)]
for env in envs if sys.argv[2] == "reset" else ():
  env.reset()
live = list(pool._LIVE)
print(json.dumps({"pids": sorted(p for w in live for p in w.pids),
                  "segments": sorted(s.name for w in live for s in w._segments),
                  "kinds": sorted(w.kind for w in live)}), flush=True)
if sys.argv[1] == "raise":
  raise RuntimeError("the script fails before close()")
if sys.argv[1] == "wait":
  time.sleep(600)
"""
# (how the script ends, whether it resets its envs, the signal its process group
# gets, its exit status); resetting costs each script a compilation, so two do.
ENDINGS = {"end": ("end", "reset", None, 0), "raise": ("raise", "made", None, 1),
           "sigint": ("wait", "made", signal.SIGINT, -signal.SIGINT),
           "sigterm": ("wait", "reset", signal.SIGTERM, 128 + signal.SIGTERM)}
START_S = 900   # building the envs on a busy 2-core machine
EXIT_S = 30     # from the end of the script (or the signal) to the process's exit; generous, as
                # the four scripts end at once beside the other tests on two cores


def _dead(pid: int) -> bool:
  try:
    with open(f"/proc/{pid}/stat") as f:
      return f.read().split()[2] == "Z"   # a zombie is dead for our purposes
  except FileNotFoundError:
    return True


def _start(end: str, use: str) -> subprocess.Popen:
  return subprocess.Popen([sys.executable, "-c", CHILD, end, use], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True, start_new_session=True)


@pytest.fixture(scope="module")
def children():
  """The four endings' scripts: "end" first, the others once it has built and reset its
  envs (its compiled programs are then in the session's compilation cache, which the
  other resetting script loads instead of compiling them again)."""
  procs = {"end": _start(*ENDINGS["end"][:2])}
  select.select([procs["end"].stdout], [], [], START_S)   # its first line, not read here
  procs.update({name: _start(end, use) for name, (end, use, _, _) in ENDINGS.items()
                if name not in procs})
  yield procs
  for proc in procs.values():   # whatever a failed test left running
    if proc.poll() is None:
      os.killpg(proc.pid, signal.SIGKILL)
      proc.wait()


def _first_line(proc) -> str:
  ready, _, _ = select.select([proc.stdout], [], [], START_S)
  assert ready, f"the script did not build its envs within {START_S} s"
  line = proc.stdout.readline()
  assert line, f"the script ended before building its envs:\n{proc.stderr.read()[-3000:]}"
  return line


@pytest.mark.slow
@pytest.mark.parametrize("ending", list(ENDINGS))
def test_a_process_with_open_envs_exits_promptly_and_leaves_nothing(children, ending):
  _, _, sig, status = ENDINGS[ending]
  proc = children[ending]
  made = json.loads(_first_line(proc))
  assert made["kinds"] == ["physics", "render", "render", "render"]
  t0 = time.monotonic()
  if sig is not None:   # (the other scripts may have ended already)
    assert all(os.path.exists(f"/dev/shm/{n}") for n in made["segments"])
    assert not any(_dead(p) for p in made["pids"])
    os.killpg(proc.pid, sig)   # as Ctrl-C or `timeout` signal the whole group
  try:   # stderr read while waiting: a child never blocks on a full pipe
    _, err = proc.communicate(timeout=EXIT_S)
  except subprocess.TimeoutExpired:
    os.kill(proc.pid, signal.SIGUSR1)   # its threads' stacks to stderr (faulthandler)
    time.sleep(2)
    os.killpg(proc.pid, signal.SIGKILL)
    _, err = proc.communicate()
    pytest.fail(f"the process did not exit within {EXIT_S} s of its end; its stderr, "
                f"with the stacks of its threads at that time:\n{err[-8000:]}")
  took = time.monotonic() - t0
  assert proc.returncode == status, err[-3000:]
  deadline = time.monotonic() + 5   # orphaned workers are reaped by init
  while not all(_dead(p) for p in made["pids"]) and time.monotonic() < deadline:
    time.sleep(0.1)
  assert [p for p in made["pids"] if not _dead(p)] == []
  assert [n for n in made["segments"] if os.path.exists(f"/dev/shm/{n}")] == []
  assert "leaked" not in err, err[-3000:]
  if ending == "raise":
    assert "RuntimeError: the script fails before close()" in err
  if ending == "end":
    # The first compile is announced once per shape: the 2-env env, then the 1-env
    # shape of the gymnasium env (not again for the dm_env env of the same shape).
    lines = [ln for ln in err.splitlines() if "compiling pendulum-swingup's physics" in ln]
    assert len(lines) == 2, err[-3000:]
    assert "for 2 envs on cpu, in 1 physics worker" in lines[0]
    assert "for 1 envs on cpu (" in lines[1]
  print(f"{ending}: exited {took:.1f} s after its end")


def _inputs(rm, n):
  rng = np.random.default_rng(0)
  return rm.model.qpos0 + rng.uniform(-1, 1, (n, rm.model.nq)), rm.sample(np.arange(n) * 7)


@pytest.mark.slow
def test_a_stopped_render_worker_is_announced_and_replaced_with_the_same_pixels(capfd):
  timeout = 2.0
  with RenderPool("cartpole", max_batch=4, height=16, width=16, workers=2, quality="fast",
                  timeout=timeout) as pool:
    qpos, looks = _inputs(pool.rm, 4)
    want = pool.render(qpos, looks)
    victim = pool.pids[1]
    os.kill(victim, signal.SIGSTOP)   # alive, but answers nothing
    try:
      t0 = time.monotonic()
      got = pool.render(qpos, looks)
      took = time.monotonic() - t0
    finally:
      with contextlib.suppress(ProcessLookupError):   # the pool killed it already
        os.kill(victim, signal.SIGKILL)
    np.testing.assert_array_equal(got, want)
    assert pool.restarts == 1 and victim not in pool.pids
    assert took < timeout + 15, took   # the timeout, then a new worker's start-up
  err = capfd.readouterr().err
  assert f"render worker 1 (pid {victim}) unresponsive for 2 s; replacing it" in err
  assert "DMCR_WORKER_TIMEOUT" in err


def test_the_hung_worker_timeout_is_checked_before_anything_starts(monkeypatch):
  for bad in (0, -1, "soon", float("inf")):
    with pytest.raises(ValueError, match="worker_timeout must be a number of seconds > 0"):
      dmcr_jax.make("cartpole-balance", worker_timeout=bad)
  monkeypatch.setenv("DMCR_WORKER_TIMEOUT", "soon")
  with pytest.raises(ValueError, match="DMCR_WORKER_TIMEOUT must be a number of seconds > 0"):
    dmcr_jax.make("cartpole-balance")
