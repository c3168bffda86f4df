"""Experiment: the learner with some of an update's passes on a second GPU stream.

`jax.experimental.compute_on` with ``compute_type="gpu_stream:N"`` makes XLA run the
wrapped function asynchronously on compute stream N (``call-start``/``call-done``),
so the passes that do not depend on the critic's gradient pass can overlap it:
``td``: the TD target (online and target encoders on o′, a′, Q′) on stream 1.
``blocks``: no stream; the actor's pass reuses the critic pass's prepared blocks
(rows < B) instead of preparing ô again. ``td+blocks``: both.

Usage (one variant per process, since XLA flags are read at start-up)::

    python experiments/probes/learner_streams.py {main,td,blocks,td+blocks} [--check] [--pairs 25]

Prints one JSON line: updates/s of `benchmarks.learner`'s scanned update (1 agent,
bfloat16, batch 256, 84×84×9, DrQ); with ``--check`` also the largest difference of
the agent's parameters from main's after one call of two update pairs, and how many
async calls the compiled module holds.
"""
import argparse
import json
import os

import jax
import jax.numpy as jnp
from jax.experimental import compute_on as _compute_on

import dmcr_jax  # noqa: F401 (sets MUJOCO_GL and XLA:CPU flags before JAX starts)
from dmcr_jax.benchmarks import learner as L
from dmcr_jax.train import sac

_td_target = sac.td_target


def td_on_stream(agent, next_obs, reward, discount, key, config):
  """`sac.td_target`, computed by a jitted call on compute stream 1."""
  fn = lambda a, o, r, d, k: _td_target(a, o, r, d, k, config)
  # jax 0.10 names the function form compute_on2; later versions compute_on.
  api = getattr(_compute_on, "compute_on2", _compute_on.compute_on)
  return api(fn, compute_type="gpu_stream:1", out_memory_spaces=jax.memory.Space.Device)(
      agent, next_obs, reward, discount, key)


_encoder_inputs = sac.encoder_inputs


def inputs_with_actor_blocks(encoder, batch, mixed, z_obs, config, stage=False):
  """`sac.encoder_inputs`, with the actor's input the critic's blocks, rows < B."""
  inputs = _encoder_inputs(encoder, batch, mixed, z_obs, config, stage)
  size = batch.obs.shape[0]
  critic = inputs.critic
  return inputs._replace(obs=critic.replace(data=critic.data[:size]))


def patch(variant: str) -> None:
  sac.td_target = td_on_stream if "td" in variant else _td_target
  sac.encoder_inputs = inputs_with_actor_blocks if "blocks" in variant else _encoder_inputs
  jax.clear_caches()


def params_after_one_call(variant: str, pairs: int):
  patch(variant)
  call, _, _ = L.scanned_workload(1, "bfloat16", "vmap", None, pairs)
  return jax.device_get(call().params)


def main():
  p = argparse.ArgumentParser()
  p.add_argument("variant", choices=["main", "td", "blocks", "td+blocks"])
  p.add_argument("--pairs", type=int, default=25)
  p.add_argument("--seconds", type=float, default=3.0)
  p.add_argument("--check", action="store_true")
  args = p.parse_args()
  row = dict(variant=args.variant, xla_flags=os.environ.get("XLA_FLAGS", ""))
  if args.check:
    ref = params_after_one_call("main", 2)
    new = params_after_one_call(args.variant, 2)
    diffs = jax.tree_util.tree_map(lambda a, b: float(jnp.max(jnp.abs(a - b))), ref, new)
    row["max_param_diff"] = max(jax.tree_util.tree_leaves(diffs))
  patch(args.variant)
  bench = L.bench_scanned(1, "bfloat16", "vmap", None, args.pairs, 84, 3, 6, 10_000,
                          args.seconds)
  row.update(updates_per_s=bench["updates_per_s_per_agent"], ms_per_call=bench["ms_per_call"],
             compile_s=bench["compile_s"])
  if args.check:
    call, _, _ = L.scanned_workload(1, "bfloat16", "vmap", None, 1)
    row["async_calls"] = call.hlo_text().count("call-start")
  row["device"] = jax.devices()[0].device_kind
  print(json.dumps(row), flush=True)


if __name__ == "__main__":
  main()
