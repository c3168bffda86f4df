"""CURL and SAC+AE in the learner (train/curl.py, train/sac_ae.py, train/sac.py).

Each auxiliary loss against a NumPy computation on tiny inputs, the parameters
each step may and may not move, the configuration's defaults and refusals, and a
short run per algorithm that learns a pixel cue a random policy cannot use.
"""

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax.train import curl, loop, sac, sac_ae
from dmcr_jax.train.networks import (BlockConv, BlockDense, Decoder, Encoder, StrideTwoConv,
                                     StrideTwoConvTranspose, block_channel_multiple,
                                     center_crop, encoder_sides, space_to_depth,
                                     stride_one_on_blocks, stride_two_blocks)

pytestmark = pytest.mark.xdist_group("aux_losses")

ACTION_SIZE = 2
TINY = dict(feature_dim=8, hidden_dim=16, conv_channels=4, init_alpha=0.3)
CURL = sac.SACConfig(algo="curl", batch_size=6, curl_crop=16, **TINY)
SAC_AE = sac.SACConfig(algo="sac_ae", batch_size=6, **TINY)
SIDES = {"curl": 20, "sac_ae": 16}


def make_batch(seed: int, side: int, size: int = 6) -> sac.Batch:
  rng = np.random.default_rng(seed)
  pixels = lambda: jnp.asarray(rng.integers(0, 256, (size, side, side, 9), dtype=np.uint8))
  return sac.Batch(obs=pixels(), action=jnp.asarray(rng.uniform(-1, 1, (size, ACTION_SIZE)),
                                                    jnp.float32),
                   reward=jnp.asarray(rng.normal(size=size), jnp.float32),
                   discount=jnp.ones(size, jnp.float32), next_obs=pixels())


def _log_softmax(x):
  x = x - x.max(axis=1, keepdims=True)
  return x - np.log(np.exp(x).sum(axis=1, keepdims=True))


def test_curl_logits_and_info_nce_match_numpy():
  rng = np.random.default_rng(0)
  q, k, w = rng.normal(size=(5, 3)), rng.normal(size=(5, 3)), rng.normal(size=(3, 3))
  expect = q @ w @ k.T
  expect = expect - expect.max(axis=1, keepdims=True)
  got = curl.logits(jnp.asarray(q, jnp.float32), jnp.asarray(k, jnp.float32),
                    jnp.asarray(w, jnp.float32))
  np.testing.assert_allclose(got, expect, rtol=1e-5, atol=1e-5)
  assert np.allclose(np.max(got, axis=1), 0)
  # Labels are the diagonal: each anchor's positive is its own row's key.
  expect_loss = -np.mean(np.diag(_log_softmax(expect)))
  loss = curl.info_nce(jnp.asarray(q, jnp.float32), jnp.asarray(k, jnp.float32),
                       jnp.asarray(w, jnp.float32))
  np.testing.assert_allclose(loss, expect_loss, rtol=1e-5)
  # Matching keys score best: the loss falls when each key equals its query.
  eye = jnp.eye(3) * 10
  assert float(curl.info_nce(jnp.asarray(q), jnp.asarray(q), eye)) < float(
      curl.info_nce(jnp.asarray(q), jnp.asarray(q[::-1]), eye))


def test_crops_are_windows_of_their_images():
  images = jnp.asarray(np.random.default_rng(1).integers(0, 256, (7, 20, 22, 6)), jnp.uint8)
  out = np.asarray(curl.random_crop(jax.random.key(0), images, 16))
  assert out.shape == (7, 16, 16, 6)
  offsets = set()
  for b in range(7):
    found = [(t, l) for t in range(5) for l in range(7)
             if np.array_equal(out[b], np.asarray(images[b, t:t + 16, l:l + 16]))]
    assert found, b  # one window for all channels (frames) of the sample
    offsets.add(found[0])
  assert len(offsets) > 1  # per-sample offsets
  anchor, nxt, positive = curl.crops(jax.random.key(2), images, images, 16)
  assert not np.array_equal(anchor, positive)  # independent draws
  np.testing.assert_array_equal(center_crop(images, 16), images[:, 2:18, 3:19])
  with pytest.raises(ValueError, match="cannot crop"):
    curl.random_crop(jax.random.key(0), images, 21)


