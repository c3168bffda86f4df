"""Tests of the SAC+AUG learner core (train/networks.py, train/losses.py,
train/sac_config.py, train/sac.py).

Tiny networks on 16×16×9 images: the losses against NumPy recomputations from the
modules' outputs, the Polyak targets, β row mixing, where the λ term's and the
actor's gradients go, the tanh-Gaussian log-density, and a jitted and a vmapped
`update_pair`.
"""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax import augment
from dmcr_jax.train import losses, sac
from dmcr_jax.train.networks import (Actor, squash_log_std, tanh_gaussian_log_prob,
                            tanh_gaussian_sample)
from tests.compile_options import run_faster

pytestmark = pytest.mark.xdist_group("sac")

OBS_SHAPE = (16, 16, 9)
ACTION_SIZE = 2
BATCH = 8
CONFIG = sac.SACConfig(batch_size=BATCH, feature_dim=8, hidden_dim=16, conv_channels=4,
                       lam=0.1, init_alpha=0.3)


def make_batch(seed: int, leading=()) -> sac.Batch:
  """Random transitions; pixels in 1…254 (so 0 and 255 − x are recognisable)."""
  rng = np.random.default_rng(seed)
  shape = (*leading, BATCH)
  return sac.Batch(
      obs=jnp.asarray(rng.integers(1, 255, (*shape, *OBS_SHAPE), dtype=np.uint8)),
      action=jnp.asarray(rng.uniform(-1, 1, (*shape, ACTION_SIZE)), jnp.float32),
      reward=jnp.asarray(rng.normal(size=shape), jnp.float32),
      discount=jnp.asarray(rng.integers(0, 2, shape), jnp.float32),
      next_obs=jnp.asarray(rng.integers(1, 255, (*shape, *OBS_SHAPE), dtype=np.uint8)))


# One compiled initialiser for the whole file (eager init compiles op by op).
init_agent = jax.jit(sac.init_agent, static_argnums=(1, 2, 3))


@pytest.fixture(scope="module")
def agent():
  """An agent whose targets differ from its online networks (as after training)."""
  agent = init_agent(jax.random.key(0), OBS_SHAPE, ACTION_SIZE, CONFIG)
  other = init_agent(jax.random.key(1), OBS_SHAPE, ACTION_SIZE, CONFIG)
  return agent.replace(target_params={"encoder": other.params["encoder"],
                                      "critic": other.params["critic"]})


@pytest.fixture(scope="module")
def batch():
  return make_batch(0)


def _encode(agent, obs, target=False):
  params = agent.target_params if target else agent.params
  return np.asarray(agent.networks.encoder.apply(params["encoder"], obs), np.float64)


def _q(agent, features, action, target=False):
  params = agent.target_params if target else agent.params
  q1, q2 = agent.networks.critic.apply(params["critic"], jnp.asarray(features, jnp.float32),
                                       action)
  return np.asarray(q1, np.float64), np.asarray(q2, np.float64)


def _sample(agent, features, key):
  action, log_prob = agent.networks.actor.apply(
      agent.params["actor"], jnp.asarray(features, jnp.float32), key, method=Actor.sample)
  return action, np.asarray(log_prob, np.float64)


def _assert_tree(check, a, b):
  jax.tree_util.tree_map(lambda x, y: check(np.asarray(x), np.asarray(y)), a, b)


def _assert_same_computation(x, y):
  """Equal up to float32's last bits: the values of two XLA programs that compute
  the same function (another fusion, another instruction order)."""
  np.testing.assert_allclose(x, y, rtol=2e-5, atol=1e-7)


# --------------------------------------------------------------------------- #
# The policy distribution.
# --------------------------------------------------------------------------- #


