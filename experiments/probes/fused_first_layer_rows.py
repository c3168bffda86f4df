"""Experiment: `fused_first_layer.py`'s Pallas kernel with rows carried, and for two kernels at once.

A program per (transition, chunk of `rows_per` output rows) loops over its rows;
per row it gathers only the two new image rows' (64 columns × 32 taps) tiles (taps
kx, c of one ky, 27 of 32 used) and carries the third (ky = 0 is the previous row's
ky = 2), then sums three K = 32 products on tensor cores: half the gathers of
`fused_first_layer.py`'s kernel, and less zero padding. DrQ's noise comes from an
int8 table XLA draws first (``table``) or is left out (``none``: not the same
function, a lower bound). ``pair`` applies two kernels (as the online and target
encoders do to o′) to the same gathered tiles; ``xla_pair`` is the learner's way,
blocks built once and two cuDNN convolutions.

Usage (from the repository root)::

    python experiments/probes/fused_first_layer_rows.py [--rows 256] [--slots 500] [--interpret]

Prints the largest and mean difference from XLA's outputs, then µs per R rows
(best of two rounds of five `lax.fori_loop`s of `--iters` calls).
"""
import functools
import os
import sys

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import fused_first_layer as F  # noqa: E402 (this folder is not a package)
from fused_first_layer import CH, FEAT, H, OUT, PAD, W  # noqa: E402


def _kernel(frames_ref, base_ref, shift_ref, noise_ref, w_ref, b_ref, *out_refs, noise, rows_per, pair):
  """Output rows y0 … y0 + rows_per − 1 of transition r, one or two kernels."""
  r, chunk = pl.program_id(0), pl.program_id(1)
  y0 = chunk * rows_per
  x = jnp.arange(64, dtype=jnp.int32)[:, None]
  t = jnp.arange(32, dtype=jnp.int32)[None, :]
  kx, c = t // CH, t % CH
  frame, ch = c // 3, c % 3
  valid = (t < 3 * CH) & (x < OUT)
  img_c = jnp.minimum(2 * x + kx, W - 1)
  src_c = jnp.clip(img_c + shift_ref[r, 1] - PAD, 0, W - 1)
  dy = shift_ref[r, 0]
  base = jnp.where(frame == 0, base_ref[r, 0], jnp.where(frame == 1, base_ref[r, 1], base_ref[r, 2]))
  col = base + src_c * 3 + ch
  ncol = (r * H * W + img_c) * 3 + ch

  def tile(img_r):
    img_r = jnp.minimum(img_r, H - 1)
    src_r = jnp.clip(img_r + dy - PAD, 0, H - 1)
    pix = plgpu.load(frames_ref.at[col + src_r * (W * 3)], mask=valid, other=0).astype(jnp.int32)
    if noise == "table":
      n = plgpu.load(noise_ref.at[ncol + img_r * (W * 3)], mask=valid, other=0).astype(jnp.int32)
      pix = jnp.clip(pix + n, 0, 255)
    return jnp.where(valid, pix.astype(jnp.float32) / 255.0, 0.0).astype(jnp.bfloat16)

  co = jnp.arange(FEAT, dtype=jnp.int32)[None, :]
  nk = 2 if pair else 1
  ws = [[w_ref[k, j] for j in range(3)] for k in range(nk)]
  bs = [b_ref[k].astype(jnp.bfloat16).astype(jnp.float32)[None, :] for k in range(nk)]

  def body(i, t0):
    y = y0 + i
    t1 = tile(2 * y + 1)
    t2 = tile(2 * y + 2)
    for k in range(nk):
      acc = plgpu.dot(t0, ws[k][0]) + plgpu.dot(t1, ws[k][1]) + plgpu.dot(t2, ws[k][2])
      out = jnp.maximum(acc.astype(jnp.bfloat16).astype(jnp.float32) + bs[k], 0.0)
      plgpu.store(out_refs[k].at[r, jnp.minimum(y, OUT - 1), x, co], out.astype(jnp.bfloat16),
                  mask=(x < OUT) & (y < OUT))
    return t2

  jax.lax.fori_loop(0, rows_per, body, tile(2 * y0))


