"""The protocol's speed: `dmcr_jax.protocol` wall time and agent-steps/s beside the env's own.

For one task (walker-walk by default) and the paper's protocol sizes (every
condition that applies, 100 held-out looks × 3 initial states, 100 train episodes
at seed 0's look, which "none" shares), it measures in one run, per renderer and
per number of agents K (`--agents 1,4`; random-init SAC agents of the paper's
sizes, evaluated with `dmcr-evaluate`'s greedy policy):
- the protocol: its first pass (compilation, the pool's start and one run) and a
  second pass with other params of the same shapes, in one ``with proto:`` block
  (the run alone: nothing compiles or starts again), and
  agent-steps/s of the second pass (every env's steps, K agents' together); of
  the first pass also the seconds JAX spent tracing and lowering ("trace_s") and
  XLA spent compiling ("xla_compile_s"), as JAX's monitoring events report them,
  and the seconds of its first block ("first_block_s": the pass less what came
  before its blocks, e.g. the pool's start). With `--passes 1` the row is the first
  pass alone: its agent-steps/s count the start and the compilation;
- ray caster ("jax"): the JAX env's own agent-steps/s at the same batch size (the
  envs of one block: `jax_env.PixelEnv.step` with zero actions in one jitted
  `lax.scan` over an episode, no policy, its frames kept as the result so that
  they are drawn), compile and run apart, and the ratio;
- pool: the render pool's exact frames/s at the protocol's batch size
  (`RenderPool.render` of fixed states, `dmcr_jax.benchmarks.render.bench_pool`,
  the block's envs in one call, with the protocol's render workers) and the ratio
  of the protocol's frames/s (one frame per agent step) to it; the protocol draws
  the block as `pool_groups` pipelined groups, the physics on the host CPU
  ("groups", "workers" and "physics_workers" in its row:
  `protocol_pool.workers_for`).

    python -m dmcr_jax.benchmarks.evaluate --task walker-walk --agents 1,4 \\
        --out benchmarks/results/evaluate_h200.jsonl
    python -m dmcr_jax.benchmarks.evaluate --task walker-walk --agents 1,4 --equal-batch \\
        --no-baseline --out benchmarks/results/evaluate_h200.jsonl   # K=4 beside K=1, same envs
    python -m dmcr_jax.benchmarks.evaluate --task walker-walk --renderers pool --agents 1 \\
        --passes 1 --out benchmarks/results/evaluate_h100.jsonl   # the full pool protocol once

One JSON line per row (`dmcr_jax.benchmarks.rows`) and a Markdown table beside
the JSONL file.
"""

from __future__ import annotations

import argparse
import contextlib
import time

import dmcr_jax  # noqa: F401  (first: picks a headless MUJOCO_GL before dm_control reads it)
from dmcr_jax.benchmarks import rows as R


def sac_agents(task: str, k: int, image_size: int, frame_stack: int, seed: int = 0):
  """K random-init SAC agents of the paper's network sizes as `dmcr-evaluate`'s
  policy params (`evaluate.policy_params`), stacked on a leading axis."""
  from dmcr_jax import models
  from dmcr_jax.train import evaluate, loop
  cfg = loop.TrainConfig(task=task, seeds=tuple(range(seed, seed + k)), image_size=image_size,
                         frame_stack=frame_stack)
  agents = loop.init_agents(cfg, (image_size, image_size, 3 * frame_stack),
                            models.load(task).action_size)
  return evaluate.policy_params(agents, list(range(k)))


@contextlib.contextmanager
def compile_seconds():
  """A context giving a dict that fills with the seconds JAX spends, inside it,
  tracing and lowering ("trace_s") and in XLA's compiler ("xla_compile_s")
  (`jax.monitoring` duration events of every function compiled)."""
  import jax
  trace = ("/jax/core/compile/jaxpr_trace_duration",
           "/jax/core/compile/jaxpr_to_mlir_module_duration")
  out = dict(trace_s=0.0, xla_compile_s=0.0)

  def listen(event, seconds, **_):
    if event in trace:
      out["trace_s"] += seconds
    elif event == "/jax/core/compile/backend_compile_duration":
      out["xla_compile_s"] += seconds
  jax.monitoring.register_event_duration_secs_listener(listen)
  try:
    yield out
  finally:
    jax.monitoring.unregister_event_duration_listener(listen)