def test_tanh_gaussian_log_prob_and_sample_match_numpy():
  rng = np.random.default_rng(0)
  mean = rng.normal(size=(5, 3)).astype(np.float32)
  log_std = rng.uniform(-2, 1, (5, 3)).astype(np.float32)
  u = rng.normal(size=(5, 3)).astype(np.float32) * 2
  std = np.exp(log_std.astype(np.float64))
  expected = np.sum(-0.5 * ((u - mean) / std) ** 2 - np.log(std)
                    - 0.5 * np.log(2 * np.pi) - np.log(1 - np.tanh(u.astype(np.float64)) ** 2),
                    axis=-1)
  got = tanh_gaussian_log_prob(jnp.asarray(u), jnp.asarray(mean), jnp.asarray(log_std))
  np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)

  key = jax.random.key(3)
  action, log_prob = tanh_gaussian_sample(key, jnp.asarray(mean), jnp.asarray(log_std))
  pre_tanh = mean + std * np.asarray(jax.random.normal(key, mean.shape), np.float64)
  np.testing.assert_allclose(action, np.tanh(pre_tanh), rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(
      log_prob, tanh_gaussian_log_prob(jnp.asarray(pre_tanh, jnp.float32),
                                       jnp.asarray(mean), jnp.asarray(log_std)),
      rtol=1e-5, atol=1e-5)

  # The log-std squashing: (−10, 2), rescaled tanh, midpoint −4 at 0.
  raw = jnp.asarray([-1e4, 0.0, 1e4, 0.3])
  np.testing.assert_allclose(squash_log_std(raw),
                             [-10, -4, 2, -10 + 6 * (np.tanh(0.3) + 1)], rtol=1e-6)


def test_network_shapes_and_act(agent, batch):
  features = agent.networks.encoder.apply(agent.params["encoder"], batch.obs)
  assert features.shape == (BATCH, CONFIG.feature_dim)
  assert np.all(np.abs(features) < 1)
  mean, log_std = agent.networks.actor.apply(agent.params["actor"], features)
  assert mean.shape == log_std.shape == (BATCH, ACTION_SIZE)
  assert np.all((log_std > -10) & (log_std < 2))

  act = jax.jit(sac.act, static_argnames="deterministic")
  greedy = act(agent, batch.obs, jax.random.key(0), deterministic=True)
  np.testing.assert_allclose(greedy, np.tanh(mean), rtol=1e-6, atol=1e-6)
  sampled = act(agent, batch.obs, jax.random.key(0))
  assert sampled.shape == (BATCH, ACTION_SIZE)
  assert np.all(np.abs(sampled) <= 1) and not np.allclose(sampled, greedy)


# --------------------------------------------------------------------------- #
# The losses against NumPy.
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("beta", [0.0, 0.9, 1.0])
def test_critic_loss_matches_numpy(agent, batch, beta):
  config = dataclasses.replace(CONFIG, beta=beta)
  mixed, z_obs = losses.augment_and_mix(jax.random.key(5), batch, augment.get("drq"), beta)
  key = jax.random.key(7)
  params = {"encoder": agent.params["encoder"], "critic": agent.params["critic"]}
  loss, metrics = losses.critic_loss(params, agent, batch, mixed, z_obs, key, config)

  alpha = math.exp(float(agent.log_alpha))
  next_action, next_log_prob = _sample(agent, _encode(agent, mixed.next_obs), key)
  tq1, tq2 = _q(agent, _encode(agent, mixed.next_obs, target=True), next_action,
                target=True)
  y = (np.asarray(mixed.reward) + 0.99 * np.asarray(mixed.discount)
       * (np.minimum(tq1, tq2) - alpha * next_log_prob))
  q1, q2 = _q(agent, _encode(agent, mixed.obs), mixed.action)
  td = np.mean((q1 - y) ** 2) + np.mean((q2 - y) ** 2)
  lam = 0.1 * np.mean(np.sum((_encode(agent, batch.obs) - _encode(agent, z_obs)) ** 2, -1))
  assert lam > 0
  np.testing.assert_allclose(metrics["critic_loss"], td, rtol=1e-5)
  np.testing.assert_allclose(metrics["lam_loss"], lam, rtol=1e-4)
  np.testing.assert_allclose(loss, td + lam, rtol=1e-5)
  np.testing.assert_allclose(metrics["q"], 0.5 * (q1.mean() + q2.mean()), rtol=1e-5,
                             atol=1e-6)


def test_actor_and_alpha_losses_match_numpy(agent, batch):
  key = jax.random.key(11)
  loss, log_prob = losses.actor_loss(agent.params["actor"], agent, batch.obs, key)
  features = _encode(agent, batch.obs)
  action, expected_log_prob = _sample(agent, features, key)
  q1, q2 = _q(agent, features, action)
  alpha = math.exp(float(agent.log_alpha))
  np.testing.assert_allclose(log_prob, expected_log_prob, rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(loss, np.mean(alpha * expected_log_prob - np.minimum(q1, q2)),
                             rtol=1e-5, atol=1e-6)

  target_entropy = CONFIG.entropy_target(ACTION_SIZE)
  assert target_entropy == -ACTION_SIZE
  value, (grad_log_alpha, grad_log_prob) = jax.value_and_grad(
      losses.alpha_loss, argnums=(0, 1))(agent.log_alpha, log_prob, target_entropy)
  expected = np.mean(-alpha * (expected_log_prob + target_entropy))
  np.testing.assert_allclose(value, expected, rtol=1e-5)
  np.testing.assert_allclose(grad_log_alpha, expected, rtol=1e-5)  # d e^x/dx = e^x
  assert not np.any(np.asarray(grad_log_prob))  # log π is a constant


def test_soft_update_targets_matches_numpy(agent):
  new = losses.soft_update_targets(agent, CONFIG)
  for name, tau in (("encoder", 0.05), ("critic", 0.01)):
    _assert_tree(lambda got, want: np.testing.assert_allclose(got, want, rtol=1e-6,
                                                              atol=1e-7),
                 new.target_params[name],
                 jax.tree_util.tree_map(
                     lambda p, t: (1 - tau) * np.asarray(t, np.float64)
                     + tau * np.asarray(p, np.float64),
                     agent.params[name], agent.target_params[name]))
  _assert_tree(np.testing.assert_array_equal, new.params, agent.params)


# --------------------------------------------------------------------------- #
# β mixing and the λ term.
# --------------------------------------------------------------------------- #


def test_num_augmented():
  assert losses.num_augmented(256, 0.9) == 230
  assert losses.num_augmented(100, 0.29) == 29
  assert losses.num_augmented(8, 0.0) == 0 and losses.num_augmented(8, 1.0) == 8


@pytest.mark.parametrize("beta", [0.0, 0.3, 0.9, 1.0])
def test_beta_mixes_exactly_the_first_rows(batch, beta):
  n = math.floor(beta * BATCH)
  invert = lambda key, images: jax.tree_util.tree_map(lambda x: 255 - x, images)
  mixed, z_obs = losses.augment_and_mix(jax.random.key(0), batch, invert, beta)
  np.testing.assert_array_equal(z_obs, 255 - np.asarray(batch.obs))
  for got, raw in ((mixed.obs, batch.obs), (mixed.next_obs, batch.next_obs)):
    got, raw = np.asarray(got), np.asarray(raw)
    assert np.all(got[:n] != raw[:n])  # pixels are never 127.5
    np.testing.assert_array_equal(got[n:], raw[n:])
  for name in ("action", "reward", "discount"):
    np.testing.assert_array_equal(getattr(mixed, name), getattr(batch, name))

  # A registered augmentation: "window" zeroes a border, drawn once per sample
  # for o and o′ alike.
  mixed, _ = losses.augment_and_mix(jax.random.key(1), batch, augment.get("window"), beta)
  obs, next_obs = np.asarray(mixed.obs), np.asarray(mixed.next_obs)
  changed = np.any(obs != np.asarray(batch.obs), axis=(1, 2, 3))
  np.testing.assert_array_equal(changed, np.arange(BATCH) < n)
  np.testing.assert_array_equal(obs == 0, next_obs == 0)


def _lam_grad(agent, batch, aug, key):
  """Gradient w.r.t. the encoder of the λ term as `critic_loss` computes it."""
  mixed, z_obs = losses.augment_and_mix(key, batch, aug, CONFIG.beta)
  def lam_term(encoder_params):
    params = {"encoder": encoder_params, "critic": agent.params["critic"]}
    return losses.critic_loss(params, agent, batch, mixed, z_obs, key, CONFIG)[1]["lam_loss"]
  return jax.grad(lam_term)(agent.params["encoder"]), z_obs


def test_lambda_gradient_flows_only_through_the_augmented_pass(agent, batch):
  encoder, params = agent.networks.encoder, agent.params["encoder"]
  grad, z_obs = _lam_grad(agent, batch, augment.get("drq"), jax.random.key(2))
  clean = jnp.asarray(_encode(agent, batch.obs), jnp.float32)  # held constant

  def reference(p, both_passes=False):
    anchor = encoder.apply(p, batch.obs) if both_passes else clean
    return 0.1 * jnp.mean(jnp.sum((anchor - encoder.apply(p, z_obs)) ** 2, -1))

  want = jax.grad(reference)(params)
  _assert_tree(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-6),
               grad, want)
  # The check can tell: letting the gradient through e(o) too gives another one.
  both = jax.grad(functools.partial(reference, both_passes=True))(params)
  assert not np.allclose(np.asarray(both["params"]["fc"]["kernel"]),
                         np.asarray(want["params"]["fc"]["kernel"]), rtol=1e-2)

  # With the identity as augmentation the λ term and its gradient vanish: e(o) and
  # e(aug(o)) are then the same features up to float32 rounding (XLA may compute the
  # two passes with different blockings), so the gradient is rounding-sized against
  # the augmented one's.
  none, _ = _lam_grad(agent, batch, augment.get("none"), jax.random.key(2))
  for leaf, drq in zip(jax.tree_util.tree_leaves(none), jax.tree_util.tree_leaves(grad)):
    assert np.abs(np.asarray(leaf)).max() <= 1e-5 * np.abs(np.asarray(drq)).max()


def test_actor_loss_gradient_never_reaches_the_encoder(agent, batch):
  def loss_of(encoder_params, log_alpha):
    other = agent.replace(params={**agent.params, "encoder": encoder_params},
                          log_alpha=log_alpha)
    return losses.actor_loss(agent.params["actor"], other, batch.obs, jax.random.key(4))[0]
  grads = jax.grad(loss_of, argnums=(0, 1))(agent.params["encoder"], agent.log_alpha)
  for leaf in jax.tree_util.tree_leaves(grads):  # features and α are constants
    assert not np.any(np.asarray(leaf))
  # ... while the actor's own gradient is not zero.
  actor_grad = jax.grad(lambda p: losses.actor_loss(p, agent, batch.obs,
                                                 jax.random.key(4))[0])(agent.params["actor"])
  assert any(np.any(np.asarray(g)) for g in jax.tree_util.tree_leaves(actor_grad))


# --------------------------------------------------------------------------- #
# Jitted and vmapped updates.
# --------------------------------------------------------------------------- #

_traces = []  # the config of every trace of `update_pair`


def _counted_update_pair(agent, batches, key, config):
  _traces.append(config)
  return sac.update_pair(agent, batches, key, config)


update_pair = jax.jit(_counted_update_pair, static_argnames="config")


def test_update_pair_jitted_changes_params_and_compiles_once(agent):
  batches = make_batch(1, leading=(2,))
  new, metrics = update_pair(agent, batches, jax.random.key(0), CONFIG)
  assert int(new.step) == 2
  assert set(metrics) == {"critic_loss", "lam_loss", "q", "alpha", "actor_loss",
                          "alpha_loss", "entropy"}
  assert all(np.isfinite(float(v)) for v in metrics.values())
  for group in ("encoder", "critic", "actor"):
    for old, now in zip(jax.tree_util.tree_leaves(agent.params[group]),
                        jax.tree_util.tree_leaves(new.params[group])):
      assert not np.array_equal(old, now), group
  for group in ("encoder", "critic"):
    for old, now in zip(jax.tree_util.tree_leaves(agent.target_params[group]),
                        jax.tree_util.tree_leaves(new.target_params[group])):
      assert not np.array_equal(old, now), group
  assert float(new.log_alpha) != float(agent.log_alpha)

  update_pair(new, make_batch(2, leading=(2,)), jax.random.key(1), CONFIG)
  assert _traces.count(CONFIG) == 1


update = jax.jit(sac.update, static_argnames=("config", "update_actor"))


def test_actor_step_moves_only_actor_alpha_and_targets(agent):
  # The key is split the same way with and without the actor step, so the
  # encoder and critic must come out identical: the actor step leaves them alone.
  batch = make_batch(3)
  full, metrics = update(agent, batch, jax.random.key(9), CONFIG, update_actor=True)
  critic_only, critic_metrics = update(agent, batch, jax.random.key(9), CONFIG,
                                       update_actor=False)
  for group in ("encoder", "critic"):
    _assert_tree(_assert_same_computation, full.params[group], critic_only.params[group])
  assert set(critic_metrics) == {"critic_loss", "lam_loss", "q", "alpha"}
  _assert_same_computation(metrics["critic_loss"], critic_metrics["critic_loss"])
  _assert_tree(np.testing.assert_array_equal, critic_only.params["actor"],
               agent.params["actor"])
  _assert_tree(np.testing.assert_array_equal, critic_only.target_params,
               agent.target_params)
  assert float(critic_only.log_alpha) == float(agent.log_alpha)
  assert float(full.log_alpha) != float(agent.log_alpha)
  assert int(full.step) == int(critic_only.step) == 1


def test_update_pair_scans(agent):
  # lax.scan over pairs: the state's types are stable, and scanning equals a loop.
  batches = jax.tree_util.tree_map(lambda *x: jnp.stack(x), make_batch(6, leading=(2,)),
                                   make_batch(7, leading=(2,)))
  keys = jax.random.split(jax.random.key(5), 2)
  scan = jax.jit(lambda a, b, k: jax.lax.scan(
      lambda carry, xs: sac.update_pair(carry, *xs, CONFIG), a, (b, k)))
  scanned, metrics = scan(agent, batches, keys)
  assert metrics["actor_loss"].shape == (2,) and int(scanned.step) == 4
  looped = agent
  for i in range(2):
    looped, _ = update_pair(looped, jax.tree_util.tree_map(lambda x: x[i], batches),
                            keys[i], CONFIG)
  _assert_tree(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5),
               scanned.params, looped.params)


