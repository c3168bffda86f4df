"""Benchmark of the learner (SAC+AUG, CURL, SAC+AE): gradient updates per second.

Times exactly what `train` runs: `dmcr_jax.train.step.learn_jit`, a jitted call that loops
``--pairs`` `sac.update_pair`s (two updates each, actor and targets on the
second) for K agents, each sampling its own batches from its own full device
replay buffer (random 84×84 frames, 3-frame stacks rebuilt at sampling, as in
training), with the paper's defaults (batch 256, DrQ augmentation, β = .9,
λ = 1e-5). Each row varies the number of agents K, the compute dtype (float32,
bfloat16), how the agents are batched (``vmap``: one batched computation,
``map``: one after the other inside the call) and, with ``--algos``, the
algorithm (`dmcr_jax.train.sac.ALGOS`; each at its own defaults: CURL samples 100×100
frames and crops them to 84, SAC+AE uses batch 128 unless ``--batch`` is given). The baseline measured in the same
run is a plain Python loop over one jitted `sac.update` per gradient step (one
agent, float32, batch sampled in the same call), i.e. one host dispatch per update
as a PyTorch-style loop does.

Compile time and run time are reported apart; the run time is the median of
several calls (each ended by ``block_until_ready``) over at least ``--seconds``.
Rows go to ``--out`` (JSON lines, appended) and a Markdown table beside it.
``--cost`` instead prints XLA's cost analysis of one update (GFLOP and GB accessed,
from the compiled module; nothing runs), which turns updates/s into FLOP/s.

``--devices 1,2,4,8`` measures each row's agents sharded over that many local
devices (as `train` shards them: `shard_map` over the agent axis, K / D agents
per device), one row per count; every count must divide every K of ``--agents``
(1 always does) and be at most the local device count, or the run is refused
before anything compiles. With several counts each row also carries its scaling
efficiency: its agent-updates/s over D times those of the same row on one device
(1.0: linear).

Usage::

    python -m dmcr_jax.benchmarks.learner [--agents 1,8] [--dtypes float32,bfloat16] \\
        [--loops vmap,map] [--algos sac_aug,curl,sac_ae] [--augs drq,cj+drq] [--batch 256] \\
        [--pairs 25] [--devices 1,2,4,8] [--out PATH]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.benchmarks import rows as R
from dmcr_jax.train import loop, replay, sac
from dmcr_jax.train import step as train_step


def filled_buffers(k: int, capacity: int, size: int, stack: int, action_size: int,
                   seed: int = 0) -> replay.ReplayBuffer:
  """K full replay buffers of one env each, random frames, an episode every 125 rows."""
  one = replay.init(capacity, 1, (size, size, 3), action_size, stack)
  t = one.ring_size
  key = jax.random.key(seed)
  frames = jax.random.randint(key, (k, 1, t, size, size, 3), 0, 256, jnp.int32)
  return one.replace(
      frames=frames.astype(jnp.uint8),
      action=jax.random.uniform(key, (k, 1, t, action_size), minval=-1, maxval=1),
      reward=jax.random.uniform(key, (k, 1, t)),
      first=jnp.broadcast_to(jnp.arange(t) % 125 == 0, (k, 1, t)),
      pos=jnp.zeros((k, 1), jnp.int32),
      count=jnp.full((k, 1), t, jnp.int32))


def device_counts(text: str, agents: list[int], available: int) -> list[int]:
  """`--devices`' comma-separated counts, sorted and deduplicated.

  Args:
    text: e.g. "1,2,4".
    agents: every K the run measures; each count must divide each of them (1
      always does).
    available: the local device count.

  Raises:
    ValueError: naming the valid counts, for a count that is not a positive
      int, exceeds `available` or does not divide some K.
  """
  valid = [n for n in range(1, available + 1)
           if all(n in loop.valid_device_counts(k, available) for k in agents)]
  where = (f"valid counts for K = {','.join(map(str, agents))} on {available} local "
           f"device{'s' if available != 1 else ''}: {', '.join(map(str, valid))}")
  counts = []
  for item in text.split(","):
    item = item.strip()
    if not item.isdigit() or int(item) < 1:
      raise ValueError(f"{item!r} is not a positive device count; {where}")
    n = int(item)
    if n > available:
      raise ValueError(f"{n} devices: more than the local devices; {where}")
    if n not in valid:
      odd = [k for k in agents if k % n]
      raise ValueError(f"{n} devices: K = {','.join(map(str, odd))} agents is not a "
                       f"multiple of {n} (each device takes K / {n} agents); {where}")
    counts.append(n)
  return sorted(set(counts))


def scaling_efficiency(rate: float | None, rate_one: float | None, devices: int
                       ) -> float | None:
  """`rate` (a total over all agents, per second) on `devices` devices over
  `devices` × `rate_one`, the same measurement on one device (1.0: linear
  scaling); None when either rate is missing."""
  if not rate or not rate_one:
    return None
  return round(rate / (devices * rate_one), 3)


def _agents(k: int, obs_shape, action_size: int, config: sac.SACConfig):
  return jax.vmap(lambda s: sac.init_agent(jax.random.key(s), obs_shape, action_size,
                                           config))(jnp.arange(k))


def scanned_workload(k: int = 1, dtype: str = "float32", agent_loop: str = "vmap",
                     batch: int | None = None, pairs: int = 25, size: int = 84,
                     stack: int = 3, action_size: int = 6, capacity: int = 10_000,
                     algo: str = "sac_aug", aug: str | None = None, devices: int = 1):
  """`dmcr_jax.train.step.learn_jit` for K agents on full random buffers, ready to call repeatedly.

  `batch` None takes the algorithm's default; for CURL the frames are rendered
  ``curl_crop + 16`` pixels (`size` is the encoder's input). `aug` None takes
  the algorithm's default augmentation (SAC+AUG: DrQ). `devices`: the agents and
  their buffers are sharded over that many local devices, as `train` shards them
  (`dmcr_jax.train.loop.agent_mesh`; it must divide K).

  Returns:
    (call, config, frame side): ``call()`` runs `pairs` update pairs of every
    agent (one jitted call; the agents are carried from call to call, since the
    update donates them) and returns the new agents; the first call compiles.
  """
  config = sac.SACConfig(algo=algo, batch_size=batch, compute_dtype=dtype,
                         **({"aug": aug} if aug else {}),
                         **({"curl_crop": size} if algo == "curl" else {}))
  if algo == "curl":
    size = size + 16
  obs_shape = (size, size, 3 * stack)
  buffers = filled_buffers(k, capacity, size, stack, action_size)
  spec = train_step.StepSpec(agents=k, num_envs=1, warmup_steps=0, utd=1.0, sac=config,
                             agent_loop=agent_loop, low=(-1.0,) * action_size,
                             high=(1.0,) * action_size)
  mesh = loop.agent_mesh(k, devices)
  learner = [train_step.init_learner(
      loop.put_agents(_agents(k, obs_shape, action_size, config), mesh),
      loop.put_agents(buffers, mesh), jax.random.key(1), 0, spec)]
  update = functools.partial(train_step.learn_jit, pairs=pairs, spec=spec, mesh=mesh)

  def call():
    learner[0] = update(learner[0])   # donated: the buffers pass through unchanged
    return learner[0].agents
  # The compiled module (its text for dmcr_jax.benchmarks.profile --by source, its cost for
  # --cost); compiles again.
  call.compiled = lambda: train_step.learn_jit.lower(learner[0], **update.keywords).compile()
  call.hlo_text = lambda: call.compiled().as_text()
  return call, config, size


def bench_scanned(k: int, dtype: str, agent_loop: str, batch: int | None, pairs: int,
                  size: int, stack: int, action_size: int, capacity: int, seconds: float,
                  algo: str = "sac_aug", aug: str | None = None, devices: int = 1) -> dict:
  """Updates/s of `dmcr_jax.train.step.learn_jit` for K agents sharded over `devices` local
  devices (`scanned_workload`); one result row."""
  call, config, size = scanned_workload(k, dtype, agent_loop, batch, pairs, size, stack,
                                        action_size, capacity, algo, aug, devices)
  timing = R.measure(call, repeats=3, seconds=seconds, warmup=2)  # the first call compiles
  compile_s, per_call, times = timing.compile_s, timing.run_s, np.asarray(timing.times)
  updates = 2 * pairs
  return dict(kind="scanned", algo=algo, aug=",".join(config.aug_names) or "-", agents=k,
              devices=devices, dtype=dtype, agent_loop=agent_loop, batch=config.batch_size, frame_side=size,
              pairs_per_call=pairs, compile_s=round(compile_s, 2), reps=int(times.size),
              ms_per_call=round(per_call * 1e3, 3),
              updates_per_s_per_agent=round(updates / per_call, 1),
              agent_updates_per_s=round(k * updates / per_call, 1))


def bench_python_loop(batch: int | None, size: int, stack: int, action_size: int, capacity: int,
                      seconds: float) -> dict:
  """The baseline: one jitted `sac.update` (with its sampling) per host call."""
  config = sac.SACConfig(batch_size=batch)
  batch = config.batch_size
  agent = _agents(1, (size, size, 3 * stack), action_size, config)
  agent = jax.tree.map(lambda x: x[0], agent)
  buffer = jax.tree.map(lambda x: x[0], filled_buffers(1, capacity, size, stack, action_size))

  @functools.partial(jax.jit, static_argnames=("update_actor",), donate_argnums=(0,))
  def one_update(agent, key, update_actor):
    k_sample, k_update = jax.random.split(key)
    batch_ = replay.sample(buffer, k_sample, batch)
    return sac.update(agent, batch_, k_update, config, update_actor=update_actor)[0]

  key = jax.random.key(2)
  t0 = time.perf_counter()
  agent = one_update(agent, key, update_actor=False)
  agent = one_update(agent, key, update_actor=True)
  jax.block_until_ready(agent)
  compile_s = time.perf_counter() - t0
  n = 20

  carried = [agent]  # donated by each update

  def call():
    for i in range(n):  # a host dispatch per update, as a Python training loop
      carried[0] = one_update(carried[0], jax.random.fold_in(key, i), update_actor=i % 2 == 1)
    return carried[0]

  times = np.asarray(R.time_calls(call, repeats=3, seconds=seconds, warmup=1))
  per_update = float(np.median(times)) / n
  return dict(kind="python_loop", algo="sac_aug", agents=1, devices=1, dtype="float32",
              agent_loop="-",
              batch=batch,
              pairs_per_call=0, compile_s=round(compile_s, 2), reps=int(times.size),
              ms_per_call=round(per_update * 1e3, 3),
              updates_per_s_per_agent=round(1 / per_update, 1),
              agent_updates_per_s=round(1 / per_update, 1))


def markdown(rows: list[dict]) -> str:
  """All rows as one Markdown table, newest last."""
  return R.table(rows, [
      ("device", "device_kind"), ("kind", "kind"), ("algo", lambda r: r.get("algo", "sac_aug")),
      ("aug", lambda r: r.get("aug", "drq" if r.get("algo", "sac_aug") == "sac_aug" else "-")),
      ("agents", "agents"), ("devices", lambda r: r.get("devices", 1)), ("dtype", "dtype"),
      ("agent loop", "agent_loop"),
      ("batch", "batch"), ("updates per call", lambda r: 2 * r["pairs_per_call"] or 1),
      ("compile s", lambda r: f"{r['compile_s']:.1f}"),
      ("ms per call", lambda r: f"{r['ms_per_call']:.1f}"),
      ("updates/s per agent", lambda r: f"{r['updates_per_s_per_agent']:,.0f}"),
      ("agent-updates/s", lambda r: f"{r['agent_updates_per_s']:,.0f}"),
      ("scaling", lambda r: R.fmt(r.get("scaling_efficiency"), ".2f")),
      ("× baseline", lambda r: R.fmt(r.get("x_baseline"), ".1f")),
      ("UTC", lambda r: r["time_utc"][11:16])])


PYTHON_LOOP = "python loop (one dispatch per update)"
"""The baseline's name in the suite's rows."""


def variant(row: dict) -> str:
  """The row's line in the suite's plot: algorithm, K, dtype, loop and devices."""
  if row["kind"] == "python_loop":
    return PYTHON_LOOP
  algo, k, n = row.get("algo", "sac_aug"), row["agents"], row.get("devices") or 1
  return (("" if algo == "sac_aug" else f"{algo} ") + f"K={k} {row['dtype']}"
          + (f" {row['agent_loop']}" if k > 1 else "") + (f" on {n} devices" if n > 1 else ""))


def update_cost(dtype: str = "float32", algo: str = "sac_aug", batch: int | None = None,
                size: int = 84, stack: int = 3, action_size: int = 6) -> dict:
  """XLA's cost analysis of one agent's update pair (`scanned_workload` with one
  pair per call) on the default backend, halved: floating-point operations and
  bytes accessed per gradient update. Compiles once; runs nothing."""
  batch = batch or sac.SACConfig(algo=algo).batch_size
  call, config, side = scanned_workload(1, dtype, "vmap", batch, 1, size, stack,
                                        action_size, 4 * batch, algo)
  cost = call.compiled().cost_analysis()
  cost = cost[0] if isinstance(cost, (list, tuple)) else cost
  return dict(kind="cost", algo=algo, dtype=dtype, batch=config.batch_size, frame_side=side,
              gflop_per_update=round(cost["flops"] / 2e9, 2),
              gbytes_per_update=round(cost["bytes accessed"] / 2e9, 2))


def main(argv=None) -> None:
  """Command-line entry: the rows, appended to --out, and the Markdown table."""
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--agents", default="1,8", help="comma-separated K values")
  p.add_argument("--dtypes", default="float32,bfloat16")
  p.add_argument("--loops", default="vmap,map", help="agent batching for K > 1")
  p.add_argument("--algos", default="sac_aug", help="comma-separated: sac_aug, curl, sac_ae")
  p.add_argument("--augs", default=None,
                 help="comma-separated augmentations (`dmcr_jax.augment` names, e.g. "
                      "drq,cj+drq,nr+drq) to run for each algorithm; default: its own")
  p.add_argument("--batch", type=int, default=None,
                 help="default: each algorithm's (256; SAC+AE 128)")
  p.add_argument("--pairs", type=int, default=25, help="update pairs per jitted call")
  p.add_argument("--size", type=int, default=84)
  p.add_argument("--stack", type=int, default=3)
  p.add_argument("--action-size", type=int, default=6)
  p.add_argument("--capacity", type=int, default=10_000, help="buffer rows per agent")
  p.add_argument("--seconds", type=float, default=3.0)
  p.add_argument("--no-baseline", action="store_true")
  p.add_argument("--cost", action="store_true",
                 help="only print XLA's cost analysis (GFLOP and GB per update) of each "
                      "algorithm and dtype, one JSON line each, and stop (nothing is timed "
                      "or written)")
  p.add_argument("--devices", default="1",
                 help="comma-separated local device counts to shard the agents over, a "
                      "row each (e.g. 1,2,4,8; each must divide every K; default: "
                      "%(default)s)")
  p.add_argument("--out", default=None,
                 help="JSONL (default benchmarks/results/learner_<device>.jsonl)")
  a = p.parse_args(argv)
  agents = [int(k) for k in a.agents.split(",")]
  for dtype in a.dtypes.split(","):
    sac.SACConfig(compute_dtype=dtype)  # fails early on a bad name
  augs = a.augs.split(",") if a.augs else [None]
  for aug in augs:
    if aug:
      try:
        sac.SACConfig(aug=aug)
      except ValueError as e:
        p.error(f"--augs: {e}")
  for name in a.algos.split(","):
    if name not in sac.ALGOS:
      p.error(f"--algos: {name!r} is not one of {', '.join(sac.ALGOS)}")
  for name in a.loops.split(","):
    if name not in loop.AGENT_LOOPS:
      p.error(f"--loops: {name!r} is not one of {', '.join(loop.AGENT_LOOPS)}")
  try:
    counts = device_counts(a.devices, agents, jax.local_device_count())
  except ValueError as e:
    p.error(f"--devices: {e}")
  if a.cost:
    for algo in a.algos.split(","):
      for dtype in a.dtypes.split(","):
        print(json.dumps(update_cost(dtype, algo, a.batch, a.size, a.stack, a.action_size)),
              flush=True)
    return
  device = jax.devices()[0]
  out = a.out or os.path.join("benchmarks", "results",
                              f"learner_{R.device_slug(device.device_kind)}.jsonl")
  os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
  common = dict(device_kind=device.device_kind, device=device.device_kind,
                platform=device.platform, jax=jax.__version__, size=a.size, stack=a.stack,
                action_size=a.action_size, capacity=a.capacity, time_utc=R.utc_now())
  shape = dict(batch=a.batch, size=a.size, stack=a.stack, action_size=a.action_size,
               capacity=a.capacity, seconds=a.seconds)
  baseline = None
  todo = []
  if not a.no_baseline:
    todo.append(lambda: bench_python_loop(**shape))
  for algo, aug in [(al, au) for al in a.algos.split(",") for au in augs]:
    for k in agents:
      for dtype in a.dtypes.split(","):
        for agent_loop in (a.loops.split(",") if k > 1 else ["vmap"]):
          for n in counts:
            todo.append(functools.partial(bench_scanned, k, dtype, agent_loop,
                                          pairs=a.pairs, algo=algo, aug=aug, devices=n,
                                          **shape))
  one_device = {}  # a row's setting (all but its device count) → its rate on one
  for job in todo:
    row = dict(job(), **common)
    if row["kind"] == "python_loop":
      baseline = row["updates_per_s_per_agent"]
    if baseline:
      row["x_baseline"] = round(row["agent_updates_per_s"] / baseline, 2)
    if len(counts) > 1 and row["kind"] == "scanned":
      setting = tuple(row[key] for key in ("algo", "aug", "agents", "dtype", "agent_loop",
                                           "batch"))
      if row["devices"] == 1:
        one_device[setting] = row["agent_updates_per_s"]
      row["scaling_efficiency"] = scaling_efficiency(
          row["agent_updates_per_s"], one_device.get(setting), row["devices"])
    own = row["kind"] == "python_loop"
    R.emit(R.row(row, variant(row), n=row["batch"], throughput=row["agent_updates_per_s"],
                 unit="agent-updates/s", compile_s=row["compile_s"],
                 run_s=row["ms_per_call"] / 1e3,
                 baseline=PYTHON_LOOP if baseline and not own else None,
                 baseline_throughput=None if own else baseline, is_baseline=own), out)
  rows = R.read(out)
  R.write_markdown(out, f"Rows of `python -m dmcr_jax.benchmarks.learner` (see its docstring), "
                   f"appended to `{os.path.basename(out)}`; the last run: `python -m "
                   f"dmcr_jax.benchmarks.learner {' '.join(sys.argv[1:] if argv is None else argv)}` "
                   f"({os.cpu_count()} cores). Updates/s count gradient updates (critic every "
                   "update; actor, α and targets every second one).\n\n" + markdown(rows))
  print(markdown(rows))


if __name__ == "__main__":
  main()
