"""`jax.jit` compiler options for the suite's few programs whose run, not their
compilation, takes most of their time."""

import os


def run_faster() -> dict | None:
  """Compiler options that turn LLVM's optimisation passes back on (level 2) for one
  program, against the suite's `--xla_backend_optimization_level=0` (conftest's
  `compile_faster`): for a test's long training loop, whose run those passes shorten
  by more than they lengthen its compilation. None (the process's flags) when
  DMCR_TESTS_XLA_DEFAULTS is set, where every program compiles as a user's does."""
  if os.environ.get("DMCR_TESTS_XLA_DEFAULTS"):
    return None
  return {"xla_backend_optimization_level": 2}