@pytest.mark.slow
def test_update_pair_vmaps_over_agents():
  agents = jax.tree_util.tree_map(
      lambda *x: jnp.stack(x),
      *(init_agent(jax.random.key(k), OBS_SHAPE, ACTION_SIZE, CONFIG) for k in (3, 4)))
  batches = jax.tree_util.tree_map(lambda *x: jnp.stack(x),
                                   make_batch(4, leading=(2,)), make_batch(5, leading=(2,)))
  step_keys = jax.random.split(jax.random.key(4), 2)
  vmapped = jax.jit(jax.vmap(functools.partial(sac.update_pair, config=CONFIG)))
  new, metrics = vmapped(agents, batches, step_keys)
  assert metrics["critic_loss"].shape == (2,)
  np.testing.assert_array_equal(new.step, [2, 2])
  for k in range(2):
    pick = lambda tree, k=k: jax.tree_util.tree_map(lambda x: x[k], tree)
    alone, alone_metrics = update_pair(pick(agents), pick(batches), step_keys[k], CONFIG)
    _assert_tree(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5),
                 pick(new.params), alone.params)
    np.testing.assert_allclose(metrics["critic_loss"][k], alone_metrics["critic_loss"],
                               rtol=1e-4)


@pytest.mark.slow
def test_agents_with_different_augmentations_vmap_together():
  # aug="drq,cj+drq": the agent with aug_index i trains exactly as one configured
  # with that augmentation alone, also when vmapped beside an agent using the other.
  both = dataclasses.replace(CONFIG, aug="drq,cj+drq")
  agents = jax.tree_util.tree_map(
      lambda *x: jnp.stack(x),
      *(init_agent(jax.random.key(3), OBS_SHAPE, ACTION_SIZE, both, i) for i in (0, 1)))
  np.testing.assert_array_equal(agents.aug_index, [0, 1])
  batches = jax.tree_util.tree_map(lambda *x: jnp.stack(x),
                                   make_batch(4, leading=(2,)), make_batch(5, leading=(2,)))
  keys = jax.random.split(jax.random.key(4), 2)
  new, _ = jax.jit(jax.vmap(functools.partial(sac.update_pair, config=both)))(
      agents, batches, keys)
  for k, name in enumerate(("drq", "cj+drq")):
    pick = lambda tree, k=k: jax.tree_util.tree_map(lambda x: x[k], tree)
    single = dataclasses.replace(CONFIG, aug=name)  # "drq": CONFIG, compiled already
    alone, _ = update_pair(init_agent(jax.random.key(3), OBS_SHAPE, ACTION_SIZE, single),
                           pick(batches), keys[k], single)
    _assert_tree(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5),
                 pick(new.params), alone.params)
  with pytest.raises(ValueError, match="distinct"):
    sac.SACConfig(aug="drq,drq")


