"""The losses of the DMCR paper's SAC+AUG learner (Sec. 3.2, appendix), and the β
mixing of augmented rows that feeds them, as pure functions of parameters and one
batch; `dmcr_jax.train.sac.update` differentiates them and steps the optimizers.
They take uint8 observations (how the encoder computes on them is
`dmcr_jax.train.networks.Encoder`'s affair). For a batch of B transitions
(o, a, r, d, o′):

- β mixing (`augment_and_mix`): z is the augmentation (`dmcr_jax.augment.get(aug)`,
  one draw per sample shared by o, o′ and the frames of the stack). The first
  n = ⌊β·B⌋ rows of o and o′ are replaced by z(o), z(o′); the rest stay as they are.
  This mixed batch (ô, a, r, d, ô′) serves the critic and the actor.
- Critic (`critic_loss`, `td_target`; both heads, sum of their mean squared errors):
  y = sg(r + γ·d·(min_i Q′_i(e′(ô′), a′) − α·log π(a′|sg e(ô′)))), a′ ~ π(·|sg e(ô′)),
  L_critic = mean_b (Q_1(e(ô), a) − y)² + mean_b (Q_2(e(ô), a) − y)²,
  with e, Q the online encoder and critic, e′, Q′ their targets, α = exp(log α).
- Encoder (`critic_loss`): L_encoder = L_critic + L_λ,
  L_λ = λ · mean_b Σ_f (sg(e(o_b)) − e(z(o_b)))_f², over all B rows, gradient
  only through the augmented pass e(z(o)) as the paper's text says (DESIGN.md
  puts the stop-gradient on the other side; the paper's text is followed). The
  encoder and critic take one Adam step on L_encoder; in SAC+AUG no other loss
  reaches the encoder.
- Actor (`actor_loss`): ã ~ π(·|sg e(ô)) reparameterised,
  L_actor = mean_b (sg(α)·log π(ã|·) − min_i Q_i(sg e(ô), ã)); only the actor's
  parameters move.
- Temperature (`alpha_loss`): L_α = mean_b (−α·(sg(log π(ã|·)) + H̄)), H̄ = −|A|
  by default, optimised over log α.
- Targets (`soft_update_targets`, Polyak): e′ ← (1 − τ_e)·e′ + τ_e·e with
  τ_e = .05, Q′ ← (1 − τ_Q)·Q′ + τ_Q·Q with τ_Q = .01, after every actor update.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import optax

from dmcr_jax import augment
from dmcr_jax.train.networks import Actor
from dmcr_jax.train.replay import Batch
from dmcr_jax.train.sac_config import SACConfig

if TYPE_CHECKING:
  from dmcr_jax.train.sac import AgentState

Params = Any
Metrics = dict[str, jax.Array]


# --------------------------------------------------------------------------- #
# Augmentation and β mixing.
# --------------------------------------------------------------------------- #


def num_augmented(batch_size: int, beta: float) -> int:
  """n = ⌊β·B⌋, the number of leading rows of a batch that are augmented.

  Args:
    batch_size: B.
    beta: β in [0, 1].

  Returns:
    A Python int in [0, B] (a tiny tolerance keeps e.g. ⌊.29·100⌋ = 29).
  """
  return min(batch_size, max(0, math.floor(beta * batch_size + 1e-9)))


def agent_augmentation(agent: AgentState, config: SACConfig):
  """The augmentation `agent` trains with: ``aug(key, tree) -> tree``.

  With one name in `config.aug` that augmentation; with several, a
  `jax.lax.switch` on `agent.aug_index` (under vmap over agents with different
  indices every listed augmentation is computed and the agent's selected).

  Args:
    agent: the agent (its `aug_index`).
    config: the hyperparameters (`aug`).

  Returns:
    A function like `dmcr_jax.augment.get`'s.
  """
  fns = [augment.get(name) for name in config.aug_names]
  if len(fns) == 1:
    return fns[0]
  index = jnp.clip(agent.aug_index, 0, len(fns) - 1)
  return lambda key, tree: jax.lax.switch(index, fns, key, tree)


def augment_and_mix(key: jax.Array, batch: Batch, aug, beta: float
                    ) -> tuple[Batch, jax.Array]:
  """Augments o and o′ with one draw per sample and mixes the first ⌊β·B⌋ rows in.

  Args:
    key: a `jax.random` key for the augmentation.
    batch: the batch from the replay buffer.
    aug: ``aug(key, (obs, next_obs)) -> (z_obs, z_next_obs)``, e.g.
      ``dmcr_jax.augment.get("drq")``; it must give a sample's o and o′ the same
      draw (the augment module does).
    beta: β in [0, 1].

  Returns:
    (mixed, z_obs): `batch` whose obs and next_obs have their first ⌊β·B⌋ rows
    replaced by the augmented ones, and z(o) for all B rows (for the λ term).
  """
  z_obs, z_next_obs = aug(key, (batch.obs, batch.next_obs))
  n = num_augmented(batch.obs.shape[0], beta)
  mix = lambda z, x: jnp.concatenate([z[:n], x[n:]], axis=0)
  return batch._replace(obs=mix(z_obs, batch.obs),
                        next_obs=mix(z_next_obs, batch.next_obs)), z_obs


# --------------------------------------------------------------------------- #
# Losses.
# --------------------------------------------------------------------------- #


def td_target(agent: AgentState, next_obs: jax.Array, reward: jax.Array,
              discount: jax.Array, key: jax.Array, config: SACConfig) -> jax.Array:
  """y = r + γ·d·(min_i Q′_i(e′(o′), a′) − α·log π(a′|sg e(o′))), a′ ~ π(·|sg e(o′)).

  a′ is drawn by the current actor on the online encoder's features of o′; the
  target encoder and target critic give Q′. No gradient flows through y.

  Args:
    agent: the agent (online and target parameters, log α).
    next_obs: uint8 (B, H, W, C), o′ (already mixed).
    reward: (B,).
    discount: (B,).
    key: a `jax.random` key for a′.
    config: the hyperparameters (γ).

  Returns:
    float32 (B,).
  """
  nets, params, targets = agent.networks, agent.params, agent.target_params
  features = nets.encoder.apply(params["encoder"], next_obs)
  next_action, next_log_prob = nets.actor.apply(params["actor"], features, key,
                                                method=Actor.sample)
  target_features = nets.encoder.apply(targets["encoder"], next_obs)
  q1, q2 = nets.critic.apply(targets["critic"], target_features, next_action)
  alpha = jnp.exp(agent.log_alpha)
  soft_value = jnp.minimum(q1, q2) - alpha * next_log_prob
  return jax.lax.stop_gradient(reward + config.gamma * discount * soft_value)


def critic_loss(critic_params: Params, agent: AgentState, batch: Batch, mixed: Batch,
                z_obs: jax.Array, key: jax.Array, config: SACConfig
                ) -> tuple[jax.Array, Metrics]:
  """L_encoder = L_critic + L_λ, a function of ``{"encoder", "critic"}`` (module doc).

  L_critic = mean_b (Q_1 − y)² + mean_b (Q_2 − y)² on the mixed batch;
  L_λ = λ · mean_b Σ_f (sg(e(o_b)) − e(z(o_b)))_f² over all B rows, with the
  gradient only through e(z(o)) (paper Sec. 3.2). The encoder pass on the mixed
  batch already holds e(z(o)) for rows < n and e(o) for rows ≥ n, so only the
  missing rows are encoded again.

  Args:
    critic_params: ``{"encoder": …, "critic": …}``, the differentiated parameters.
    agent: the agent (targets, actor, log α; its encoder/critic are not used here
      except for drawing a′ in `td_target`).
    batch: the un-augmented batch.
    mixed: `augment_and_mix`'s mixed batch for `batch`.
    z_obs: `augment_and_mix`'s z(o), all B rows.
    key: a `jax.random` key for a′ in the target.
    config: the hyperparameters (β, λ, γ).

  Returns:
    (L_encoder, metrics with "critic_loss" (L_critic), "lam_loss" (L_λ) and "q"
    (mean of both heads' Q on the batch)).
  """
  encoder, critic = agent.networks.encoder, agent.networks.critic
  size = batch.obs.shape[0]
  n = num_augmented(size, config.beta)
  y = td_target(agent, mixed.next_obs, mixed.reward, mixed.discount, key, config)
  if config.lam > 0:
    # One pass with gradient over the mixed batch and the z(o) rows it lacks.
    # (Empty pieces are left out statically: n is a Python int.)
    cat = lambda parts: jnp.concatenate([x for x in parts if x.shape[0]], axis=0)
    all_features = encoder.apply(critic_params["encoder"], cat([mixed.obs, z_obs[n:]]))
    features = all_features[:size]
    z_features = cat([all_features[:n], all_features[size:]])
    # e(o) is a constant (the paper: "only let gradients flow through the
    # e(z(o)) pass"; DESIGN.md's formula puts the sg on the wrong side).
    frozen_encoder = jax.lax.stop_gradient(critic_params["encoder"])
    clean_head = [encoder.apply(frozen_encoder, batch.obs[:n])] if n else []
    clean = cat(clean_head + [features[n:]])
    diff = jax.lax.stop_gradient(clean) - z_features
    lam_loss = config.lam * jnp.mean(jnp.sum(jnp.square(diff), axis=-1))
  else:
    features = encoder.apply(critic_params["encoder"], mixed.obs)
    lam_loss = jnp.zeros((), jnp.float32)
  q1, q2 = critic.apply(critic_params["critic"], features, mixed.action)
  td_loss = jnp.mean(jnp.square(q1 - y)) + jnp.mean(jnp.square(q2 - y))
  metrics = {"critic_loss": td_loss, "lam_loss": lam_loss,
             "q": 0.5 * (jnp.mean(q1) + jnp.mean(q2))}
  return td_loss + lam_loss, metrics


def actor_loss(actor_params: Params, agent: AgentState, obs: jax.Array,
               key: jax.Array) -> tuple[jax.Array, jax.Array]:
  """L_actor = mean_b (sg(α)·log π(ã|f) − min_i Q_i(f, ã)), f = sg(e(o)), ã ~ π(·|f).

  Gradients reach only `actor_params`: the features and α are constants, and the
  critic's parameters come from `agent` (not differentiated).

  Args:
    actor_params: the differentiated actor parameters.
    agent: the agent (encoder, critic, log α).
    obs: uint8 (B, H, W, C), the mixed observations.
    key: a `jax.random` key for ã.

  Returns:
    (L_actor, log π(ã|f) of shape (B,)).
  """
  nets, params = agent.networks, agent.params
  features = jax.lax.stop_gradient(nets.encoder.apply(params["encoder"], obs))
  action, log_prob = nets.actor.apply(actor_params, features, key, method=Actor.sample)
  q1, q2 = nets.critic.apply(params["critic"], features, action)
  alpha = jax.lax.stop_gradient(jnp.exp(agent.log_alpha))
  return jnp.mean(alpha * log_prob - jnp.minimum(q1, q2)), log_prob


def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array,
               target_entropy: float) -> jax.Array:
  """L_α = mean_b (−exp(log α)·(sg(log π_b) + H̄)), a function of log α.

  Args:
    log_alpha: scalar, the differentiated log temperature.
    log_prob: (B,), log π of the actor's samples (treated as constants).
    target_entropy: H̄.

  Returns:
    A scalar.
  """
  log_prob = jax.lax.stop_gradient(log_prob)
  return jnp.mean(-jnp.exp(log_alpha) * (log_prob + target_entropy))


def soft_update_targets(agent: AgentState, config: SACConfig) -> AgentState:
  """Polyak averaging: θ′ ← (1 − τ)·θ′ + τ·θ, τ_e for the encoder, τ_Q for the critic.

  Args:
    agent: the agent.
    config: the hyperparameters (`encoder_tau`, `critic_tau`).

  Returns:
    The agent with new `target_params`.
  """
  params, targets = agent.params, agent.target_params
  return agent.replace(target_params={
      "encoder": optax.incremental_update(params["encoder"], targets["encoder"],
                                          config.encoder_tau),
      "critic": optax.incremental_update(params["critic"], targets["critic"],
                                         config.critic_tau)})
