"""train/layouts.py: each layer is its flax layer (nn.Conv, nn.Dense, nn.ConvTranspose).

The same outputs and the same gradients (parameters and input) as the flax layer
on random parameters, in either implementation, for even and odd, non-square
sides (a wrong tap, row or channel order fails them); the same initial
parameters from one key; and the whole encoder on blocks as on pixels.
"""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax.train import layouts
from dmcr_jax.train.layouts import Blocks, Conv, Dense, StrideTwoConvTranspose
from dmcr_jax.train.networks import Encoder

pytestmark = pytest.mark.xdist_group("layouts")


def assert_same_layer(cases, inputs, pairs):
  """Each case's two layers give the same outputs and the same gradients of a random
  linear functional Σ weights·y with respect to the params and the input.

  Args:
    cases: one tuple per case (printed on failure).
    inputs: per case (params, x, weights).
    pairs: per case (layer under test, the flax reference layer), with the same params.
  """
  @jax.jit
  def outputs_and_grads(inputs):  # one compilation for all cases
    results = []
    for (params, x, weights), layers in zip(inputs, pairs):
      for layer in layers:
        y, vjp = jax.vjp(layer.apply, params, x)
        results.append((y, *vjp(weights)))
    return results

  results = outputs_and_grads(inputs)
  for case, (_, _, weights), got, expect in zip(cases, inputs, results[::2], results[1::2]):
    assert got[0].shape == expect[0].shape == weights.shape, case
    assert got[0].dtype == expect[0].dtype == jnp.float32, case
    for g, e in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(expect)):
      np.testing.assert_allclose(g, e, rtol=1e-5, atol=1e-5 * np.abs(e).max(),
                                 err_msg=str(case))


def _as_pixels(layer, blocks_in=False):
  """`layer` with pixels in and out: its output cut back into pixels (and, with
  `blocks_in`, its input given as `Blocks`)."""
  def apply(params, x):
    return layouts.to_pixels(layer.apply(params, layouts.to_blocks(x) if blocks_in else x))
  return type("AsPixels", (), {"apply": staticmethod(apply)})


def _same_params(a, b):
  return (jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
          and jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, a, b)))


@pytest.mark.parametrize("strides", [1, 2])
def test_conv_is_nn_conv_in_either_implementation(strides):
  # (H, W, C_in, C_out): the encoder's sides (84 and CURL's 100 at stride 2, 41 at
  # stride 1), then small ones, odd and even, never square.
  cases = [(84, 85, 9, 32), (41, 40, 32, 32), (21, 20, 3, 5), (3, 4, 2, 3), (6, 7, 1, 1)]
  if strides == 2:
    cases.append((100, 101, 9, 4))
  rng = np.random.default_rng(strides)
  normal = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
  out = lambda side: (side - 3) // strides + 1
  inputs = [({"params": {"kernel": normal(3, 3, c_in, c_out), "bias": normal(c_out)}},
             normal(2, h, w, c_in), normal(2, out(h), out(w), c_out))
            for h, w, c_in, c_out in cases]
  flax_conv = lambda c_out: nn.Conv(c_out, (3, 3), strides=(strides, strides), padding="VALID")
  variants = [(impl, blocks_in) for impl in layouts.IMPLS for blocks_in in (False, True)]
  for impl, blocks_in in variants:
    assert_same_layer(
        [(impl, blocks_in, *case) for case in cases], inputs,
        [(_as_pixels(Conv(c_out, strides, impl=impl), blocks_in), flax_conv(c_out))
         for *_, c_out in cases])
  for impl in layouts.IMPLS:
    # The layout of the output is the implementation's.
    params, x, _ = inputs[2]
    y = Conv(5, strides, impl=impl).apply(params, x)
    assert isinstance(y, Blocks) == (impl == "blocks"), impl
    # The compute dtype is respected; the parameters stay float32.
    half = Conv(5, strides, impl=impl, dtype="bfloat16")
    assert jax.eval_shape(half.apply, params, x).dtype == jnp.bfloat16
    # The same key initialises it as it does nn.Conv.
    init = nn.initializers.orthogonal()
    x = jnp.zeros((1, 84, 84, 9))
    got, expect = jax.jit(lambda key: (
        Conv(32, strides, impl=impl, kernel_init=init, bias_init=nn.initializers.ones
             ).init(key, x),
        nn.Conv(32, (3, 3), strides=(strides, strides), padding="VALID", kernel_init=init,
                bias_init=nn.initializers.ones).init(key, x)))(jax.random.key(3))
    assert _same_params(got, expect), impl


