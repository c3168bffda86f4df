"""Where the protocol's compile time goes: its block program and its parts, compiled apart.

For one task and block size it lowers and compiles (ahead of time, nothing runs)
each of: the ray caster protocol's block program (`protocol._ray_block`) with the
SAC policy `dmcr-evaluate` uses, for one agent and for K agents of N / K envs
each; the JAX env's own episode (`jax_env.PixelEnv.reset`, then a `lax.scan` of
`step` with zero actions, its frames kept); and the parts a block is made of:
the looks from per-env masks, `physics_env.init`, one frame per env
(`PixelEnv.draw`, chunked as the protocol chunks it), `physics_env.step` (with
its auto-reset branch), `protocol.episode_step` (without it) and the policy
vmapped over envs. Per program: seconds to lower, seconds to compile (wall and
this process's CPU time, which a loaded machine does not inflate) and the
optimised HLO's size (characters and instructions).

    python -m dmcr_jax.benchmarks.protocol_compile --task walker-walk --envs 4 --image-size 64 --steps 3
    python -m dmcr_jax.benchmarks.protocol_compile --envs 2400 --parts block,block_k,env --out rows.jsonl
"""

from __future__ import annotations

import argparse
import re
import time

import dmcr_jax  # noqa: F401  (first: picks a headless MUJOCO_GL before dm_control reads it)
from dmcr_jax.benchmarks import rows as R

PARTS = ("block", "block_k", "env", "looks", "init", "render", "step", "episode_step",
         "policy")
"""What `--parts` picks from (module docstring, in that order)."""


def hlo_size(text: str) -> tuple[int, int]:
  """(characters, instructions) of an HLO module's text."""
  return len(text), len(re.findall(r"^\s*(?:ROOT )?%?[\w.\-]+ = ", text, re.M))


def compile_program(fn, *args, **kwargs) -> dict:
  """Lowers and compiles `fn` (a jitted function) for `args`; the seconds and sizes."""
  t0 = time.perf_counter()
  lowered = fn.lower(*args, **kwargs)
  t1, c1 = time.perf_counter(), time.process_time()
  compiled = lowered.compile()
  t2, c2 = time.perf_counter(), time.process_time()
  chars, ops = hlo_size(compiled.as_text())
  return dict(lower_s=t1 - t0, compile_s=t2 - t1, compile_cpu_s=c2 - c1, hlo_chars=chars,
              hlo_ops=ops)


