"""Experiment: MJX physics of N envs on the host CPU split into k groups, group i on XLA:CPU device i (one jit, async dispatch)."""
import os, time, json
import jax
ndev = int(os.environ.get("NDEV", "16"))
jax.config.update("jax_num_cpu_devices", ndev)
import numpy as np
import dmcr_jax  # noqa: F401 (sets MUJOCO_GL and the XLA:CPU flag before JAX starts)
from dmcr_jax import models, physics_env

def timeit(f, n=20):
  f(); f()
  t = time.perf_counter()
  for _ in range(n):
    f()
  return (time.perf_counter() - t) / n * 1e3

N = int(os.environ.get("N", "16"))
for task_name, fs in [("ball_in_cup-catch", 4), ("walker-walk", 2)]:
  task = models.load(task_name)
  cpus = jax.devices("cpu")
  seeds = np.zeros((N,), np.int32)
  es0 = jax.device_get(jax.jit(lambda k, s: physics_env.init(task, s, k, N))(
      jax.device_put(jax.random.key(0), cpus[0]), jax.device_put(seeds, cpus[0])))
  act = np.random.default_rng(0).uniform(-1, 1, (N, task.action_size)).astype(np.float32)
  stepj = jax.jit(lambda es, a, s: physics_env.step(task, s, fs, es, a))
  for k in [1, 2, 4, 8, 16]:
    if k > len(cpus) or N % k: continue
    n = N // k
    part = lambda x, i: x[i * n:(i + 1) * n]
    ess = [jax.device_put(jax.tree.map(lambda x: part(x, i), es0), cpus[i]) for i in range(k)]
    ss = [jax.device_put(part(seeds, i), cpus[i]) for i in range(k)]
    acts = [part(act, i) for i in range(k)]
    def go():
      outs = [stepj(ess[i], jax.device_put(acts[i], cpus[i]), ss[i]) for i in range(k)]
      for i, (e, r, t) in enumerate(outs):
        ess[i] = e
      np.concatenate(jax.device_get([o[1] for o in outs]))
    t0 = time.perf_counter(); go(); c = time.perf_counter() - t0
    ms = timeit(go)
    print(json.dumps(dict(task=task_name, n=N, frame_skip=fs, groups=k, ms_per_agent_step=round(ms, 2), first_s=round(c, 1))), flush=True)