def test_stride_two_blocks_pad_channels_for_either_multiple():
  # Blocks padded to 64 channels (16-bit inputs on GPUs) convolve the same as the
  # 36 channels in order padded to 40 (elsewhere): frames of 3 channels then take 4
  # each (9 → 16 per pixel).
  assert [layouts.block_channel_multiple(dtype, platform) for dtype, platform in
          (("bfloat16", "gpu"), ("float32", "gpu"), ("bfloat16", "cpu"))] == [32, 8, 8]
  rng = np.random.default_rng(1)
  normal = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
  cases = ((84, 85, 9, 32), (21, 20, 3, 5), (6, 7, 1, 1), (9, 9, 12, 2))
  multiples = (32, 8)
  inputs = [(normal(3, 3, c_in, c_out), normal(2, h, w, c_in)) for h, w, c_in, c_out in cases]
  for (_, _, c_in, _), (_, x) in zip(cases, inputs):
    for multiple in multiples:
      made = {}

      def blocks_of(x, multiple=multiple):
        data, made["per_pixel"] = layouts.stride_two_blocks(x, multiple)
        return data
      shape = jax.eval_shape(blocks_of, x).shape
      assert shape[-1] % multiple == 0
      if c_in == 9:
        assert (shape[-1], made["per_pixel"]) == ((64, 16) if multiple == 32 else (40, 9))

  @jax.jit
  def convs_and_grads(inputs):  # one compilation for all cases
    conv = lambda k, x: jax.lax.conv_general_dilated(
        x, k, (2, 2), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    results = []
    for kernel, x in inputs:
      runs = [lambda k, x=x: conv(k, x)] + [
          lambda k, x=x, m=m: layouts.stride_two_conv(x, k, channel_multiple=m)
          for m in multiples]
      results.append([(run(kernel), jax.grad(lambda k, run=run: jnp.sum(jnp.sin(run(k))))(kernel))
                      for run in runs])
    return results

  for case, ((expect, want), *got) in zip(cases, convs_and_grads(inputs)):
    for multiple, (out, grad) in zip(multiples, got):
      np.testing.assert_allclose(out, expect, rtol=1e-5, atol=1e-5 * np.abs(expect).max(),
                                 err_msg=str((case, multiple)))
      np.testing.assert_allclose(grad, want, rtol=1e-4, atol=1e-4 * np.abs(want).max(),
                                 err_msg=str((case, multiple)))
  with pytest.raises(ValueError, match="H, W ≥ 3"):
    Conv(4, 2, impl="blocks").init(jax.random.key(0), jnp.zeros((1, 2, 5, 3)))


def test_dense_is_nn_dense_of_the_flattened_images():
  # On `Blocks` whose pixels past the image (an odd side's extra row or column)
  # hold garbage, which must not count; and on pixels.
  rng = np.random.default_rng(2)
  normal = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
  cases = [(35, 35, 32, 50), (5, 4, 3, 7), (4, 5, 2, 3), (1, 1, 1, 1)]

  def garbage_blocks(x):
    h, w = x.shape[1:3]
    padded = jnp.pad(x, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), constant_values=7.0)
    return Blocks(layouts.space_to_depth(padded, h + h % 2, w + w % 2), h, w)

  on_blocks = lambda layer: type("OnBlocks", (), {"apply": staticmethod(
      lambda p, x: layer.apply(p, garbage_blocks(x)))})
  flat_dense = lambda features: type("FlatDense", (), {"apply": staticmethod(
      lambda p, x: nn.Dense(features).apply(p, x.reshape(x.shape[0], -1)))})
  inputs = [({"params": {"kernel": normal(h * w * c, f), "bias": normal(f)}},
             normal(2, h, w, c), normal(2, f)) for h, w, c, f in cases]
  for wrap in (on_blocks, lambda layer: layer):
    assert_same_layer(cases, inputs, [(wrap(Dense(f)), flat_dense(f)) for *_, f in cases])
  x = jnp.zeros((1, 5, 4, 3))
  got, expect = jax.jit(lambda key: (
      Dense(7, kernel_init=nn.initializers.orthogonal()).init(key, layouts.to_blocks(x)),
      nn.Dense(7, kernel_init=nn.initializers.orthogonal()).init(key, x.reshape(1, -1))
  ))(jax.random.key(5))
  assert _same_params(got, expect)


def test_blocks_round_trip_and_refusals():
  x = jnp.asarray(np.random.default_rng(3).normal(size=(2, 5, 6, 3)), jnp.float32)
  blocks = layouts.to_blocks(x)
  assert blocks.data.shape == (2, 3, 3, 12) and blocks.shape == x.shape
  np.testing.assert_array_equal(layouts.to_pixels(blocks), x)
  # Block channel (2a + b)·C + c holds pixel (2i + a, 2j + b), channel c.
  np.testing.assert_array_equal(blocks.data[:, 1, 2, (2 * 1 + 0) * 3 + 2], x[:, 3, 4, 2])
  assert layouts.to_blocks(blocks) is blocks
  assert [layouts.default_impl(p) for p in ("gpu", "cpu", "tpu")] == ["blocks", "pixels",
                                                                      "pixels"]
  with pytest.raises(ValueError, match="impl must be one of pixels, blocks"):
    Conv(4, impl="cudnn").init(jax.random.key(0), x)
  with pytest.raises(ValueError, match="strides must be 1 or 2"):
    Conv(4, 3).init(jax.random.key(0), x)
  with pytest.raises(ValueError, match="H, W ≥ 3"):
    Conv(4, impl="blocks").init(jax.random.key(0), jnp.zeros((1, 2, 5, 3)))


