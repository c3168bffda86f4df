"""Experiment: the encoder's stride-1 3×3 layers on pixels, or on 2×2 pixel blocks.

The encoder's layers 2–4 (ReLU(Conv(32, 3×3, stride 1, VALID) + bias)) map a
(R, 41, 41, 32) bfloat16 activation to (R, 35, 35, 32). ``pixels``: as `nn.Conv`
computes them (the encoder's way on CPUs; 32 channels). ``blocks``: the same function
on 2×2 pixel blocks, the encoder's way on GPUs (`networks.BlockConv`): the input
padded to 42 × 42 and cut into 21 × 21 blocks of 128 channels
(`networks.space_to_depth`), each layer a 2×2 VALID convolution with a
(2, 2, 128, 128) kernel assembled from the 3×3 one
(`networks.stride_one_block_kernel`: most of its taps are zero), the result cut
back to pixels and cropped to 35 × 35 (the encoder's dense layer reads the blocks
instead). More multiply-adds (16 × 128² per 4 output pixels against 9 × 32² per
pixel), on the channel counts tensor cores are made for. Times a forward pass (``fwd``) and the
gradient of a sum with respect to the parameters and the input (``grad``, as the
critic's pass needs).

Usage (from the repository root)::

    python experiments/probes/block_layers.py [--rows 256,512] [--iters 50]

Prints the largest difference between the two forms' outputs, then µs per call of
each form and pass.
"""
import argparse
import time

import jax
import jax.numpy as jnp

from dmcr_jax.train import networks

SIDE, CH, LAYERS = 41, 32, 3


def conv(x, k):
  return jax.lax.conv_general_dilated(x, k, (1, 1), "VALID",
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


def pixels(params, x):
  for k, bias in params:
    x = jax.nn.relu(conv(x, k.astype(x.dtype)) + bias.astype(x.dtype))
  return x


def blocks(params, x):
  side = x.shape[1] + (x.shape[1] % 2)
  y = networks.space_to_depth(x, side, side)
  for k, bias in params:
    block_kernel = networks.stride_one_block_kernel(k).astype(x.dtype)
    y = jax.nn.relu(conv(y, block_kernel) + jnp.tile(bias, 4).astype(x.dtype))
  r, h, w, c = y.shape
  y = y.reshape(r, h, w, 2, 2, c // 4).transpose(0, 1, 3, 2, 4, 5).reshape(r, 2 * h, 2 * w, c // 4)
  out = x.shape[1] - 2 * len(params)
  return y[:, :out, :out]


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--rows", default="256,512")
  p.add_argument("--iters", type=int, default=50)
  a = p.parse_args()
  key = jax.random.PRNGKey(0)
  params = []
  for i in range(LAYERS):
    kk, kb, key = jax.random.split(key, 3)
    params.append((jax.random.normal(kk, (3, 3, CH, CH)) * 0.08,
                   jax.random.normal(kb, (CH,)) * 0.05))
  print(jax.devices()[0].device_kind, flush=True)
  for rows in [int(r) for r in a.rows.split(",")]:
    x = jax.random.uniform(key, (rows, SIDE, SIDE, CH)).astype(jnp.bfloat16)
    ref = jax.jit(pixels)(params, x).astype(jnp.float32)
    got = jax.jit(blocks)(params, x).astype(jnp.float32)
    diff, mean = float(jnp.max(jnp.abs(ref - got))), float(jnp.mean(jnp.abs(ref)))
    print(f"rows {rows}: shapes {ref.shape} {got.shape}, largest |difference| {diff:.4f}, "
          f"mean |output| {mean:.4f}", flush=True)
    for name, fn in (("pixels", pixels), ("blocks", blocks)):
      loss = lambda pr, xx, fn=fn: fn(pr, xx).astype(jnp.float32).sum()
      passes = {"fwd": jax.jit(loss), "grad": jax.jit(jax.grad(loss, argnums=(0, 1)))}
      for pname, f in passes.items():
        def run(n):
          out = None
          for i in range(n):
            out = f(params, x)
          jax.block_until_ready(out)
        run(3)
        best = float("inf")
        for _ in range(3):
          t = time.perf_counter()
          run(a.iters)
          best = min(best, (time.perf_counter() - t) / a.iters)
        print(f"  {name:6s} {pname:4s} {best * 1e6:8.1f} µs", flush=True)


if __name__ == "__main__":
  main()