def env_baseline(task: str, num_envs: int, steps: int, frame_skip: int, frame_stack: int,
                 size: int) -> dict:
  """The JAX env's own agent-steps/s: `steps` zero-action steps of `num_envs` envs
  (visual seeds 1…N, every factor varying) in one jitted scan after a reset, the
  last frame stacks returned (unreturned, XLA would drop the frames unused), the
  frames drawn in the protocol's chunks (`protocol.render_chunk`)."""
  import jax
  import jax.numpy as jnp
  import numpy as np
  from dmcr_jax import jax_env, models, protocol
  task_ = models.load(task)
  penv = jax_env.make_env(task_, num_envs, np.arange(1, num_envs + 1, dtype=np.int32), "all",
                          frame_skip, frame_stack, size, size,
                          render_chunk=protocol.render_chunk(num_envs))

  @jax.jit
  def episode(penv, key):
    state = penv.reset(key)
    zeros = jnp.zeros((num_envs, task_.action_size), jnp.float32)
    state, _ = jax.lax.scan(lambda s, _: (penv.step(s, zeros)[0], None), state, None,
                            length=steps)
    return state.physics.episode_return, state.obs

  with compile_seconds() as seconds:
    t = R.measure(lambda: episode(penv, jax.random.key(0)), repeats=1)
  return dict(seconds, compile_s=t.compile_s - t.run_s, run_s=t.run_s,
              agent_steps_per_s=num_envs * steps / t.run_s)


def sizes_for(k: int, args) -> tuple[int, int]:
  """(held-out looks, train episodes) of each of K agents: the options' own, or with
  `--equal-batch` a K-th of the looks (train episodes at most looks × initial
  states), so that every K's pass steps as many envs."""
  if not args.equal_batch:
    return args.visual_seeds, args.train_episodes
  looks = args.visual_seeds // k
  return looks, min(args.train_episodes, looks * args.dynamics_seeds)


def bench_protocol(task: str, renderer: str, k: int, args) -> dict:
  """Two passes of the protocol for K agents (the second with other params), or with
  `--passes 1` one, whose time (start and compilation included) is then the row's."""
  import jax
  from dmcr_jax import protocol, protocol_pool
  from dmcr_jax.train import evaluate
  render = dict(quality="exact", workers=args.workers) if renderer == "pool" else {}
  conditions = tuple(args.conditions.split(",")) if args.conditions else None
  visual_seeds, train_episodes = sizes_for(k, args)
  proto = protocol.prepare(task, evaluate.greedy_policy, agents=k, renderer=renderer,
                           visual_seeds=visual_seeds, dynamics_seeds=args.dynamics_seeds,
                           train_episodes=train_episodes, conditions=conditions,
                           image_size=args.image_size, frame_stack=args.frame_stack,
                           action_repeat=args.action_repeat, max_envs=args.max_envs, **render)
  first_params = sac_agents(task, k, args.image_size, args.frame_stack, seed=0)
  second_params = sac_agents(task, k, args.image_size, args.frame_stack, seed=k)
  with proto:
    t0 = time.perf_counter()
    with compile_seconds() as seconds:
      first = proto(first_params)
    first_s = time.perf_counter() - t0
    second, run_s = first, first_s
    if args.passes == 2:
      t0 = time.perf_counter()
      second = proto(second_params)
      run_s = time.perf_counter() - t0
  steps = second.agent_steps
  # A one-pass row has no pass without compilation to set apart: no "compile s".
  compile_s = max(first_s - run_s, 0.0) if args.passes == 2 else None
  workers = protocol_pool.workers_for(proto) if renderer == "pool" else (None, None)
  return dict(task=task, renderer=renderer, agents=k, conditions=list(proto.conditions),
              visual_seeds=visual_seeds, dynamics_seeds=args.dynamics_seeds,
              train_episodes=train_episodes, image_size=args.image_size,
              episodes_per_agent=proto.plan.episodes, block_envs=proto.block_envs,
              groups=len(protocol.pool_groups(k, proto.block)) if renderer == "pool" else None,
              workers=workers[0], physics_workers=workers[1],
              blocks=proto.num_blocks, episode_length=proto.episode_length,
              action_repeat=proto.env_kwargs["frame_skip"], first_pass_s=first_s,
              compile_s=compile_s, run_s=run_s, agent_steps=steps, **seconds,
              passes=args.passes, first_block_s=first.compile_s,
              agent_steps_per_s=steps / run_s, mean_all=float(first.mean(
                  proto.conditions[-1]).mean()),
              device=jax.devices()[0].device_kind, platform=jax.default_backend())