def programs(task: str, envs: int, size: int, steps: int, agents: int, frame_stack: int = 3,
             action_repeat: int | None = None) -> dict:
  """name → (jitted function, args, kwargs) of every part (`PARTS`)."""
  import jax
  import jax.numpy as jnp
  import numpy as np
  from dmcr_jax import jax_env, models, physics_env
  from dmcr_jax import protocol as P
  from dmcr_jax.benchmarks.evaluate import sac_agents
  from dmcr_jax.env_checks import default_frame_skip
  from dmcr_jax.models.base import physics_jit
  from dmcr_jax.train import evaluate as tev
  from dmcr_jax.visuals.params import factor_mask
  t = models.load(task)
  skip = action_repeat or default_frame_skip(task)
  penv = P._pixel_env(task, envs, skip, frame_stack, size, size, ())
  seeds = jnp.arange(1, envs + 1, dtype=jnp.int32)
  masks = jnp.asarray(np.stack([factor_mask(t.spec.domain, "all")] * envs))
  resets = jnp.arange(envs, dtype=jnp.uint32)
  index = jnp.arange(envs, dtype=jnp.int32)
  key = jax.random.key(0)
  one = jax.tree.map(lambda x: x[0], sac_agents(task, 1, size, frame_stack))
  block = P._ray_block_jit()
  policy = tev.greedy_policy
  looks = jax.jit(P.block_looks)(penv.maker, masks, seeds)
  physics = jax.jit(lambda s, r: physics_env.init(t, s, jax.vmap(jax.random.key)(r), envs))(
      seeds, resets)
  actions = jnp.zeros((envs, t.action_size), jnp.float32)
  obs = jnp.zeros((envs, size, size, 3 * frame_stack), jnp.uint8)
  fixed = jax_env.make_env(t, envs, np.arange(1, envs + 1, dtype=np.int32), "all", skip,
                           frame_stack, size, size, render_chunk=penv.render_chunk)

  def env_episode(env, key):
    state = env.reset(key)
    state, _ = jax.lax.scan(lambda s, _: (env.step(s, actions)[0], None), state, None,
                            length=steps)
    return state.physics.episode_return, state.obs   # the frames kept: they are drawn

  return dict(
      block=(block, (penv, one, seeds, masks, resets, index, key),
             dict(policy=policy, agents=None, steps=steps)),
      block_k=(block, (penv, sac_agents(task, agents, size, frame_stack), seeds, masks,
                       resets, index, key), dict(policy=policy, agents=agents, steps=steps)),
      env=(physics_jit(env_episode), (fixed, key), {}),
      looks=(jax.jit(P.block_looks), (penv.maker, masks, seeds), {}),
      init=(physics_jit(lambda s, r: physics_env.init(t, s, jax.vmap(jax.random.key)(r),
                                                      envs)), (seeds, resets), {}),
      render=(jax.jit(lambda e, ph, lk: e.draw(e.render_inputs(ph), lk)),
              (penv, physics, looks), {}),
      step=(physics_jit(lambda ph, a: physics_env.step(t, seeds, skip, ph, a)),
            (physics, actions), {}),
      episode_step=(physics_jit(lambda ph, a: P.episode_step(t, skip, ph, a)),
                    (physics, actions), {}),
      policy=(jax.jit(lambda p, o: P.policy_actions(policy, p, o, index, jnp.int32(0), key,
                                                    None)), (one, obs), {}))


def main(argv=None) -> None:
  """`python -m dmcr_jax.benchmarks.protocol_compile [options]`."""
  p = argparse.ArgumentParser(prog="python -m dmcr_jax.benchmarks.protocol_compile",
                              description=__doc__.splitlines()[0])
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--envs", type=int, default=4, help="envs of the block (N)")
  p.add_argument("--agents", type=int, default=2, help="K of the K-agent block (N / K each)")
  p.add_argument("--image-size", type=int, default=64)
  p.add_argument("--steps", type=int, default=3, help="scan length (agent steps)")
  p.add_argument("--action-repeat", type=int, default=None)
  p.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated: {', '.join(PARTS)}")
  p.add_argument("--out", default=None, help="JSONL file the rows are appended to")
  a = p.parse_args(argv)
  parts = a.parts.split(",")
  bad = sorted(set(parts) - set(PARTS))
  if bad:
    raise SystemExit(f"unknown part {', '.join(bad)}; valid: {', '.join(PARTS)}")
  if a.envs % a.agents:
    raise SystemExit(f"--envs ({a.envs}) must be a multiple of --agents ({a.agents})")
  import jax
  progs = programs(a.task, a.envs, a.image_size, a.steps, a.agents,
                   action_repeat=a.action_repeat)
  print("| program | lower s | compile s | compile CPU s | HLO chars | HLO ops |")
  print("|---|---:|---:|---:|---:|---:|")
  for name in parts:
    fn, args, kwargs = progs[name]
    m = compile_program(fn, *args, **kwargs)
    own = dict(m, benchmark="protocol_compile", task=a.task, part=name, envs=a.envs,
               agents=a.agents if name == "block_k" else 1, image_size=a.image_size,
               steps=a.steps, device=jax.devices()[0].device_kind,
               platform=jax.default_backend())
    if a.out:
      R.emit(R.row(own, name, n=a.envs, throughput=None, unit="s", compile_s=m["compile_s"]),
             a.out)
    print(f"| {name} | {m['lower_s']:.1f} | {m['compile_s']:.1f} | {m['compile_cpu_s']:.1f} | "
          f"{m['hlo_chars']:,} | {m['hlo_ops']:,} |", flush=True)


if __name__ == "__main__":
  main()
