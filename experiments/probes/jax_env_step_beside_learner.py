"""Experiment: where the JAX env's step (physics on the host CPU, frames on the GPU)
spends its time while the learner's updates run on the GPU.

The loop of `train` (host driver) reduced to its device calls: each iteration launches a
`learn_jit` call of 8 pairs from a thread, then steps the env (`step_async`,
`step_wait`) with random actions, then waits for an action computed on the GPU from the
new frames. The env's internals are timed by wrapping them: the physics call and its
result, the transfer of the physics state to the GPU, the frames' dispatch, the host
fields. Prints the median ms of each part, with the learner and without.
"""
import collections, threading, time
import jax, jax.numpy as jnp, numpy as np
import dmcr_jax
from dmcr_jax import env as env_mod, jax_env
from dmcr_jax.train import sac, step as train_step
from dmcr_jax.benchmarks.learner import filled_buffers, _agents

cfg = sac.SACConfig(compute_dtype="bfloat16")
spec = train_step.StepSpec(agents=1, num_envs=16, warmup_steps=0, utd=1.0, sac=cfg,
                           agent_loop="map", low=(-1.0,), high=(1.0,))
learner = train_step.init_learner(_agents(1, (84, 84, 9), 1, cfg),
                                  filled_buffers(1, 100_000, 84, 3, 1), jax.random.key(0), 0, spec)
times = collections.defaultdict(list)

def timed(name, fn):
  def wrapper(*a, **k):
    t = time.perf_counter(); out = fn(*a, **k); times[name].append(time.perf_counter() - t)
    return out
  return wrapper

env = dmcr_jax.make("ball_in_cup-catch", num_envs=16, visual_seeds=0, renderer="jax",
                    physics_device="cpu", obs_on_device=True)
jax_env.observe = timed("observe dispatch", jax_env.observe)
orig_put = jax.device_put
env_mod.jax.device_put = timed("device_put", orig_put)
env._adopt = timed("adopt (host fields)", env._adopt)
step_fn = env._step
def physics(*a):
  t = time.perf_counter(); out = step_fn(*a); times["physics dispatch"].append(time.perf_counter() - t)
  jax.block_until_ready(out); times["physics done"].append(time.perf_counter() - t)
  return out
env._step = physics
policy = jax.jit(lambda o: jnp.mean(o.astype(jnp.float32), axis=(1, 2, 3)))
env.reset(seed=0)
box = {}
def launch(l):
  box["l"] = train_step.learn_jit(l, pairs=8, spec=spec)
for busy in (False, True):
  for i in range(25):
    if i == 5:
      times.clear()
    t0 = time.perf_counter()
    th = threading.Thread(target=launch, args=(learner,)) if busy else None
    if th: th.start()
    t = time.perf_counter(); env.step_async(np.random.uniform(-1, 1, (16, 2)).astype(np.float32))
    obs, *_ = env.step_wait(); times["step"].append(time.perf_counter() - t)
    if th: th.join(); learner = box["l"]
    t = time.perf_counter(); np.asarray(policy(obs)); times["act wait"].append(time.perf_counter() - t)
    times["iteration"].append(time.perf_counter() - t0)
  print("learner running" if busy else "alone", {k: round(float(np.median(v)) * 1e3, 2) for k, v in times.items()}, flush=True)