def test_reconstruction_target_matches_sac_ae_preprocessing():
  obs = jnp.asarray(np.arange(256, dtype=np.uint8).reshape(1, 4, 8, 8))
  key = jax.random.key(3)
  target = np.asarray(sac_ae.reconstruction_target(key, obs, bits=5))
  noise = np.asarray(jax.random.uniform(key, obs.shape, jnp.float32))
  expect = np.floor(np.arange(256).reshape(obs.shape) / 8) / 32 + noise / 32 - 0.5
  np.testing.assert_allclose(target, expect, atol=1e-6)
  assert target.min() >= -0.5 and target.max() < 0.5
  # 8 bits: plain /256 plus the dither.
  eight = np.asarray(sac_ae.reconstruction_target(key, obs, bits=8))
  np.testing.assert_allclose(eight, np.arange(256).reshape(obs.shape) / 256 + noise / 256 - 0.5,
                             atol=1e-6)
  feats = jnp.asarray([[1.0, 2.0], [0.0, 3.0]])
  loss, m = sac_ae.loss(jnp.zeros((2, 1)), jnp.ones((2, 1)), feats, latent_lambda=0.5)
  assert float(m["reconstruction_loss"]) == 1.0 and float(m["latent_loss"]) == 3.5
  assert float(loss) == pytest.approx(1.0 + 0.5 * 3.5)


@pytest.mark.parametrize("side", [84, 16, 17])
def test_decoder_restores_the_observation_shape(side):
  decoder = Decoder(side=side, out_channels=9, channels=4)
  params = decoder.init(jax.random.key(0), jnp.zeros((1, 8)))
  assert decoder.apply(params, jnp.ones((3, 8))).shape == (3, side, side, 9)


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


def test_decoder_parameters_keep_their_names_shapes_and_initialisers():
  # Checkpoints from before the phased output layer must load unchanged.
  side, s = 84, encoder_sides(84)[-1]
  decoder = Decoder(side=side, out_channels=9, channels=4)
  shapes = jax.eval_shape(decoder.init, jax.random.key(0), jnp.zeros((1, 8)))
  conv = {"kernel": (3, 3, 4, 4), "bias": (4,)}
  assert jax.tree_util.tree_map(lambda a: (a.shape, a.dtype), shapes) == jax.tree_util.tree_map(
      lambda shape: (shape, jnp.float32), {"params": {
          "fc": {"kernel": (8, 4 * s * s), "bias": (4 * s * s,)},
          "deconv0": conv, "deconv1": conv, "deconv2": conv,
          "out": {"kernel": (3, 3, 4, 9), "bias": (9,)}}}, is_leaf=lambda t: isinstance(t, tuple))
  # The same key initialises the phased layer as it did the transposed convolution.
  x = jnp.zeros((1, 5, 4, 2))
  new = StrideTwoConvTranspose(3, after=3, bias_init=nn.initializers.ones)
  old = nn.ConvTranspose(3, (3, 3), strides=(2, 2), padding=((2, 3), (2, 3)),
                         bias_init=nn.initializers.ones)
  got, expect = jax.jit(lambda key: (new.init(key, x), old.init(key, x)))(jax.random.key(4))
  assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(expect)
  assert jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, got, expect))


@functools.lru_cache(maxsize=None)
def _agent(algo):
  config = CURL if algo == "curl" else SAC_AE
  side = SIDES[algo]
  return config, jax.jit(lambda k: sac.init_agent(k, (side, side, 9), ACTION_SIZE, config))(
      jax.random.key(0))