def markdown(rows: list[dict]) -> str:
  """The rows as a table: protocol rows with their baselines and ratios."""
  lines = ["| task | renderer | variant | envs per block × blocks | compile s | XLA compile s | "
           "run s | throughput | baseline | ratio |",
           "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
  for r in rows:
    if r.get("is_baseline"):
      continue
    ratio = (f"{r['throughput'] / r['baseline_throughput']:.2f}"
             if r.get("baseline_throughput") else "–")
    base = (f"{r['baseline_throughput']:,.0f} ({r['baseline']})"
            if r.get("baseline_throughput") else "–")
    xla = f"{r['xla_compile_s']:.1f}" if r.get("xla_compile_s") is not None else "–"
    compile_s = f"{r['compile_s']:.1f}" if r.get("compile_s") is not None else "–"
    lines.append(f"| {r['task']} | {r['renderer']} | {r['variant']} | "
                 f"{r['block_envs']:,} × {r['blocks']} | {compile_s} | {xla} | "
                 f"{r['run_s']:.1f} | {r['throughput']:,.0f} {r['unit']} | {base} | {ratio} |")
  return "\n".join(lines) + "\n"


def main(argv=None) -> None:
  """`python -m dmcr_jax.benchmarks.evaluate [options]`."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.benchmarks.evaluate",
                              description=__doc__.splitlines()[0])
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--renderers", default="jax", help="comma-separated: jax, pool")
  p.add_argument("--agents", default="1,4", help="comma-separated numbers of agents K")
  p.add_argument("--visual-seeds", type=int, default=100)
  p.add_argument("--dynamics-seeds", type=int, default=3)
  p.add_argument("--train-episodes", type=int, default=100)
  p.add_argument("--conditions", default=None, help="comma-separated (default: all)")
  p.add_argument("--image-size", type=int, default=84)
  p.add_argument("--frame-stack", type=int, default=3)
  p.add_argument("--action-repeat", type=int, default=None,
                 help="default: the paper's for the task")
  p.add_argument("--max-envs", type=int, default=None,
                 help="envs per block (default: every episode in one block)")
  p.add_argument("--workers", type=int, default=None, help="render workers (pool)")
  p.add_argument("--passes", type=int, choices=(1, 2), default=2,
                 help="2: the row times a second pass (nothing compiles in it); 1: the "
                      "first pass alone, start and compilation included")
  p.add_argument("--no-baseline", action="store_true", help="only the protocol's rows")
  p.add_argument("--equal-batch", action="store_true",
                 help="K agents share --visual-seeds (a K-th each), so every K steps as "
                      "many envs; K>1 rows are then set beside the run's K=1 row")
  p.add_argument("--out", default=None, help="JSONL file the rows are appended to")
  a = p.parse_args(argv)
  if a.train_episodes > a.visual_seeds * a.dynamics_seeds:
    p.error(f"--train-episodes ({a.train_episodes}) must be at most --visual-seeds × "
            f"--dynamics-seeds = {a.visual_seeds * a.dynamics_seeds}")
  from dmcr_jax.env_checks import check_renderer_name, default_frame_skip
  renderers = [check_renderer_name(r) for r in a.renderers.split(",")]
  ks = [int(k) for k in a.agents.split(",")]
  if a.equal_batch and any(a.visual_seeds % k for k in ks):
    p.error(f"--equal-batch: --visual-seeds ({a.visual_seeds}) must divide by every K in "
            f"--agents ({a.agents})")
  frame_skip = a.action_repeat or default_frame_skip(a.task)
  rows, baselines, one_agent = [], {}, {}   # baselines by (renderer, envs); K=1 rows by renderer
  for renderer in renderers:
    for k in ks:
      own = bench_protocol(a.task, renderer, k, a)
      n = own["block_envs"]
      base = None
      if not a.no_baseline and (renderer, n) not in baselines:
        if renderer == "jax":
          env = env_baseline(a.task, n, own["episode_length"], frame_skip, a.frame_stack,
                             a.image_size)
          b = R.row(dict(own, agents=None, trace_s=env["trace_s"],
                         xla_compile_s=env["xla_compile_s"]), "JAX env (zero actions)", n=n,
                    throughput=env["agent_steps_per_s"], unit="agent-steps/s",
                    compile_s=env["compile_s"], run_s=env["run_s"], is_baseline=True)
        else:
          from dmcr_jax.benchmarks.render import bench_pool
          pool = bench_pool(a.task, n, own["workers"], "exact", a.image_size, repeats=3)
          b = R.row(dict(own, agents=None, gl=pool["gl"], workers=pool["workers"]),
                    "pool exact frames", n=n, throughput=pool["frames_per_s"],
                    unit="frames/s", compile_s=pool["start_s"], run_s=pool["run_s"],
                    is_baseline=True)
        baselines[(renderer, n)] = b
        R.emit(b, a.out)
        rows.append(b)
      base = baselines.get((renderer, n))
      if a.equal_batch and k > 1 and renderer in one_agent:
        base = one_agent[renderer]
      unit = "agent-steps/s" if renderer == "jax" else "frames/s"
      r = R.row(own, f"protocol K={k}", n=n, throughput=own["agent_steps_per_s"], unit=unit,
                compile_s=own["compile_s"], run_s=own["run_s"],
                baseline=None if base is None else base["variant"],
                baseline_throughput=None if base is None else base["throughput"],
                headline=(f"{own['run_s']:.0f} s a pass, {own['agent_steps_per_s']:,.0f} "
                          f"{unit}"))
      if base is not None:
        r["ratio"] = r["throughput"] / base["throughput"]
      R.emit(r, a.out)
      rows.append(r)
      if k == 1:
        one_agent[renderer] = r
  R.print_and_write(rows, a.out, markdown)


if __name__ == "__main__":
  main()
