"""Experiment: MJX physics of N envs on the host CPU split over P processes (each its own XLA:CPU, optionally pinned to cores).

Each process owns N / P envs, jits their agent step once and answers "step" messages over a pipe; the
parent sends every process its actions, then waits for all replies. Prints ms per agent step of all N
envs (median of --calls) for each P, and, with --taskset, a single process confined to 1 and 2 cores.

    PYTHONPATH=$PWD python3 experiments/probes/physics_processes.py --tasks ball_in_cup-catch,walker-walk
"""
import argparse
import json
import multiprocessing as mp
import os
import statistics
import time


def worker(conn, task_name, n, frame_skip, cores):
  if cores is not None:
    os.sched_setaffinity(0, cores)
  os.environ["JAX_PLATFORMS"] = "cpu"
  import jax
  import numpy as np
  from dmcr_jax import models, physics_env
  from dmcr_jax.models.base import physics_jit
  task = models.load(task_name)
  seeds = np.zeros((n,), np.int32)
  es = physics_jit(lambda k, s: physics_env.init(task, s, k, n))(jax.random.key(0), seeds)
  step = physics_jit(lambda es, a, s: physics_env.step(task, s, frame_skip, es, a))
  a = np.zeros((n, task.action_size), np.float32)
  es, r, _ = step(es, a, seeds)
  r.block_until_ready()
  conn.send(task.action_size)
  while True:
    msg = conn.recv()
    if msg is None:
      return
    es, r, _ = step(es, msg, seeds)
    conn.send(np.asarray(r))


def run(task_name, n, frame_skip, p, calls, cores_of):
  ctx = mp.get_context("spawn")
  pipes, procs = [], []
  for i in range(p):
    a, b = ctx.Pipe()
    proc = ctx.Process(target=worker, args=(b, task_name, n // p, frame_skip, cores_of(i)), daemon=True)
    proc.start()
    pipes.append(a)
    procs.append(proc)
  t0 = time.perf_counter()
  sizes = [c.recv() for c in pipes]
  ready_s = time.perf_counter() - t0
  import numpy as np
  rng = np.random.default_rng(0)
  times = []
  for _ in range(calls):
    acts = rng.uniform(-1, 1, (n, sizes[0])).astype(np.float32)
    t = time.perf_counter()
    for i, c in enumerate(pipes):
      c.send(acts[i * (n // p):(i + 1) * (n // p)])
    for c in pipes:
      c.recv()
    times.append(time.perf_counter() - t)
  for c in pipes:
    c.send(None)
  for proc in procs:
    proc.join()
  return statistics.median(times[2:]) * 1e3, ready_s


def main():
  ap = argparse.ArgumentParser()
  ap.add_argument("--tasks", default="ball_in_cup-catch,walker-walk")
  ap.add_argument("--n", type=int, default=16)
  ap.add_argument("--procs", default="1,2,4,8,16")
  ap.add_argument("--calls", type=int, default=30)
  ap.add_argument("--pin", action="store_true", help="process i on core i")
  ap.add_argument("--taskset", action="store_true", help="also one process on 1 and on 2 cores")
  args = ap.parse_args()
  skips = {"ball_in_cup-catch": 4, "walker-walk": 2, "cartpole-balance": 8, "cheetah-run": 4,
           "finger-spin": 2, "hopper-stand": 4}
  ncpu = os.cpu_count()
  for task in args.tasks.split(","):
    runs = [(int(p), (lambda i: {i % ncpu}) if args.pin else (lambda i: None), "pinned" if args.pin else "free")
            for p in args.procs.split(",")]
    if args.taskset:
      runs += [(1, lambda i: {0}, "1 core"), (1, lambda i: {0, 1}, "2 cores"), (1, lambda i: set(range(4)), "4 cores")]
    for p, cores_of, how in runs:
      ms, ready = run(task, args.n, skips[task], p, args.calls, cores_of)
      print(json.dumps(dict(task=task, n=args.n, processes=p, cores=how, ms_per_agent_step=round(ms, 2),
                            ready_s=round(ready, 1))), flush=True)


if __name__ == "__main__":
  main()
