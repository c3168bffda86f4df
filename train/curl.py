"""CURL's auxiliary task (Srinivas, Laskin & Abbeel 2020) as pure JAX functions.

CURL renders observations larger than the encoder's input (100 px for 84) and
draws independent random crops: the anchor o_a and o′ for the critic, and a
positive o_p of the same observation. Its contrastive loss is InfoNCE with a
bilinear similarity: with q = e(o_a) (online encoder, gradient) and
k = sg(e′(o_p)) (the momentum encoder: the target encoder, Polyak-averaged with
τ_e), the logits are ``q W kᵀ`` (B × B) minus each row's maximum, and the loss
is the cross entropy with labels 0 … B − 1: each anchor's positive is its own
row's key, the other B − 1 keys are its negatives. W (F × F) is learned with the
encoder; the momentum encoder gets no gradient. At acting and evaluation time
the observation is center-cropped (`networks.Encoder.input_size`).

The auxiliary task's interface, shared with `dmcr_jax.train.sac_ae`: `PARTNER` (the
parameters trained beside the encoder), `init_partner`, `optimizer` and
`aux_loss`. The update order (critic, then actor, α and targets every
second update, then the contrastive step every update) and the wiring
into the learner are in `dmcr_jax.train.sac`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

PARTNER = "curl"
"""The key of CURL's parameters (``{"w": W}``) in the agent's params."""


def random_crop(key: jax.Array, images: jax.Array, size: int) -> jax.Array:
  """One uniformly random size × size window per image, the same for all its frames.

  Args:
    key: a `jax.random` key.
    images: (B, H, W, C) with H, W ≥ size.
    size: the output side.

  Returns:
    (B, size, size, C); sample b's window starts at (top_b, left_b), uniform
    over [0, H − size] × [0, W − size] (CURL's `random_crop`).
  """
  b, h, w, c = images.shape
  if h < size or w < size:
    raise ValueError(f"cannot crop {h}×{w} images to {size}×{size}")
  k_top, k_left = jax.random.split(key)
  tops = jax.random.randint(k_top, (b,), 0, h - size + 1)
  lefts = jax.random.randint(k_left, (b,), 0, w - size + 1)
  crop = lambda image, top, left: jax.lax.dynamic_slice(image, (top, left, 0),
                                                        (size, size, c))
  return jax.vmap(crop)(images, tops, lefts)


def crops(key: jax.Array, obs: jax.Array, next_obs: jax.Array, size: int
          ) -> tuple[jax.Array, jax.Array, jax.Array]:
  """CURL's three independent crops of a batch: (anchor o, o′, positive of o).

  Args:
    key: a `jax.random` key.
    obs: uint8 (B, H, W, C), o.
    next_obs: uint8 (B, H, W, C), o′.
    size: the crop side (the encoder's input, 84).

  Returns:
    (anchor, next, positive), each uint8 (B, size, size, C).
  """
  k_anchor, k_next, k_positive = jax.random.split(key, 3)
  return (random_crop(k_anchor, obs, size), random_crop(k_next, next_obs, size),
          random_crop(k_positive, obs, size))


def logits(queries: jax.Array, keys: jax.Array, w: jax.Array) -> jax.Array:
  """CURL's bilinear logits: q W kᵀ, minus each row's maximum (for stability).

  Args:
    queries: (B, F), the anchors' features.
    keys: (B, F), the positives' momentum-encoder features.
    w: (F, F), the bilinear matrix.

  Returns:
    float32 (B, B); entry (i, j) scores anchor i against key j.
  """
  scores = queries @ (w @ keys.T)
  return scores - jnp.max(scores, axis=1, keepdims=True)


def info_nce(queries: jax.Array, keys: jax.Array, w: jax.Array) -> jax.Array:
  """The InfoNCE loss: mean over rows of the cross entropy of `logits` with labels 0 … B − 1."""
  row_logits = logits(queries, keys, w)
  labels = jnp.arange(row_logits.shape[0])
  return jnp.mean(optax.softmax_cross_entropy_with_integer_labels(row_logits, labels))


def init_w(key: jax.Array, feature_dim: int) -> jax.Array:
  """W's initial value: uniform in [0, 1), as CURL's ``torch.rand``."""
  return jax.random.uniform(key, (feature_dim, feature_dim), jnp.float32)


def init_partner(key: jax.Array, networks, features: jax.Array, config) -> dict:
  """``{"w": W}``, W from `init_w` (`networks` and `features` are unused: W's
  shape is `config.feature_dim` squared)."""
  del networks, features
  return {"w": init_w(key, config.feature_dim)}


def optimizer(config) -> optax.GradientTransformation:
  """Adam(`config.encoder_lr`) over ``{"encoder", "curl"}``. (CURL's code steps the
  encoder with two Adam optimizers on the same contrastive gradient, its
  `encoder_optimizer` and `cpc_optimizer`; here it takes one step.)"""
  return optax.adam(config.encoder_lr)


def aux_loss(aux_params, agent, obs: jax.Array, aux_input: jax.Array, key: jax.Array,
             config) -> tuple[jax.Array, dict[str, jax.Array]]:
  """CURL's InfoNCE loss, a function of ``{"encoder", "curl"}``.

  Queries are the online encoder's features of the anchors (gradient), keys the
  target (momentum) encoder's features of the positives (no gradient).

  Args:
    aux_params: ``{"encoder": …, "curl": {"w": W}}``, the differentiated parameters.
    agent: the `dmcr_jax.train.sac.AgentState` (its encoder module and target encoder).
    obs: uint8 (B, S, S, C), the anchor crops (also the critic's o).
    aux_input: uint8 (B, S, S, C), the positives: independent crops of the same
      observations.
    key, config: unused (the signature shared with `dmcr_jax.train.sac_ae.aux_loss`).

  Returns:
    (loss, {"aux_loss": loss}).
  """
  del key, config
  encoder = agent.networks.encoder
  queries = encoder.apply(aux_params["encoder"], obs)
  keys = jax.lax.stop_gradient(encoder.apply(agent.target_params["encoder"], aux_input))
  loss = info_nce(queries, keys, aux_params[PARTNER]["w"])
  return loss, {"aux_loss": loss}
