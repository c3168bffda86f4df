"""Shared test setup: headless GL for any MuJoCo rendering, quiet JAX on CPU.

Tiers: `pytest -m "not slow"` skips the tests marked slow (each over ~7 s on a
2-core CPU, or needing a module fixture that is) for a fast developer run; CI
runs every test. Tests marked full run a whole command at its defaults and only
with `--run-full`. One JAX compilation cache serves the whole session
(`share_compilations`); XLA's CPU backend compiles with its faster-compiling
emitters and without LLVM's optimisation passes (`compile_faster`), and Python's
cyclic garbage collector runs less often (`collect_less`): most of the suite's
time is tracing and compiling."""

import atexit
import gc
import os
import shutil
import subprocess
import sys
import tempfile

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("JAX_PLATFORMS", "cpu")


def share_compilations() -> None:
  """Points JAX's persistent compilation cache at one folder for the whole session.

  Many tests compile the same physics, renderer and learner (same task, sizes and
  flags) in different modules, xdist workers and subprocesses; with one cache an
  identical XLA program compiles once. Set before JAX is imported and inherited
  through the environment by xdist workers and subprocesses. A folder the user
  set (JAX_COMPILATION_CACHE_DIR) is kept; else a fresh one, removed at exit by
  the process that made it. Only programs that take a second or more to compile
  are written: the thousands of small eager-op programs recompile faster than
  they serialize, and each write is a call into XLA's executable serializer.
  """
  if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    folder = tempfile.mkdtemp(prefix="dmcr-jax-tests-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
  os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")


share_compilations()

FAST_COMPILE_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=0",
                      "--xla_cpu_parallel_codegen_split_count=1")


def compile_faster() -> None:
  """Adds `FAST_COMPILE_FLAGS` to `XLA_FLAGS` (inherited by xdist workers and
  subprocesses), each unless XLA_FLAGS names its option already; none when
  DMCR_TESTS_XLA_DEFAULTS is set (then the suite compiles as a user's program does).

  - `--xla_cpu_use_fusion_emitters=false`: XLA:CPU emits its fused elementwise
    loops with the older LLVM IR emitters instead of the MLIR fusion emitters,
    which compile the MJX physics, the ray caster and the learner in markedly less
    time and run them as fast.
  - `--xla_backend_optimization_level=0`: LLVM generates code without its
    optimisation passes. Most of the suite's time is compiling, and LLVM's passes
    are a large part of each compilation; the programs run slower, which the
    suite's few long loops afford.
  - `--xla_cpu_parallel_codegen_split_count=1`: LLVM generates each program's code
    as one module instead of splitting it (a copy of the module per part) to
    generate the parts on several threads. Two xdist workers keep both cores busy,
    so the split buys no time and its splitting and copying cost processor time.

  Results may differ from the defaults' in the last bits of float32 (another
  instruction order, e.g. where a multiply-add is fused), and two different
  programs computing the same values (a whole step and its composed parts) may
  differ from each other there: such comparisons allow a few float32 ulps, and
  every comparison against a reference has a tolerance far above that. XLA aborts
  the process on an unknown flag, so a short subprocess first checks that this
  jaxlib knows them.
  """
  flags = os.environ.get("XLA_FLAGS", "")
  if os.environ.get("DMCR_TESTS_XLA_DEFAULTS"):
    return
  extra = " ".join(f for f in FAST_COMPILE_FLAGS if f.split("=")[0] not in flags)
  if not extra:
    return
  probe = subprocess.run(
      [sys.executable, "-c", "import jax; jax.devices()"], capture_output=True, timeout=120,
      env=dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=f"{flags} {extra}"))
  if probe.returncode == 0:
    os.environ["XLA_FLAGS"] = f"{flags} {extra}".strip()


def collect_less() -> None:
  """Runs Python's cyclic garbage collector less often. Tracing an MJX step makes
  hundreds of thousands of objects that live until the trace ends; at the default
  thresholds the collector scans them (and the suite's other live objects) again
  and again, a large share of a trace's time. Freed cycles wait longer."""
  gc.set_threshold(100_000, 20, 10)


compile_faster()
collect_less()


def pytest_addoption(parser):
  parser.addoption("--run-full", action="store_true",
                   help="also run the tests marked full (a whole command at its "
                        "defaults, minutes each)")


def _scope(item):
  """The tests that share compiled programs: an item's xdist group (whose modules
  are sized to share them), or its module if it has none."""
  mark = item.get_closest_marker("xdist_group")
  return ("group", mark.args[0]) if mark and mark.args else ("module", item.nodeid.split("::", 1)[0])


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
  """After the last test of an xdist group, or of a module outside any group (its
  fixtures finalized), drops JAX's in-memory compilations: a worker would otherwise
  keep every program the suite compiled (gigabytes by the end). Later tests that
  need one again load it from the session's compilation cache; the modules of a
  group keep theirs, as retracing and loading a large program takes seconds."""
  yield
  if "jax" in sys.modules and (nextitem is None or _scope(item) != _scope(nextitem)):
    sys.modules["jax"].clear_caches()
    gc.collect()


def pytest_collection_modifyitems(config, items):
  if config.getoption("--run-full"):
    return
  skip = pytest.mark.skip(reason="a whole command at its defaults (minutes): pass "
                                 "--run-full to run it")
  for item in items:
    if "full" in item.keywords:
      item.add_marker(skip)