@pytest.mark.slow
def test_bfloat16_compute_stays_close_to_float32(agent, batch):
  half = dataclasses.replace(CONFIG, compute_dtype="bfloat16")
  nets32, nets16 = sac.make_networks(ACTION_SIZE, CONFIG), sac.make_networks(ACTION_SIZE, half)
  f32 = nets32.encoder.apply(agent.params["encoder"], batch.obs)
  f16 = nets16.encoder.apply(agent.params["encoder"], batch.obs)
  assert f16.dtype == jnp.float32  # features, Q-values and log-probs stay float32
  np.testing.assert_allclose(f16, f32, atol=0.05)
  q32 = nets32.critic.apply(agent.params["critic"], f32, batch.action)
  q16 = nets16.critic.apply(agent.params["critic"], f32, batch.action)
  assert q16[0].dtype == jnp.float32
  np.testing.assert_allclose(q16, q32, atol=0.05)
  new, metrics = jax.jit(functools.partial(sac.update, config=half, update_actor=True))(
      agent.replace(networks=nets16), batch, jax.random.key(0))
  assert all(np.isfinite(float(v)) for v in metrics.values())
  assert all(x.dtype == jnp.float32 for x in jax.tree_util.tree_leaves(new.params))
  with pytest.raises(ValueError, match="float32, bfloat16"):
    sac.SACConfig(compute_dtype="float16")