def _changed(a, b):
  return any(not np.array_equal(x, y) for x, y in
             zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["curl", "sac_ae"])
def test_aux_step_moves_exactly_the_encoder_and_its_partner(algo):
  config, agent = _agent(algo)
  partner = "curl" if algo == "curl" else "decoder"
  batch = make_batch(0, SIDES[algo])
  obs = batch.obs if algo == "sac_ae" else curl.random_crop(jax.random.key(0), batch.obs, 16)
  aux_input = obs if algo == "sac_ae" else curl.random_crop(jax.random.key(1), batch.obs, 16)
  new, metrics = jax.jit(functools.partial(sac.aux_step, config=config))(
      agent, obs, aux_input, jax.random.key(5))
  assert np.isfinite(float(metrics["aux_loss"]))
  assert _changed(new.params["encoder"], agent.params["encoder"])
  assert _changed(new.params[partner], agent.params[partner])
  for untouched in ("critic", "actor"):
    assert not _changed(new.params[untouched], agent.params[untouched])
  assert not _changed(new.target_params, agent.target_params)
  assert not _changed(new.critic_opt_state, agent.critic_opt_state)
  if algo == "curl":
    # The momentum (target) encoder gets no gradient from the contrastive loss.
    aux = {"encoder": agent.params["encoder"], "curl": agent.params["curl"]}
    grad = jax.grad(lambda t: curl.aux_loss(
        aux, agent.replace(target_params={**agent.target_params, "encoder": t}),
        obs, aux_input, jax.random.key(0), config)[0])(agent.target_params["encoder"])
    assert all(not np.any(g) for g in jax.tree_util.tree_leaves(grad))
  else:
    # The decoder's optimizer decays its weights (a zero gradient still moves
    # them); the encoder's does not.
    params = {"encoder": agent.params["encoder"], "decoder": agent.params["decoder"]}
    zeros = jax.tree_util.tree_map(jnp.zeros_like, params)
    updates, _ = sac.aux_optimizer(config).update(zeros, agent.aux_opt_state, params)
    assert not _changed(updates["encoder"], zeros["encoder"])
    kernel = updates["decoder"]["params"]["fc"]["kernel"]
    assert np.all(np.sign(kernel) == -np.sign(params["decoder"]["params"]["fc"]["kernel"]))


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["curl", "sac_ae"])
def test_update_runs_the_aux_step_after_sac(algo):
  config, agent = _agent(algo)
  batch = make_batch(1, SIDES[algo])
  new, metrics = jax.jit(functools.partial(sac.update, config=config, update_actor=True))(
      agent, batch, jax.random.key(7))
  assert {"aux_loss", "critic_loss", "actor_loss"} <= set(metrics)
  assert all(np.isfinite(float(v)) for v in metrics.values())
  assert _changed(new.aux_opt_state, agent.aux_opt_state)
  # Acting takes the full observation (CURL center-crops it inside the encoder).
  assert sac.act(new, batch.obs, jax.random.key(0)).shape == (6, ACTION_SIZE)


def test_config_defaults_and_refusals():
  assert (SAC_AE.aug, SAC_AE.beta, SAC_AE.lam) == ("none", 1.0, 0.0)
  assert sac.SACConfig(algo="sac_ae").batch_size == 128
  assert sac.SACConfig().batch_size == 256 and sac.SACConfig().aug == "drq"
  assert (sac.SACConfig(algo="curl").aug, sac.SACConfig(algo="curl").beta) == ("none", 1.0)
  with pytest.raises(ValueError, match="sac_aug, curl, sac_ae"):
    sac.SACConfig(algo="drq")
  with pytest.raises(ValueError, match="CURL crops every row itself"):
    sac.SACConfig(algo="curl", aug="drq")
  with pytest.raises(ValueError, match="needs an augmentation"):
    sac.SACConfig(algo="sac_ae", lam=1e-5)
  assert sac.SACConfig(algo="sac_ae", aug="drq", lam=1e-5).beta == 1.0  # allowed
  assert loop.TrainConfig(sac=sac.SACConfig(algo="curl")).image_size == 100
  assert loop.TrainConfig(sac=sac.SACConfig(algo="sac_ae")).image_size == 84
  with pytest.raises(ValueError, match="image_size must be > curl_crop"):
    loop.check_config(loop.TrainConfig(image_size=84, sac=sac.SACConfig(algo="curl")))
  with pytest.raises(ValueError, match="CURL crops"):
    sac.init_agent(jax.random.key(0), (16, 16, 9), 1, sac.SACConfig(algo="curl", **TINY))


