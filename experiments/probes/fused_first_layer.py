"""Experiment: the encoder's first layer on DrQ-augmented stored stacks, fused in one Pallas kernel.

What the learner's no-gradient passes compute before their second layer: for R
sampled transitions, gather each stack's three frames from the replay buffer's
uint8 frames, DrQ (replicate-pad 4, shift, rounded-Gaussian noise), /255 in
bfloat16, then ReLU(Conv(32, 3×3, stride 2) + bias).

``xla``: as the learner does it (a gather, `augment.drq`'s apply, `encoder_input`'s
2×2 blocks, `StrideTwoConv`). ``pallas_<noise>_w<warps>``: one Triton kernel
(`jax.experimental.pallas`), a program per (transition, output row), that reads
the frames' bytes at the shifted pixels of its 64 × 128 tile (output column ×
tap: 3×3 taps of 9 channels, zero-padded) and multiplies the tile by the kernel on
tensor cores. ``<noise>``: ``hash``, the noise computed in the kernel from the
same hash as `augment.drq`; ``table``, read from an int8 table XLA draws first;
``none``, no noise (a lower bound, not the same function).

Usage::

    python experiments/probes/fused_first_layer.py [--rows 256] [--slots 500] [--interpret]

Prints each Pallas variant's largest and mean difference from ``xla`` (bfloat16
rounding of another summation order), then µs per R rows for every variant
(a `lax.fori_loop` of `--iters` calls, best of two rounds of five); ``--interpret``
runs the kernels in Pallas's interpreter (any backend) and only compares.
"""
import argparse
import functools
import time

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

import dmcr_jax  # noqa: F401 (sets MUJOCO_GL and XLA:CPU flags before JAX starts)
from dmcr_jax import augment
from dmcr_jax.train import networks

H = W = 84          # the frames' side
PAD = 4             # DrQ's replicate padding
CH = 9              # 3 stacked RGB frames
OUT = 41            # the first layer's output side
FEAT = 32           # its filters
K_MAX, THRESHOLDS = augment._rounded_gaussian_thresholds(1.0)
THRESHOLDS = [int(v) for v in THRESHOLDS]
DRQ = augment.drq()


def xla_forward(frames, env, slots, dy, dx, seed, kernel, bias):
  """The learner's way: (R, 41, 41, 32) bfloat16 ReLU outputs."""
  return xla_forwards(frames, env, slots, dy, dx, seed, [(kernel, bias)])[0]


def xla_forwards(frames, env, slots, dy, dx, seed, layers):
  """`xla_forward` for each (kernel, bias) of `layers` on the same blocks, built
  once (as the learner's online and target encoders share o′'s): a tuple."""
  r = env.shape[0]
  obs = jnp.moveaxis(frames[env[:, None], slots], 1, 3).reshape(r, H, W, CH)
  z = jax.vmap(DRQ.apply)({"dy": dy, "dx": dx, "noise_seed": seed}, obs)
  blocks = networks.encoder_input(networks.Encoder(dtype="bfloat16"), z)
  conv = networks.StrideTwoConv(FEAT, dtype="bfloat16")
  return tuple(jax.nn.relu(conv.apply({"params": {"kernel": k, "bias": b}}, blocks))
               for k, b in layers)


