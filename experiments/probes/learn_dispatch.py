"""Experiment: how long the host is held by dispatching `dmcr_jax.train.step.learn_jit`, against the
call's whole time, for 1 and 8 update pairs per call (the XLA flags in XLA_FLAGS apply).

If dispatching an update call holds the host thread for a large part of the call's GPU
time (kernel launches, loop conditions read back), the host driver cannot step the env
meanwhile. One JSON line per pair count on stdout:

    python3 experiments/probes/learn_dispatch.py
"""
import json
import os
import time

import jax

import dmcr_jax  # noqa: F401 (sets MUJOCO_GL and the XLA:CPU flag before JAX starts)
from dmcr_jax.benchmarks.learner import _agents, filled_buffers
from dmcr_jax.train import sac
from dmcr_jax.train import step as train_step

cfg = sac.SACConfig(compute_dtype="bfloat16")
spec = train_step.StepSpec(agents=1, num_envs=16, warmup_steps=0, utd=1.0, sac=cfg,
                           agent_loop="map", low=(-1.0,), high=(1.0,))
learner = train_step.init_learner(_agents(1, (84, 84, 9), 6, cfg),
                                  filled_buffers(1, 100_000, 84, 3, 6), jax.random.key(0), 0,
                                  spec)
for pairs in (1, 8):
  for _ in range(2):  # compile, and a call with the output's layout
    learner = jax.block_until_ready(train_step.learn_jit(learner, pairs=pairs, spec=spec))
  held, whole, calls = 0.0, 0.0, max(8, 64 // pairs)
  for _ in range(calls):
    t0 = time.perf_counter()
    learner = train_step.learn_jit(learner, pairs=pairs, spec=spec)
    t1 = time.perf_counter()
    learner = jax.block_until_ready(learner)
    held, whole = held + t1 - t0, whole + time.perf_counter() - t0
  print(json.dumps(dict(pairs=pairs, xla_flags=os.environ.get("XLA_FLAGS", ""),
                        dispatch_ms=round(1e3 * held / calls, 2),
                        call_ms=round(1e3 * whole / calls, 2),
                        updates_per_s=round(2 * pairs * calls / whole, 1))), flush=True)