def test_encoder_on_blocks_is_the_encoder_on_pixels():
  # Encoder(impl="blocks") must be the same function of the same parameters as on
  # pixels: the same initial parameters from one key, outputs and gradients; at the
  # paper's size, CURL's crop, sides that leave one output pixel, a single layer.
  rng = np.random.default_rng(3)
  cases = ((84, 4, 32, None), (100, 4, 4, 84), (15, 4, 4, None), (16, 2, 3, None),
           (84, 1, 4, None))
  obs = [jnp.asarray(rng.integers(0, 256, (2, side, side, 9)), jnp.uint8)
         for side, *_ in cases]
  encoders = []
  for side, layers, channels, input_size in cases:
    pixels = Encoder(channels=channels, feature_dim=6, num_layers=layers,
                     input_size=input_size, impl="pixels")
    encoders.append((pixels, pixels.clone(impl="blocks")))

  @jax.jit
  def init_apply_and_grads(obs):  # one compilation for all cases
    results = []
    for (pixels, blocks), x in zip(encoders, obs):
      params, block_params = (e.init(jax.random.key(4), x) for e in (pixels, blocks))
      expect, got = (e.apply(params, x) for e in (pixels, blocks))
      want, grads = (jax.grad(lambda p, e=e: jnp.sum(jnp.sin(3 * e.apply(p, x))))(params)
                     for e in (pixels, blocks))
      results.append((params, block_params, expect, got, want, grads))
    return results

  for case, (params, block_params, expect, got, want, grads) in zip(
      cases, init_apply_and_grads(obs)):
    case = (case[0], case[1], case[3])   # side, layers, input_size
    assert _same_params(params, block_params), case
    np.testing.assert_allclose(got, expect, rtol=1e-5, atol=1e-5, err_msg=str(case))
    for g, w in zip(jax.tree_util.tree_leaves(grads), jax.tree_util.tree_leaves(want)):
      np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-4 * np.abs(w).max(), err_msg=str(case))


def test_phased_output_layer_is_the_strided_conv_transpose():
  # StrideTwoConvTranspose must compute nn.ConvTranspose(stride 2, padding (2,
  # after)) of the same params: the same outputs, and the same gradients of a
  # random linear functional Σ weights·y with respect to the params and the input.
  # (input side, padding after, C_in, C_out): the Decoder's output layer for sides
  # 84, 100, 64, 33, 17 and 16, then paddings it never uses (past the last input
  # pixel, and none). The inputs are not square, to tell the axes apart.
  cases = [(41, 3, 32, 9), (49, 3, 3, 5), (31, 3, 4, 9), (16, 2, 4, 3), (8, 2, 1, 1),
           (7, 3, 2, 4), (6, 5, 3, 2), (5, 0, 2, 3)]
  rng = np.random.default_rng(0)
  normal = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
  inputs = [({"params": {"kernel": normal(3, 3, c_in, c_out), "bias": normal(c_out)}},
             normal(2, in_side, in_side + 1, c_in),
             normal(2, 2 * in_side - 1 + after, 2 * in_side + 1 + after, c_out))
            for in_side, after, c_in, c_out in cases]

  assert_same_layer(cases, inputs, [
      (StrideTwoConvTranspose(c_out, after=after),
       nn.ConvTranspose(c_out, (3, 3), strides=(2, 2), padding=((2, after), (2, after))))
      for _, after, _, c_out in cases])
  for case, (params, x, _) in zip(cases, inputs):
    # The compute dtype is respected; the parameters stay float32.
    half = StrideTwoConvTranspose(case[3], after=case[1], dtype="bfloat16")
    assert jax.eval_shape(half.apply, params, x).dtype == jnp.bfloat16, case
  # The same key initialises it as nn.ConvTranspose.
  x = jnp.zeros((1, 5, 4, 2))
  new = StrideTwoConvTranspose(3, after=3, bias_init=nn.initializers.ones)
  old = nn.ConvTranspose(3, (3, 3), strides=(2, 2), padding=((2, 3), (2, 3)),
                         bias_init=nn.initializers.ones)
  got, expect = jax.jit(lambda key: (new.init(key, x), old.init(key, x)))(jax.random.key(4))
  assert _same_params(got, expect)