def _kernel(frames_ref, base_ref, shift_ref, seed_ref, noise_ref, w_ref, b_ref, out_ref, *,
            noise):
  """Output row y of transition r: a (64 columns × 128 taps) tile of pixels · (128 × 32) kernel."""
  r, y = pl.program_id(0), pl.program_id(1)
  x = jnp.arange(64, dtype=jnp.int32)[:, None]
  t = jnp.arange(128, dtype=jnp.int32)[None, :]
  ky, kx, c = t // (3 * CH), (t // CH) % 3, t % CH
  frame, ch = c // 3, c % 3
  valid = (t < 9 * CH) & (x < OUT)
  img_r = jnp.minimum(2 * y + ky, H - 1)
  img_c = jnp.minimum(2 * x + kx, W - 1)
  src_r = jnp.clip(img_r + shift_ref[r, 0] - PAD, 0, H - 1)
  src_c = jnp.clip(img_c + shift_ref[r, 1] - PAD, 0, W - 1)
  base = jnp.where(frame == 0, base_ref[r, 0],
                   jnp.where(frame == 1, base_ref[r, 1], base_ref[r, 2]))
  pix = plgpu.load(frames_ref.at[base + src_r * (W * 3) + src_c * 3 + ch], mask=valid,
                   other=0).astype(jnp.int32)
  idx = (img_r * W + img_c) * 3 + ch
  if noise == "hash":
    u = augment._hash32(augment._hash32(idx.astype(jnp.uint32)) ^ seed_ref[r]) >> 16
    n = jnp.zeros(u.shape, jnp.int32)
    for threshold in THRESHOLDS:
      n += (u >= jnp.uint32(threshold)).astype(jnp.int32)
    pix = jnp.clip(pix + n - K_MAX, 0, 255)
  elif noise == "table":
    n = plgpu.load(noise_ref.at[r * (H * W * 3) + idx], mask=valid, other=0)
    pix = jnp.clip(pix + n.astype(jnp.int32), 0, 255)
  a = jnp.where(valid, pix.astype(jnp.float32) / 255.0, 0.0).astype(jnp.bfloat16)
  acc = plgpu.dot(a, w_ref[...])
  bias = b_ref[...].astype(jnp.bfloat16).astype(jnp.float32)[None, :]
  out = jnp.maximum(acc.astype(jnp.bfloat16).astype(jnp.float32) + bias, 0.0)
  co = jnp.arange(FEAT, dtype=jnp.int32)[None, :]
  plgpu.store(out_ref.at[r, y, x, co], out.astype(jnp.bfloat16), mask=x < OUT)


def pallas_forward(frames, env, slots, dy, dx, seed, kernel, bias, *, noise="hash", warps=4,
                   interpret=False):
  """`xla_forward` as one Pallas kernel (``noise="none"``: without DrQ's noise)."""
  r = env.shape[0]
  flat, base, shift, table = kernel_operands(frames, env, slots, dy, dx, seed, noise)
  w = jnp.pad(kernel.reshape(9 * CH, FEAT), ((0, 128 - 9 * CH), (0, 0))).astype(jnp.bfloat16)
  call = pl.pallas_call(
      functools.partial(_kernel, noise=noise), grid=(r, OUT),
      out_shape=jax.ShapeDtypeStruct((r, OUT, OUT, FEAT), jnp.bfloat16), interpret=interpret,
      compiler_params=None if interpret else plgpu.CompilerParams(num_warps=warps, num_stages=1))
  return call(flat, base, shift, seed, table, w, bias)


def kernel_operands(frames, env, slots, dy, dx, seed, noise):
  """What the Pallas kernels read besides the weights: (the frames' bytes flat, int32 (R, 4)
  byte offsets of each stack's frames (the last 0), int32 (R, 2) DrQ shifts (dy, dx), and
  the noise: ``noise="table"``, int8 (R·H·W·3) `augment.drq`'s noise; otherwise 8 zeros)."""
  t = frames.shape[1]
  base = jnp.pad(((env[:, None] * t + slots) * (H * W * 3)).astype(jnp.int32), ((0, 0), (0, 1)))
  shift = jnp.stack([dy, dx], 1).astype(jnp.int32)
  if noise == "table":
    table = jax.vmap(lambda s: augment._rounded_gaussian(s, (H, W, 3), 1.0))(seed)
    table = table.astype(jnp.int8).reshape(-1)
  else:
    table = jnp.zeros((8,), jnp.int8)
  return frames.reshape(-1), base, shift, table