PIXEL_CUE_PAIRS = 100
"""`update_pair` calls of the pixel-cue test, as test_sac's: each learner's score passes
0.9 within 75 pairs."""


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["curl", "sac_ae"])
def test_learns_to_read_a_pixel_cue(algo):
  # The one-step pixel-cue task of tests/test_sac.py: a bright patch on the left
  # or right says which sign of the action pays (reward = ±action, discount 0); a
  # random policy earns 0. 200 updates of each algorithm must read it.
  side = SIDES[algo]
  config = dataclasses.replace(CURL if algo == "curl" else SAC_AE, batch_size=64,
                               init_alpha=0.01, critic_lr=3e-3, encoder_lr=3e-3,
                               actor_lr=3e-3)

  def images(right):  # right: (B,) bool
    cols = jnp.arange(side)
    mask = jnp.where(right[:, None], (cols >= side - 7) & (cols < side - 3),
                     (cols >= 3) & (cols < 7))
    rows = (jnp.arange(side) >= side // 2 - 3) & (jnp.arange(side) < side // 2 + 3)
    patch = rows[None, :, None] & mask[:, None, :]
    return jnp.broadcast_to(jnp.where(patch, 230, 20)[..., None],
                            (*patch.shape, 9)).astype(jnp.uint8)

  def make(key):
    k_side, k_action = jax.random.split(key)
    right = jax.random.bernoulli(k_side, 0.5, (64,))
    obs = images(right)
    action = jax.random.uniform(k_action, (64, 1), minval=-1, maxval=1)
    return sac.Batch(obs=obs, action=action, reward=jnp.where(right, 1.0, -1.0) * action[:, 0],
                     discount=jnp.zeros((64,)), next_obs=obs)

  @jax.jit
  def train(agent, key):
    def body(agent, k):
      k_batch, k_update = jax.random.split(k)
      return sac.update_pair(agent, jax.vmap(make)(jax.random.split(k_batch, 2)), k_update,
                             config)
    return jax.lax.scan(body, agent, jax.random.split(key, PIXEL_CUE_PAIRS))[0]

  agent = sac.init_agent(jax.random.key(0), (side, side, 9), 1, config)
  test = make(jax.random.key(123))
  sign = jnp.sign(test.reward / test.action[:, 0])
  score = lambda a: float(jnp.mean(sign * sac.act(a, test.obs, None, deterministic=True)[:, 0]))
  before = score(agent)
  agent = train(agent, jax.random.key(1))
  after = score(agent)
  assert int(agent.step) == 2 * PIXEL_CUE_PAIRS
  assert after > 0.8 and after > before + 0.5, (before, after)


def test_block_first_layer_is_the_strided_conv():
  # StrideTwoConv must compute nn.Conv(3×3, stride 2, VALID) of the same params:
  # the same outputs and gradients (params and input), for even and odd sides
  # (the encoder's 84 and CURL's 100, then small ones), non-square inputs.
  cases = [(84, 85, 9, 32), (100, 100, 9, 4), (21, 20, 3, 5), (3, 4, 2, 3), (6, 7, 1, 1)]
  rng = np.random.default_rng(1)
  normal = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
  inputs = [({"params": {"kernel": normal(3, 3, c_in, c_out), "bias": normal(c_out)}},
             normal(2, h, w, c_in),
             normal(2, (h - 3) // 2 + 1, (w - 3) // 2 + 1, c_out))
            for h, w, c_in, c_out in cases]

  assert_same_layer(cases, inputs, [
      (StrideTwoConv(c_out), nn.Conv(c_out, (3, 3), strides=(2, 2), padding="VALID"))
      for *_, c_out in cases])
  for case, (params, x, _) in zip(cases, inputs):
    half = StrideTwoConv(case[3], dtype="bfloat16")
    assert jax.eval_shape(half.apply, params, x).dtype == jnp.bfloat16, case
  # Blocks padded to 64 channels (16-bit inputs on GPUs) convolve the same.
  assert [block_channel_multiple(dtype, platform) for dtype, platform in
          (("bfloat16", "gpu"), ("float32", "gpu"), ("bfloat16", "cpu"))] == [32, 8, 8]
  # There frames of 3 channels take 4 each (9 → 16 per pixel): the same outputs and
  # parameter gradients; elsewhere (8) the 36 channels in order, padded to 40.
  for (params, x, _), (*_, c_in, c_out) in zip(inputs, cases):
    for multiple in (32, 8):
      blocks = stride_two_blocks(x, channel_multiple=multiple)
      if c_in == 9:
        assert (blocks.data.shape[-1], blocks.pixel_channels) == (
            (64, 16) if multiple == 32 else (40, 9))
      conv = nn.Conv(c_out, (3, 3), strides=(2, 2), padding="VALID")
      expect = conv.apply(params, x)
      np.testing.assert_allclose(StrideTwoConv(c_out).apply(params, blocks), expect,
                                 rtol=1e-5, atol=1e-5 * np.abs(expect).max())
      got, want = (jax.grad(lambda p, f=f: jnp.sum(jnp.sin(f(p))))(params) for f in (
          lambda p: StrideTwoConv(c_out).apply(p, blocks), lambda p: conv.apply(p, x)))
      for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-4 * np.abs(w).max())
  # The same key initialises it as it did nn.Conv, under the encoder's name.
  x = jnp.zeros((1, 84, 84, 9))
  got, expect = jax.jit(lambda key: (
      StrideTwoConv(32, kernel_init=nn.initializers.orthogonal()).init(key, x),
      nn.Conv(32, (3, 3), strides=(2, 2), padding="VALID",
              kernel_init=nn.initializers.orthogonal()).init(key, x)))(jax.random.key(3))
  assert jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, got, expect))
  with pytest.raises(ValueError, match="H, W ≥ 3"):
    StrideTwoConv(4).init(jax.random.key(0), jnp.zeros((1, 2, 5, 3)))


