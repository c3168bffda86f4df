"""The roofline counter of `dmcr_jax.benchmarks.learner_roofline`: FLOPs and bytes
per op category of an HLO module, against hand counts of a tiny program."""

import jax
import jax.numpy as jnp

from dmcr_jax.benchmarks import learner_roofline as L

K = 3


def _conv(x, kernel):
  return jax.lax.conv_general_dilated(x, kernel, (1, 1), "VALID",
                                      dimension_numbers=("NHWC", "HWIO", "NHWC"))


def test_roofline_counts_flops_and_bytes_of_convolutions_and_dots():
  # A 3×3 VALID convolution (4 images 10×10×3 → 8×8×5), tanh, a dot with a 5×7
  # matrix: FLOPs and bytes against the hand count, plain and vmapped over K = 3
  # (one grouped convolution).
  f = lambda x, k, w: jnp.sum(jnp.tanh(_conv(x, k)) @ w)
  args = (jnp.zeros((4, 10, 10, 3)), jnp.zeros((3, 3, 3, 5)), jnp.zeros((5, 7)))
  conv_flops, dot_flops = 2 * 4 * 8 * 8 * 5 * 27, 2 * 4 * 8 * 8 * 7 * 5
  costs = L.hlo_costs(jax.jit(f).lower(*args).as_text(dialect="hlo"))
  assert costs["convolution"] == dict(flops=conv_flops, ops=1,
                                      bytes=4 * (4 * 10 * 10 * 3 + 3 * 3 * 3 * 5 + 4 * 8 * 8 * 5))
  assert costs["dot"]["flops"] == dot_flops
  assert costs["elementwise"]["flops"] == 4 * 8 * 8 * 5  # the tanh
  batched = tuple(jnp.zeros((K,) + a.shape) for a in args)
  grouped = L.hlo_costs(jax.jit(jax.vmap(f)).lower(*batched).as_text(dialect="hlo"))
  assert grouped["convolution"]["ops"] == 0
  assert grouped["grouped convolution"]["flops"] == K * conv_flops
  assert grouped["dot"]["flops"] == K * dot_flops