def random_inputs(keys, rows: int, slots: int):
  """(frames, env, slots, dy, dx, seed): 32 envs' rings of `slots` random frames, and
  `rows` transitions' stacks (3 consecutive slots), DrQ shifts and noise seeds,
  from 6 keys."""
  envs = 32
  frames = jax.random.bits(keys[0], (envs, slots, H, W, 3), jnp.uint8)
  env = jax.random.randint(keys[1], (rows,), 0, envs)
  stacks = jax.random.randint(keys[2], (rows,), 0, slots - 3)[:, None] + jnp.arange(3)
  dy = jax.random.randint(keys[3], (rows,), 0, 2 * PAD + 1)
  dx = jax.random.randint(keys[4], (rows,), 0, 2 * PAD + 1)
  seed = jax.random.bits(keys[5], (rows,), jnp.uint32)
  return frames, env, stacks, dy, dx, seed


def print_best_times(variants: dict, iters: int, rows: int) -> None:
  """Prints µs per call of each jitted loop of `iters` calls (best of two rounds of five)."""
  for f in variants.values():
    f().block_until_ready()
  best = {}
  for _ in range(2):
    for name, f in variants.items():
      t0 = time.perf_counter()
      for _ in range(5):
        f().block_until_ready()
      best[name] = min(best.get(name, 1e9), (time.perf_counter() - t0) / (5 * iters))
  for name, seconds in best.items():
    print(f"{name:24s} {seconds * 1e6:8.1f} µs per {rows} rows", flush=True)


def parse_args(doc: str) -> argparse.Namespace:
  """The command line both fused-layer scripts take (`doc`: the script's docstring)."""
  p = argparse.ArgumentParser(description=doc.splitlines()[0])
  p.add_argument("--rows", type=int, default=256, help="R, transitions per call")
  p.add_argument("--slots", type=int, default=500, help="ring slots per env of the frames (32 envs)")
  p.add_argument("--iters", type=int, default=50, help="calls per timed loop")
  p.add_argument("--interpret", action="store_true", help="Pallas's interpreter; compare only")
  return p.parse_args()


def main():
  a = parse_args(__doc__)
  ks = jax.random.split(jax.random.PRNGKey(0), 8)
  frames, env, slots, dy, dx, seed = random_inputs(ks[:6], a.rows, a.slots)
  kernel = 0.2 * jax.random.normal(ks[6], (3, 3, CH, FEAT), jnp.float32)
  bias = 0.1 * jax.random.normal(ks[7], (FEAT,), jnp.float32)
  args = (frames, env, slots, dy, dx, seed, kernel, bias)
  ref = jax.jit(xla_forward)(*args).astype(jnp.float32)
  for noise in ("hash", "table"):
    got = jax.jit(functools.partial(pallas_forward, noise=noise, interpret=a.interpret))(*args)
    d = jnp.abs(ref - got.astype(jnp.float32))
    print(f"{noise}: max |xla - pallas| {float(d.max()):.4g}, mean {float(d.mean()):.3g} "
          f"(mean |xla| {float(jnp.abs(ref).mean()):.3g}), bit-equal {float(jnp.mean(d == 0)):.4f}",
          flush=True)
  if a.interpret:
    return

  def looped(fn, **kw):  # the slots move with i, so no call is loop-invariant
    def body(i, acc):
      out = fn(frames, env, (slots + i) % a.slots, dy, dx, seed, kernel, bias, **kw)
      return acc + out[:, 0, 0, 0].astype(jnp.float32).sum()
    return jax.jit(lambda: jax.lax.fori_loop(0, a.iters, body, 0.0))

  variants = {"xla": looped(xla_forward)}
  for noise in ("hash", "table", "none"):
    for warps in (2, 4):
      variants[f"pallas_{noise}_w{warps}"] = looped(pallas_forward, noise=noise, warps=warps)
  print_best_times(variants, a.iters, a.rows)


if __name__ == "__main__":
  main()