PIXEL_CUE_PAIRS = 100
"""`update_pair` calls of the pixel-cue tests (here and in test_aux_losses): each
learner reads the cue well before (its score passes 0.9 within 75 pairs)."""


@pytest.mark.slow
def test_learns_to_read_a_pixel_cue():
  # A one-step task from pixels: a bright patch in the left or right half of a
  # 16×16×9 image says which sign of the action pays (reward = ±action, discount
  # 0). A random policy earns 0 on average; 200 SAC+AUG updates (DrQ shifts, β
  # mixing, λ term) must read the cue from the pixels.
  config = dataclasses.replace(CONFIG, batch_size=64, lam=1e-5, init_alpha=0.01,
                               critic_lr=3e-3, encoder_lr=3e-3, actor_lr=3e-3)
  action_size = 1

  def images(side):  # side: (B,) in {0, 1}
    cols = jnp.arange(16)
    left = (cols >= 2) & (cols < 6)
    right = (cols >= 10) & (cols < 14)
    mask = jnp.where(side[:, None], right[None], left[None])          # (B, 16)
    rows = (jnp.arange(16) >= 5) & (jnp.arange(16) < 11)
    patch = rows[None, :, None] & mask[:, None, :]                     # (B, 16, 16)
    return jnp.broadcast_to(jnp.where(patch, 230, 20)[..., None],
                            (*patch.shape, 9)).astype(jnp.uint8)

  def make(key):
    k_side, k_action = jax.random.split(key)
    side = jax.random.bernoulli(k_side, 0.5, (64,))
    obs = images(side)
    action = jax.random.uniform(k_action, (64, action_size), minval=-1, maxval=1)
    reward = jnp.where(side, 1.0, -1.0) * action[:, 0]
    return sac.Batch(obs=obs, action=action, reward=reward,
                     discount=jnp.zeros((64,)), next_obs=obs)

  # Its run, not its compilation, dominates: compiled with LLVM's optimisations.
  @functools.partial(jax.jit, compiler_options=run_faster())
  def train(agent, key):
    def body(agent, k):
      k_batch, k_update = jax.random.split(k)
      batches = jax.vmap(make)(jax.random.split(k_batch, 2))
      return sac.update_pair(agent, batches, k_update, config)
    return jax.lax.scan(body, agent, jax.random.split(key, PIXEL_CUE_PAIRS))[0]

  agent = sac.init_agent(jax.random.key(0), OBS_SHAPE, action_size, config)
  test = make(jax.random.key(123))
  side_sign = jnp.sign(test.reward / test.action[:, 0])
  score = lambda a: float(jnp.mean(side_sign * sac.act(a, test.obs, None,
                                                        deterministic=True)[:, 0]))
  before = score(agent)
  agent = train(agent, jax.random.key(1))
  after = score(agent)
  assert int(agent.step) == 2 * PIXEL_CUE_PAIRS
  assert after > 0.8 and after > before + 0.5, (before, after)


