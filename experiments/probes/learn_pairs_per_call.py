"""Experiment: seconds per dmcr_jax.train.step.learn_jit call against update pairs per call (per-call overhead)."""
import time, json
import jax
import dmcr_jax  # noqa: F401 (sets MUJOCO_GL and the XLA:CPU flag before JAX starts)
from dmcr_jax.train import sac, step as train_step
from dmcr_jax.benchmarks.learner import filled_buffers, _agents
cfg = sac.SACConfig(compute_dtype="bfloat16")
spec = train_step.StepSpec(agents=1, num_envs=16, warmup_steps=0, utd=1.0, sac=cfg, agent_loop="map", low=(-1.0,), high=(1.0,))
learner = train_step.init_learner(_agents(1, (84, 84, 9), 6, cfg), filled_buffers(1, 100_000, 84, 3, 6), jax.random.key(0), 0, spec)
for pairs in (1, 4, 16):
  learner = train_step.learn_jit(learner, pairs=pairs, spec=spec); jax.block_until_ready(learner.metrics)
  learner = train_step.learn_jit(learner, pairs=pairs, spec=spec); jax.block_until_ready(learner.metrics)
  calls = max(4, 64 // pairs)
  t = time.perf_counter()
  for _ in range(calls):
    learner = train_step.learn_jit(learner, pairs=pairs, spec=spec)
  jax.block_until_ready(learner.metrics)
  dt = (time.perf_counter() - t) / calls
  print(json.dumps(dict(pairs=pairs, ms_per_call=round(dt * 1e3, 2), updates_per_s=round(2 * pairs / dt, 1))), flush=True)
