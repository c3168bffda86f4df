"""JAX ray caster throughput: frames/s of `jax_render.render_batch`, or agent-steps/s of
the whole JAX pixel env (`--mode env`), at N envs.

`--mode render` (default): for one task (walker by default) with every visual
factor varying (one visual seed per env) and random body poses (a few hundred
distinct dm_control states tiled over the batch), it measures, per batch size N:
the compile time of the jitted batch render and the median run time of
`--repeats` calls (`block_until_ready`), and reports frames/s. Options choose the
image size, shadows, reflection, whether the fused GPU kernel renders
(`--kernel` / `--no-kernel`; by default it does on a GPU, as `render_batch` does;
`--block` pixels per program, `--num-warps`, `--no-skip-empty`) and, without it,
the chunk size (envs per vmapped chunk, bounding memory).

`--mode env` (end to end): `dmcr_jax.make(task, N, renderer="jax")` with visual
seeds 1 … N, vary="all", the task's frame skip (walker-walk: 2) and stacks of 3,
stepped with uniform random actions. Per N it reports the compile time (reset and
first step) and agent-steps/s (N pixel observations, rewards and auto-resets per
agent step) two ways: `env.step` in a host loop (one jitted call per step, the
observations left on the device, `info` fetched to the host) and the pure
`PixelEnv.step` scanned `--scan-steps` times in one jitted call (how
`dmcr_jax.train.device_loop` drives it: no host work between steps), each the median of
`--repeats` timed runs of `--steps` (resp. `--scan-steps`) steps.

    python -m dmcr_jax.benchmarks.jax_render --batches 1024,4096,16384 --chunk 256 \\
        --out benchmarks/results/jax_render_h100.jsonl
    python -m dmcr_jax.benchmarks.jax_render --mode env --batches 1024,4096,16384 --chunk 256 \\
        --out benchmarks/results/jax_env_h100.jsonl

`--mode check`: the fused GPU kernel's frames (`jax_render_kernel`) against the
XLA renderer's for the same N envs: how many channel values differ and by how much
(on a CPU the kernel runs in Pallas' interpreter; keep N small there).

One JSON line per row (device, backend, sizes, compile and run seconds,
frames/s or agent-steps/s) and a Markdown table beside the JSONL file.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import numpy as np

from dmcr_jax.benchmarks import rows as R


def _device() -> str:
  import jax
  d = jax.devices()[0]
  return getattr(d, "device_kind", str(d))


def inputs(task: str, n: int, states: int = 256, seed: int = 0):
  """(scene, batched BodyPoses, batched DeviceLook) for n envs of `task`."""
  import jax.numpy as jnp
  import mujoco
  from dmcr_jax.visuals import jax_render_scene as JS
  from dmcr_jax.visuals import render_model as rmod
  rm = rmod.build_render_model(task)
  scene = JS.build_scene(rm)
  m = rm.model
  rng = np.random.default_rng(seed)
  d = mujoco.MjData(m)
  xpos, xmat, com = [], [], []
  for _ in range(min(states, n)):
    d.qpos[:] = m.qpos0 + 0.2 * rng.standard_normal(m.nq)
    mujoco.mj_fwdPosition(m, d)
    xpos.append(d.xpos.copy()), xmat.append(d.xmat.copy()), com.append(d.subtree_com.copy())
  idx = np.arange(n) % len(xpos)
  bp = JS.BodyPoses(xpos=jnp.asarray(np.stack(xpos)[idx], jnp.float32),
                    xmat=jnp.asarray(np.stack(xmat)[idx].reshape(n, -1, 3, 3), jnp.float32),
                    subtree_com=jnp.asarray(np.stack(com)[idx], jnp.float32))
  looks = rmod.prepare(rm, rm.sample(np.arange(1, n + 1), vary="all"))
  return scene, bp, JS.device_looks(scene, rm, looks)


def _kernel_options(block: int | None, num_warps: int | None,
                    skip_empty: bool | None) -> dict:
  """The fused kernel's options as run (None: `jax_render_kernel`'s defaults)."""
  from dmcr_jax.visuals import jax_render_kernel as JK
  return dict(block=block or JK.BLOCK, num_warps=num_warps or JK.NUM_WARPS,
              skip_empty=JK.SKIP_EMPTY if skip_empty is None else skip_empty)


def bench(task: str, n: int, size: int, shadows: bool, reflection: bool,
          chunk: int | None, repeats: int, kernel: bool | None = None,
          block: int | None = None, num_warps: int | None = None,
          skip_empty: bool | None = None) -> dict:
  """Frames/s of `render_batch` (module doc); `kernel`: the fused GPU kernel (None:
  on a GPU), with `block` pixels per program, `num_warps` and `skip_empty` (programs
  skip work none of their pixels needs; None: `jax_render_kernel`'s defaults)."""
  import jax
  from dmcr_jax.visuals import jax_render as JR
  kernel = JR.use_kernel(kernel)
  scene, bp, look = inputs(task, n)
  extra = _kernel_options(block, num_warps, skip_empty) if kernel else {}
  # the scene is an argument, so its texture bank (~120 MB) is not baked into the
  # program as a constant
  fn = jax.jit(lambda scene, bp, look: JR.render_batch(
      scene, bp, look, height=size, width=size, shadows=shadows, reflection=reflection,
      chunk=chunk, kernel=kernel, **extra))
  timing = R.measure(lambda: fn(scene, bp, look), repeats=repeats)
  return dict(batch=n, chunk=None if kernel else chunk, kernel=kernel, **extra,
              shadows=shadows, reflection=reflection, objects=scene.num_objects,
              compile_s=timing.compile_s, run_s=timing.run_s,
              frames_per_s=n / timing.run_s)


def check_kernel(task: str, n: int, size: int, shadows: bool, reflection: bool,
                 block: int | None = None, num_warps: int | None = None,
                 skip_empty: bool | None = None, interpret: bool = False) -> dict:
  """The fused kernel's frames against the XLA renderer's (`render_batch(kernel=False)`)
  for n envs of `task` (module doc, `--mode check`): differing channel values,
  frames with any difference, the largest difference."""
  import jax
  from dmcr_jax.visuals import jax_render as JR
  from dmcr_jax.visuals import jax_render_kernel as JK
  scene, bp, look = inputs(task, n)
  opts = dict(height=size, width=size, shadows=shadows, reflection=reflection)
  xla = np.asarray(jax.jit(lambda scene, bp, look: JR.render_batch(
      scene, bp, look, kernel=False, **opts))(scene, bp, look)).astype(np.int32)
  extra = _kernel_options(block, num_warps, skip_empty)
  fused = np.asarray(jax.jit(lambda scene, bp, look: JK.render_batch(
      scene, bp, look, interpret=interpret, **extra, **opts))(scene, bp, look)
                     ).astype(np.int32)
  diff = np.abs(fused - xla)
  return dict(batch=n, **extra, shadows=shadows, reflection=reflection,
              objects=scene.num_objects, values=int(diff.size),
              values_differing=int((diff > 0).sum()),
              frames_differing=int((diff.reshape(n, -1) > 0).any(1).sum()),
              max_abs_diff=int(diff.max()), mean_abs_diff=float(diff.mean()))


def bench_env(task: str, n: int, size: int, shadows: bool, reflection: bool,
              chunk: int | None, repeats: int, steps: int, scan_steps: int,
              ls_iterations: int | None = None, kernel: bool = False) -> dict:
  """Agent-steps/s of `make(task, n, renderer="jax")` (module doc, `--mode env`)."""
  import jax
  import jax.numpy as jnp
  import dmcr_jax
  from dmcr_jax import jax_env
  env = dmcr_jax.make(task, num_envs=n, visual_seeds=np.arange(1, n + 1), vary="all",
                      image_size=size, renderer="jax", shadows=shadows,
                      reflection=reflection, render_chunk=chunk, render_kernel=kernel,
                      obs_on_device=True,
                      ls_iterations=ls_iterations)
  low, high = env.single_action_space.low, env.single_action_space.high
  rng = np.random.default_rng(0)
  actions = [rng.uniform(low, high, (n, len(low))).astype(np.float32) for _ in range(8)]
  t0 = time.perf_counter()
  env.reset(seed=0)
  jax.block_until_ready(env.step(actions[0])[0])
  compile_s = time.perf_counter() - t0
  penv = env.functional
  kernel = penv.render_kernel
  print(f"{task}, {n} envs: compiled in {compile_s:.1f} s (kernel={kernel})",
        file=sys.stderr, flush=True)

  def stepped():
    for i in range(steps):
      obs = env.step(actions[i % len(actions)])[0]
    return obs
  step_s = statistics.median(R.time_calls(stepped, repeats=repeats, warmup=0)) / steps
  print(f"  env.step: {n / step_s:,.0f} agent-steps/s", file=sys.stderr, flush=True)
  lo, hi = jnp.asarray(low), jnp.asarray(high)

  def scanned(penv, state, key):
    def body(carry, _):
      state, key = carry
      key, k = jax.random.split(key)
      a = jax.random.uniform(k, (n, len(low)), minval=lo, maxval=hi)
      state, reward, _ = penv.step(state, a)
      return (state, key), reward.sum()
    (state, _), rewards = jax.lax.scan(body, (state, key), None, length=scan_steps)
    return state, rewards

  donate = () if jax.default_backend() == "cpu" else (1,)
  run = jax.jit(scanned, donate_argnums=donate)
  carry = [jax_env.reset(penv, jax.random.key(1)), 2]  # state (donated), next key

  def scan_call():
    carry[0], _ = run(penv, carry[0], jax.random.key(carry[1]))
    carry[1] += 1
    return carry[0]
  scan = R.measure(scan_call, repeats=repeats)
  scan_compile_s, scan_s = scan.compile_s, scan.run_s / scan_steps
  return dict(batch=n, chunk=None if kernel else penv.render_chunk, kernel=kernel,
              shadows=shadows, reflection=reflection,
              ls_iterations=ls_iterations or "default",
              frame_skip=env.frame_skip, frame_stack=env.frame_stack,
              objects=penv.scene.num_objects, compile_s=compile_s,
              scan_compile_s=scan_compile_s, step_s=step_s, scan_step_s=scan_s,
              agent_steps_per_s=n / step_s, scan_agent_steps_per_s=n / scan_s)


def markdown_env(rows: list[dict]) -> str:
  """The `--mode env` rows as one Markdown table."""
  return R.table(rows, [
      ("device", "device"), ("task", "task"), ("size", "size"),
      ("batch", lambda r: f"{r['batch']:,}"),
      ("chunk", lambda r: "kernel" if r.get("kernel") else r["chunk"] or "–"),
      ("frame skip", "frame_skip"), ("line search", lambda r: r.get("ls_iterations", "default")),
      ("compile s", lambda r: f"{r['compile_s'] + r['scan_compile_s']:.1f}"),
      ("env.step agent-steps/s", lambda r: f"{r['agent_steps_per_s']:,.0f}"),
      ("scanned agent-steps/s", lambda r: f"{r['scan_agent_steps_per_s']:,.0f}")])


def _how(r: dict) -> str:
  if r.get("kernel"):
    return (f"kernel ({r['block']}, {r['num_warps']}"
            f"{', skip' if r.get('skip_empty') else ''})")
  return f"XLA, chunk {r['chunk'] or '–'}"


def markdown(rows: list[dict]) -> str:
  """The `--mode render` rows as one Markdown table."""
  return R.table(rows, [
      ("device", "device"), ("task", "task"), ("size", "size"),
      ("batch", lambda r: f"{r['batch']:,}"), ("kernel (block, warps) / chunk", _how),
      ("shadows", "shadows"), ("reflection", "reflection"),
      ("compile s", lambda r: f"{r['compile_s']:.1f}"),
      ("frames/s", lambda r: f"{r['frames_per_s']:,.0f}"),
      ("label", lambda r: r.get("label", ""))])


def look(row: dict) -> str:
  """The row's shadows and reflection, in words."""
  return ", ".join(n for n, on in (("shadows", row["shadows"]),
                                   ("reflection", row["reflection"])) if on) or (
      "no shadows, no reflection")


def suite_rows(row: dict) -> list[dict]:
  """The rows of one measurement in the suite's format: the frames/s of `--mode
  render`; for `--mode env` the row as `env.step` steps it and a row of its settings
  as the scan steps it."""
  if row["bench"] == "jax_render":
    return [R.row(row, f"frames ({look(row)})", n=row["batch"],
                  throughput=row["frames_per_s"], unit="frames/s",
                  compile_s=row["compile_s"], run_s=row["run_s"])]
  measured = ("compile_s", "scan_compile_s", "step_s", "scan_step_s", "agent_steps_per_s",
              "scan_agent_steps_per_s")
  settings = {k: v for k, v in row.items() if k not in measured}
  return [R.row(row, f"env, env.step ({look(row)})", n=row["batch"],
                throughput=row["agent_steps_per_s"], unit="agent-steps/s",
                compile_s=row["compile_s"], run_s=row["step_s"]),
          R.row(settings, f"env, scanned ({look(row)})", n=row["batch"],
                throughput=row["scan_agent_steps_per_s"], unit="agent-steps/s",
                compile_s=row["scan_compile_s"], run_s=row["scan_step_s"])]


def main(argv=None) -> None:
  argv = sys.argv[1:] if argv is None else argv
  p = argparse.ArgumentParser(description="JAX ray caster frames/s, or the JAX pixel "
                                          "env's agent-steps/s (--mode env).")
  p.add_argument("--mode", default="render", choices=("render", "env", "check"))
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--size", type=int, default=84)
  p.add_argument("--batches", default="1024,4096,16384")
  p.add_argument("--chunk", type=int, default=0, help="envs per chunk (0: all at once)")
  p.add_argument("--kernel", action=argparse.BooleanOptionalAction, default=None,
                 help="render in the fused GPU kernel (jax_render_kernel); default: "
                      "on a GPU, as render_batch; --mode env: make's default, off")
  p.add_argument("--block", type=int, default=None, help="kernel: pixels per program")
  p.add_argument("--num-warps", type=int, default=None, help="kernel: warps per program")
  p.add_argument("--skip-empty", action=argparse.BooleanOptionalAction, default=None,
                 help="kernel: programs skip work none of their pixels needs "
                      "(default: on, jax_render_kernel's default)")
  p.add_argument("--no-shadows", action="store_true")
  p.add_argument("--no-reflection", action="store_true")
  p.add_argument("--repeats", type=int, default=3)
  p.add_argument("--steps", type=int, default=20, help="--mode env: env.step calls per repeat")
  p.add_argument("--scan-steps", type=int, default=50,
                 help="--mode env: scanned steps per jitted call")
  p.add_argument("--ls-iterations", type=int, default=None,
                 help="--mode env: MJX line-search cap (default: the task's, 16)")
  p.add_argument("--out", default=None)
  p.add_argument("--label", default=None,
                 help="a note stored in every row (e.g. the code version measured)")
  args = p.parse_args(argv)
  import jax
  env_mode = args.mode == "env"
  common = dict(bench="jax_env" if env_mode else "jax_render", device=_device(),
                backend=jax.default_backend(), platform=jax.default_backend(),
                cpus=os.cpu_count(), host=platform.node(),
                task=args.task, size=args.size, vary="all")
  if args.label:
    common["label"] = args.label
  rows = []
  for n in [int(b) for b in args.batches.split(",")]:
    flags = (not args.no_shadows, not args.no_reflection)
    if args.mode == "check":
      row = dict(common, bench="jax_render_kernel_check", **check_kernel(
          args.task, n, args.size, *flags, args.block, args.num_warps, args.skip_empty,
          interpret=jax.default_backend() != "gpu"))
    elif env_mode:
      row = dict(common, **bench_env(args.task, n, args.size, *flags, args.chunk or None,
                                     args.repeats, args.steps, args.scan_steps,
                                     args.ls_iterations, bool(args.kernel)))
    else:
      chunk = args.chunk if args.chunk and n % args.chunk == 0 else None
      row = dict(common, **bench(args.task, n, args.size, *flags, chunk, args.repeats,
                                 args.kernel, args.block, args.num_warps,
                                 args.skip_empty))
    rows.append(row)
    for r in [row] if args.mode == "check" else suite_rows(row):
      R.emit(r, args.out)
  if args.mode == "check":
    table = "".join(json.dumps(r) + "\n" for r in rows)
  else:
    table = markdown_env(rows) if env_mode else markdown(rows)
  print(table)
  if args.out:
    R.write_markdown(args.out, f"`python -m dmcr_jax.benchmarks.jax_render {' '.join(argv)}`\n\n{table}")


if __name__ == "__main__":
  main()
