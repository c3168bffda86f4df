"""Experiment: does a host→GPU transfer wait for the updates queued on the GPU?

A `learn_jit` call of 8 pairs is launched from a thread; 25 ms later (its launch is
done, its kernels run) the main thread times, per variant, how long until a small
array put on the GPU is ready; the same with the GPU idle. Variants: `jax.device_put`
of a NumPy array; of an XLA:CPU array (what the JAX env does with the host physics
state); the same pytree as the env's physics state.
"""
import threading, time
import jax, numpy as np
import dmcr_jax  # noqa: F401
from dmcr_jax import models, physics_env
from dmcr_jax.train import sac, step as train_step
from dmcr_jax.benchmarks.learner import filled_buffers, _agents

cfg = sac.SACConfig(compute_dtype="bfloat16")
spec = train_step.StepSpec(agents=1, num_envs=16, warmup_steps=0, utd=1.0, sac=cfg,
                           agent_loop="map", low=(-1.0,), high=(1.0,))
learner = train_step.init_learner(_agents(1, (84, 84, 9), 2, cfg),
                                  filled_buffers(1, 100_000, 84, 3, 2), jax.random.key(0), 0, spec)
gpu, cpu = jax.devices()[0], jax.devices("cpu")[0]
task = models.load("ball_in_cup-catch")
es = jax.jit(lambda k, s: physics_env.init(task, s, k, 16))(
    jax.device_put(jax.random.key(0), cpu), jax.device_put(np.zeros(16, np.int32), cpu))
host = np.ones((16, 64), np.float32)
on_cpu = jax.device_put(host, cpu)
variants = {
    "numpy": lambda: jax.device_put(host, gpu),
    "xla_cpu_array": lambda: jax.device_put(on_cpu, gpu),
    "physics_state": lambda: jax.device_put(es, gpu),
    "numpy_via_np_copy": lambda: jax.device_put(np.asarray(on_cpu), gpu),
}
for _ in range(2):
  learner = train_step.learn_jit(learner, pairs=8, spec=spec)
  jax.block_until_ready(learner.metrics)
  for fn in variants.values():
    jax.block_until_ready(fn())
box = {}
def launch():
  box["l"] = train_step.learn_jit(learner, pairs=8, spec=spec)
for name, fn in variants.items():
  for busy in (False, True):
    times = []
    for _ in range(5):
      if busy:
        th = threading.Thread(target=launch); th.start(); time.sleep(0.025)
      t = time.perf_counter(); x = fn(); t1 = time.perf_counter()
      jax.block_until_ready(x); t2 = time.perf_counter()
      times.append(((t1 - t) * 1e3, (t2 - t) * 1e3))
      if busy:
        th.join(); learner = box["l"]; jax.block_until_ready(learner.metrics)
    call, ready = np.median(np.array(times), axis=0)
    print(f"{name:20s} gpu {'busy' if busy else 'idle'}: call {call:.2f} ms, ready {ready:.2f} ms", flush=True)
