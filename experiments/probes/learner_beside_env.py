"""Experiment: the learner's updates/s and the pixel env's agent steps/s, each alone and both at once.

The training loop runs the updates on the accelerator while the env steps on the host
(physics on XLA:CPU, frames from the render pool's workers or the JAX ray caster). If
either slows the other when they run together (cores, the GPU shared between the
workers' GL contexts and the learner's CUDA context, one CUDA stream), this shows by
how much, and in which of the env's parts (`env.timings`: physics, transfer, render,
copy, in ms per agent step).

    MUJOCO_GL=egl python3 experiments/probes/learner_beside_env.py \\
        [--task ball_in_cup-catch] [--num-envs 16] [--renderer pool] [--seconds 10] \\
        [--gl osmesa] [--workers 16]

One JSON line per setting on stdout.
"""
import argparse
import json
import threading
import time

import jax
import numpy as np

import dmcr_jax
from dmcr_jax.benchmarks.learner import _agents, filled_buffers
from dmcr_jax.train import sac
from dmcr_jax.train import step as train_step


def learner_loop(seconds: float, pairs: int = 8):
  """A callable that runs `learn_jit` calls of `pairs` pairs for `seconds`; returns updates/s."""
  cfg = sac.SACConfig(compute_dtype="bfloat16")
  spec = train_step.StepSpec(agents=1, num_envs=16, warmup_steps=0, utd=1.0, sac=cfg,
                             agent_loop="map", low=(-1.0,), high=(1.0,))
  state = [train_step.init_learner(_agents(1, (84, 84, 9), 6, cfg),
                                   filled_buffers(1, 100_000, 84, 3, 6), jax.random.key(0),
                                   0, spec)]
  for _ in range(2):  # compile, and a call with the output's layout
    state[0] = train_step.learn_jit(state[0], pairs=pairs, spec=spec)
    jax.block_until_ready(state[0].metrics)

  def run():
    calls, t = 0, time.perf_counter()
    while time.perf_counter() - t < seconds:
      state[0] = train_step.learn_jit(state[0], pairs=pairs, spec=spec)
      jax.block_until_ready(state[0].metrics)
      calls += 1
    return 2 * pairs * calls / (time.perf_counter() - t)
  return run


def env_loop(env, seconds: float):
  """A callable that steps `env` with random actions for `seconds`; returns
  (agent steps/s of the whole batch, ms per step of each env part)."""
  rng = np.random.default_rng(0)
  env.reset(seed=0)
  for _ in range(3):
    env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))

  def run():
    env.reset_timings()
    steps, t = 0, time.perf_counter()
    while time.perf_counter() - t < seconds:
      env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
      steps += 1
    rate = steps / (time.perf_counter() - t)
    return rate, {k: round(1e3 * v / max(steps, 1), 2) for k, v in env.timings.items()}
  return run


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--task", default="ball_in_cup-catch")
  p.add_argument("--num-envs", type=int, default=16)
  p.add_argument("--renderer", default="pool", choices=("pool", "jax"))
  p.add_argument("--seconds", type=float, default=10.0)
  p.add_argument("--gl", default=None, choices=("egl", "osmesa"), help="the pool's GL backend")
  p.add_argument("--workers", type=int, default=None, help="the pool's worker processes")
  a = p.parse_args()
  extra = (dict(quality="exact", gl=a.gl, workers=a.workers) if a.renderer == "pool"
           else dict(obs_on_device=True))
  env = dmcr_jax.make(a.task, num_envs=a.num_envs, renderer=a.renderer, image_size=84,
                      physics_device="cpu", **extra)
  with env:
    learn = learner_loop(a.seconds)
    step_env = env_loop(env, a.seconds)
    base = dict(task=a.task, num_envs=a.num_envs, renderer=a.renderer, gl=a.gl,
                workers=a.workers, device=jax.devices()[0].device_kind)
    print(json.dumps(dict(base, setting="learner alone", updates_per_s=round(learn(), 1))),
          flush=True)
    rate, parts = step_env()
    print(json.dumps(dict(base, setting="env alone", env_steps_per_s=round(rate, 1),
                          ms=parts)), flush=True)
    out = {}
    thread = threading.Thread(target=lambda: out.update(env=step_env()))
    thread.start()
    updates = learn()
    thread.join()
    rate, parts = out["env"]
    print(json.dumps(dict(base, setting="together", updates_per_s=round(updates, 1),
                          env_steps_per_s=round(rate, 1), ms=parts)), flush=True)


if __name__ == "__main__":
  main()