# --------------------------------------------------------------------------- #
# Configuration.
# --------------------------------------------------------------------------- #


def test_config_defaults_and_validation():
  config = sac.SACConfig()
  assert (config.batch_size, config.gamma, config.alpha_lr, config.init_alpha,
          config.encoder_tau, config.critic_tau, config.beta, config.lam,
          config.aug) == (256, 0.99, 1e-4, 0.1, 0.05, 0.01, 0.9, 1e-5, "drq")
  assert config.entropy_target(6) == -6.0
  with pytest.raises(ValueError, match="valid names: .*drq"):
    sac.SACConfig(aug="drqq")
  sac.SACConfig(aug="cj+drq")
  for bad in ({"beta": 1.5}, {"batch_size": 0}, {"critic_tau": 0.0},
              {"log_std_min": 3.0}, {"update_delay": 2}, {"stage_inputs": False}):
    with pytest.raises((ValueError, TypeError)):
      sac.SACConfig(**bad)
  with pytest.raises(ValueError, match="leading axis of 2"):
    sac.update_pair(None, make_batch(0, leading=(3,)), None, CONFIG)


def test_config_from_dict_reads_a_written_config_and_drops_retired_fields():
  config = dataclasses.replace(CONFIG, aug="drq,cj+drq", compute_dtype="bfloat16")
  fields = dataclasses.asdict(config)
  assert sac.SACConfig.from_dict(fields) == config
  # A config.json written when these were fields still loads, if it asks for what
  # the learner computes.
  old = {**fields, "stage_inputs": True, "update_delay": 2}
  assert sac.SACConfig.from_dict(old) == config
  with pytest.raises(ValueError, match="update_delay = 3 is not supported"):
    sac.SACConfig.from_dict({**fields, "update_delay": 3})
  with pytest.raises(TypeError):
    sac.SACConfig.from_dict({**fields, "no_such_field": 1})