def _blocks(x):
  """`space_to_depth` of (B, H, W, C) images, odd sides padded by one zero pixel."""
  return space_to_depth(x, x.shape[1] + x.shape[1] % 2, x.shape[2] + x.shape[2] % 2)


def _pixels(blocks, height, width):
  """The inverse of `_blocks`: the first height × width pixels of the blocks."""
  b, h, w, c4 = blocks.shape
  x = blocks.reshape(b, h, w, 2, 2, c4 // 4).transpose(0, 1, 3, 2, 4, 5)
  return x.reshape(b, 2 * h, 2 * w, c4 // 4)[:, :height, :width]


def test_block_stride_one_layers_are_the_convolutions_and_the_dense_layer():
  # BlockConv between 2×2 blocks and back must compute nn.Conv(3×3, VALID) of the same
  # params, BlockDense nn.Dense of the flattened image (the blocks' pixels past the
  # image ignored): the same outputs and gradients (params and input), for even and
  # odd sides (the encoder's 41), non-square inputs.
  rng = np.random.default_rng(2)
  normal = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
  conv_cases = [(41, 41, 32, 32), (20, 21, 3, 5), (3, 4, 2, 3), (6, 7, 1, 1)]
  on_blocks = lambda layer, h, w: type("OnBlocks", (), {"apply": staticmethod(
      lambda p, x: _pixels(layer.apply(p, _blocks(x)), h - 2, w - 2))})
  assert_same_layer(
      conv_cases,
      [({"params": {"kernel": normal(3, 3, c_in, c_out), "bias": normal(c_out)}},
        normal(2, h, w, c_in), normal(2, h - 2, w - 2, c_out)) for h, w, c_in, c_out in conv_cases],
      [(on_blocks(BlockConv(c_out), h, w), nn.Conv(c_out, (3, 3), padding="VALID"))
       for h, w, _, c_out in conv_cases])
  # The image is the first H × W pixels of larger blocks: the rest must not count.
  dense_cases = [(35, 35, 32, 50, 1), (5, 4, 3, 7, 2), (1, 1, 1, 1, 0)]
  with_rest = lambda layer, extra: type("WithRest", (), {"apply": staticmethod(
      lambda p, x: layer.apply(p, _blocks(jnp.pad(x, ((0, 0), (0, extra), (0, extra), (0, 0)),
                                                  constant_values=7.0))))})
  flat_dense = lambda features: type("FlatDense", (), {"apply": staticmethod(
      lambda p, x: nn.Dense(features).apply(p, x.reshape(x.shape[0], -1)))})
  assert_same_layer(
      dense_cases,
      [({"params": {"kernel": normal(h * w * c, f), "bias": normal(f)}},
        normal(2, h, w, c), normal(2, f)) for h, w, c, f, _ in dense_cases],
      [(with_rest(BlockDense(f, (h, w)), extra), flat_dense(f))
       for h, w, _, f, extra in dense_cases])
  with pytest.raises(ValueError, match="2×2 blocks"):
    BlockConv(4).init(jax.random.key(0), jnp.zeros((1, 3, 3, 6)))
  with pytest.raises(ValueError, match="do not hold a 5×4 image"):
    BlockDense(3, (5, 4)).init(jax.random.key(0), jnp.zeros((1, 2, 2, 4)))


def test_encoder_on_blocks_is_the_encoder_on_pixels():
  # Encoder(blocks=True) must be the same function of the same parameters as on
  # pixels: the same initial parameters from one key, outputs and gradients; at the
  # paper's size, CURL's crop, sides that leave one output pixel, a single layer.
  assert [stride_one_on_blocks(platform) for platform in ("gpu", "cpu", "tpu")] == [
      True, False, False]
  rng = np.random.default_rng(3)
  for side, layers, channels, input_size in ((84, 4, 32, None), (100, 4, 4, 84),
                                             (15, 4, 4, None), (16, 2, 3, None),
                                             (84, 1, 4, None)):
    obs = jnp.asarray(rng.integers(0, 256, (2, side, side, 9)), jnp.uint8)
    pixels = Encoder(channels=channels, feature_dim=6, num_layers=layers,
                     input_size=input_size, blocks=False)
    blocks = pixels.clone(blocks=True)
    params, block_params = (e.init(jax.random.key(4), obs) for e in (pixels, blocks))
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, params, block_params))
    case = (side, layers, input_size)
    expect, got = (e.apply(params, obs) for e in (pixels, blocks))
    np.testing.assert_allclose(got, expect, rtol=1e-5, atol=1e-5, err_msg=str(case))
    want, grads = (jax.grad(lambda p, e=e: jnp.sum(jnp.sin(3 * e.apply(p, obs))))(params)
                   for e in (pixels, blocks))
    for g, w in zip(jax.tree_util.tree_leaves(grads), jax.tree_util.tree_leaves(want)):
      np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-4 * np.abs(w).max(), err_msg=str(case))