def rows_forward(frames, env, slots, dy, dx, seed, kernels, biases, *, noise="table", rows_per=11,
                 warps=4, interpret=False):
  """`fused_first_layer.xla_forward` for each of 1 or 2 (kernel (3, 3, 9, 32), bias) pairs: a tuple."""
  r = env.shape[0]
  flat, base, shift, table = F.kernel_operands(frames, env, slots, dy, dx, seed, noise)
  w = jnp.stack([jnp.pad(k.reshape(3, 3 * CH, FEAT), ((0, 0), (0, 32 - 3 * CH), (0, 0))) for k in kernels]
                ).astype(jnp.bfloat16)                                  # (nk, ky, 32, FEAT)
  b = jnp.stack(biases)
  pair = len(kernels) == 2
  call = pl.pallas_call(
      functools.partial(_kernel, noise=noise, rows_per=rows_per, pair=pair),
      grid=(r, -(-OUT // rows_per)),
      out_shape=[jax.ShapeDtypeStruct((r, OUT, OUT, FEAT), jnp.bfloat16)] * len(kernels),
      interpret=interpret,
      compiler_params=None if interpret else plgpu.CompilerParams(num_warps=warps, num_stages=1))
  return tuple(call(flat, base, shift, table, w, b))


def main():
  a = F.parse_args(__doc__)
  ks = jax.random.split(jax.random.PRNGKey(0), 10)
  frames, env, slots, dy, dx, seed = F.random_inputs(ks[:6], a.rows, a.slots)
  k1 = 0.2 * jax.random.normal(ks[6], (3, 3, CH, FEAT), jnp.float32)
  b1 = 0.1 * jax.random.normal(ks[7], (FEAT,), jnp.float32)
  k2 = 0.2 * jax.random.normal(ks[8], (3, 3, CH, FEAT), jnp.float32)
  b2 = 0.1 * jax.random.normal(ks[9], (FEAT,), jnp.float32)
  base_args = (frames, env, slots, dy, dx, seed)
  ref1 = jax.jit(F.xla_forward)(*base_args, k1, b1).astype(jnp.float32)
  ref2 = jax.jit(F.xla_forward)(*base_args, k2, b2).astype(jnp.float32)
  got = jax.jit(functools.partial(rows_forward, rows_per=11, interpret=a.interpret))(*base_args, [k1, k2], [b1, b2])
  for ref, g in zip((ref1, ref2), got):
    d = jnp.abs(ref - g.astype(jnp.float32))
    print(f"rows_per 11: max {float(d.max()):.4g} mean {float(d.mean()):.3g} bit-equal {float(jnp.mean(d == 0)):.4f}", flush=True)
  if a.interpret:
    return

  xla_pair = lambda *s: F.xla_forwards(*s, [(k1, b1), (k2, b2)])

  def looped(fn):
    def body(i, acc):
      outs = fn(frames, env, (slots + i) % a.slots, dy, dx, seed)
      outs = outs if isinstance(outs, tuple) else (outs,)
      return acc + sum(o[:, 0, 0, 0].astype(jnp.float32).sum() for o in outs)
    return jax.jit(lambda: jax.lax.fori_loop(0, a.iters, body, 0.0))

  variants = {"xla": looped(lambda *s: F.xla_forward(*s, k1, b1)), "xla_pair": looped(xla_pair)}
  for noise, rp, wp in (("table", 6, 4), ("table", 11, 4), ("table", 11, 2), ("table", 21, 4), ("none", 11, 4)):
    variants[f"rows{rp}_{noise}_w{wp}"] = looped(
        lambda *s, noise=noise, rp=rp, wp=wp: rows_forward(*s, [k1], [b1], noise=noise, rows_per=rp, warps=wp))
  variants["pair_rows11_table_w4"] = looped(
      lambda *s: rows_forward(*s, [k1, k2], [b1, b2], noise="table", rows_per=11, warps=4))
  F.print_best_times(variants, a.iters, a.rows)


if __name__ == "__main__":
  main()
