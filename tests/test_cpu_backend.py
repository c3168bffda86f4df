"""XLA's CPU backend as the package sets it up: 1,024 walkers step to the end.

With XLA's default CPU scheduler the first step of `make("walker-walk", 1024)`, and
of the task's bare vmapped physics step that it runs, never finished on the 2-core
machine (every thread parked on a futex; 1,000 envs ran). `dmcr_jax` sets
``--xla_cpu_enable_concurrency_optimized_scheduler=false`` at import unless the user
set that flag.
"""

import os
import subprocess
import sys

import pytest

STEP_1024_WALKERS = """
import dmcr_jax
import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx
from dmcr_jax.models import base
task = dmcr_jax.load("walker-walk")
data = jax.vmap(lambda _: mjx.make_data(task.mjx_model))(jnp.zeros(1024))
step = base.physics_jit(jax.vmap(task.advance))  # as the env's physics jits it
out = step(data, jnp.zeros((1024, task.action_size), jnp.float32))
print("stepped", out.qpos.shape, bool(np.isfinite(np.asarray(out.qpos)).all()), flush=True)
"""


def _env(xla_flags=None):
  env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
  env["JAX_PLATFORMS"] = "cpu"
  if xla_flags is not None:
    env["XLA_FLAGS"] = xla_flags
  return env


SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"


def _session_flags_but_the_scheduler() -> str | None:
  """This session's XLA_FLAGS (the tests' compile setting, `tests/conftest.py`) less
  the scheduler flag, which the package must add itself; None if nothing is left."""
  flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(SCHEDULER_FLAG)]
  return " ".join(flags) or None


@pytest.mark.slow
@pytest.mark.xdist_group("walker")
def test_1024_vmapped_walkers_step_on_cpu():
  # The step hangs without the package's scheduler flag with or without the
  # session's compile flags, which only make it compile faster.
  out = subprocess.run([sys.executable, "-c", STEP_1024_WALKERS],
                       env=_env(_session_flags_but_the_scheduler()),
                       capture_output=True, text=True, timeout=240)
  assert out.returncode == 0, out.stderr[-2000:]
  assert "stepped (1024, 9) True" in out.stdout


def test_the_flag_is_added_once_and_a_users_choice_is_kept():
  show = "import os, dmcr_jax; print('XLA_FLAGS=' + os.environ['XLA_FLAGS'])"

  def run(flags):
    out = subprocess.run([sys.executable, "-c", show], env=_env(flags),
                         capture_output=True, text=True, timeout=120).stdout
    return [line for line in out.splitlines() if line.startswith("XLA_FLAGS=")][0][10:]
  flag = SCHEDULER_FLAG
  assert run(None) == f"{flag}=false"
  assert run("--xla_dump_to=/tmp/x") == f"--xla_dump_to=/tmp/x {flag}=false"
  assert run(f"{flag}=true") == f"{flag}=true"


@pytest.mark.slow
def test_env_physics_compiles_without_ynnpack_fusions():
  """The env's jitted physics takes `physics_compiler_options` (`dmcr_jax.models.base`):
  at 32 ball_in_cup envs, past the size where XLA:CPU's default hands products to
  YNNPACK, the compiled step holds no YNNPACK fusion."""
  import jax
  import numpy as np

  from dmcr_jax import env_base
  from dmcr_jax import models
  from dmcr_jax.models import base
  assert base.physics_compiler_options() == base.NO_YNN_FUSIONS  # this jaxlib knows it
  task = models.load("ball_in_cup-catch")
  init, step = env_base._physics_fns(task, 32, 4, False)
  seeds = np.zeros(32, np.int32)
  states = jax.eval_shape(init, jax.random.key(0), seeds)
  actions = jax.ShapeDtypeStruct((32, task.action_size), np.float32)
  hlo = step.lower(states, actions, seeds).compile().as_text()
  assert "ynn_fusion" not in hlo
