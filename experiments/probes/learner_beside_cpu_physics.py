"""Experiment: the learner's updates/s alone vs with MJX physics stepping on XLA:CPU in another thread."""
import threading, time
import jax, numpy as np
import dmcr_jax  # noqa: F401 (sets MUJOCO_GL and the XLA:CPU flag before JAX starts)
from dmcr_jax import models, physics_env
from dmcr_jax.train import sac, step as train_step
from dmcr_jax.benchmarks.learner import filled_buffers, _agents
cfg = sac.SACConfig(compute_dtype="bfloat16")
spec = train_step.StepSpec(agents=1, num_envs=16, warmup_steps=0, utd=1.0, sac=cfg, agent_loop="map", low=(-1.0,), high=(1.0,))
agents = _agents(1, (84, 84, 9), 2, cfg)
buffers = filled_buffers(1, 100_000, 84, 3, 2)
learner = train_step.init_learner(agents, buffers, jax.random.key(0), 0, spec)
def learn_rate(learner, calls=15, pairs=4):
  learner = train_step.learn_jit(learner, pairs=pairs, spec=spec); jax.block_until_ready(learner.metrics)
  t = time.perf_counter()
  for _ in range(calls):
    learner = train_step.learn_jit(learner, pairs=pairs, spec=spec)
  jax.block_until_ready(learner.metrics)
  return learner, calls * pairs * 2 / (time.perf_counter() - t)
learner, r0 = learn_rate(learner); print("alone", r0, flush=True)
task = models.load("ball_in_cup-catch"); cpu = jax.devices("cpu")[0]; N = 16
es = jax.jit(lambda k, s: physics_env.init(task, s, k, N))(jax.device_put(jax.random.key(0), cpu), jax.device_put(np.zeros(N, np.int32), cpu))
stepj = jax.jit(lambda es, a, s: physics_env.step(task, s, 4, es, a))
seeds = jax.device_put(np.zeros(N, np.int32), cpu); act = np.zeros((N, task.action_size), np.float32)
jax.block_until_ready(stepj(es, act, seeds))
stop = False; count = [0]
def phys():
  e = es
  while not stop:
    e, r, _ = stepj(e, act, seeds); jax.block_until_ready(r); count[0] += 1
th = threading.Thread(target=phys); th.start()
t = time.perf_counter(); learner, r1 = learn_rate(learner, calls=30); dt = time.perf_counter() - t
stop = True; th.join()
print("with physics thread", r1, "physics steps/s", count[0] / dt, flush=True)
t = time.perf_counter(); n = 0
while time.perf_counter() - t < 3:
  jax.block_until_ready(stepj(es, act, seeds)[1]); n += 1
print("physics alone steps/s", n / (time.perf_counter() - t))
learner, r2 = learn_rate(learner); print("alone again", r2, flush=True)
