"""CURL and SAC+AE in the learner (train/curl.py, train/sac_ae.py, train/sac.py).

Each auxiliary loss against a NumPy computation on tiny inputs, the parameters
each step may and may not move, the configuration's defaults and refusals, and a
short run per algorithm that learns a pixel cue a random policy cannot use.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax.train import curl, loop, sac, sac_ae
from dmcr_jax.train.networks import Decoder, center_crop, encoder_sides
from tests.compile_options import run_faster

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


def test_decoder_parameters_keep_their_names_shapes_and_initialisers():
  # The parameter tree checkpoints hold (the output layer's is nn.ConvTranspose's;
  # tests/test_layouts.py checks the layer itself).
  side, s = 84, encoder_sides(84)[-1]
  decoder = Decoder(side=side, out_channels=9, channels=4)
  shapes = jax.eval_shape(decoder.init, jax.random.key(0), jnp.zeros((1, 8)))
  conv = {"kernel": (3, 3, 4, 4), "bias": (4,)}
  assert jax.tree_util.tree_map(lambda a: (a.shape, a.dtype), shapes) == jax.tree_util.tree_map(
      lambda shape: (shape, jnp.float32), {"params": {
          "fc": {"kernel": (8, 4 * s * s), "bias": (4 * s * s,)},
          "deconv0": conv, "deconv1": conv, "deconv2": conv,
          "out": {"kernel": (3, 3, 4, 9), "bias": (9,)}}}, is_leaf=lambda t: isinstance(t, tuple))


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

  # Its run, not its compilation, dominates: compiled with LLVM's optimisations.
  @functools.partial(jax.jit, compiler_options=run_faster())
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
