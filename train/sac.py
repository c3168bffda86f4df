"""SAC+AUG, the DMCR paper's learner (Sec. 3.2, appendix, Table 6), as pure JAX
functions; with `SACConfig.algo` (`dmcr_jax.train.sac_config`, re-exported here),
also its baselines CURL and SAC+AE on the same SAC. One immutable `AgentState`
(parameters, targets, log α, Adam states); `init_agent`; `act`; the optimizers;
and `update`, pure and jittable with ``update_actor`` static, which takes one Adam
step on each loss of `dmcr_jax.train.losses` (whose docstring gives them): the
encoder and critic on L_encoder = L_critic + L_λ first, then, with
``update_actor``, the actor on L_actor with the updated encoder and critic (as
SAC-AE, CURL and DrQ do), then log α on L_α, then the Polyak targets.
`update_pair` is a critic-only update then a full one, the paper's "actor and
target updates every 2 steps" (a fixed part of the algorithm here), so `jax.vmap`
over K agents and `jax.lax.scan` over pairs stay cheap. CURL (``algo="curl"``,
`dmcr_jax.train.curl`): instead of β mixing, every row of o and o′ is a random
crop of the larger rendered observation (anchor, o′), the SAC losses run on them
(λ = 0), and after the targets one more Adam step on the encoder and the bilinear
W minimises InfoNCE between the anchors (online encoder) and independent positive
crops (target encoder, no gradient). SAC+AE (``algo="sac_ae"``,
`dmcr_jax.train.sac_ae`): the SAC losses on the (un-augmented by default) batch,
then one Adam step on the encoder and the decoder on the reconstruction loss.
Both auxiliary steps run every update, as in the original code, with their own
Adam states (`aux_optimizer`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import optax

from dmcr_jax.train import curl, losses, sac_ae
from dmcr_jax.train.losses import Metrics, Params
from dmcr_jax.train.networks import Actor, Critic, Decoder, Encoder, encoder_sides
from dmcr_jax.train.replay import Batch  # what `replay.sample` returns and `update` consumes
from dmcr_jax.train.sac_config import (  # noqa: F401 (re-exported: sac.SACConfig, sac.ALGOS, …)
    ALGO_DEFAULTS, ALGOS, COMPUTE_DTYPES, DROPPED_FIELDS, SACConfig, is_int)

AUX_TASKS = {"curl": curl, "sac_ae": sac_ae}
"""The auxiliary task of each learner that has one: a module with `PARTNER`,
`init_partner`, `optimizer` and `aux_loss(aux_params, agent, obs, aux_input, key,
config)`."""


# --------------------------------------------------------------------------- #
# State and batches.
# --------------------------------------------------------------------------- #


class Networks(NamedTuple):
  """The flax modules of an agent (static: they hold no parameters)."""
  encoder: Encoder
  actor: Actor
  critic: Critic
  decoder: Decoder | None = None  # SAC+AE only


def make_networks(action_size: int, config: SACConfig,
                  obs_shape: tuple[int, int, int] | None = None) -> Networks:
  """Builds the encoder, actor and twin critic (and SAC+AE's decoder) for `config`.

  Args:
    action_size: |A|.
    config: the hyperparameters (algorithm, widths and log-std range are read).
    obs_shape: (H, W, C) of one observation; needed for SAC+AE's decoder.

  Returns:
    A `Networks` (paper Table 6). For CURL the encoder center-crops inputs larger
    than `config.curl_crop`.
  """
  dtype = config.compute_dtype
  decoder = None
  if config.algo == "sac_ae":
    if obs_shape is None:
      raise ValueError("make_networks needs obs_shape for SAC+AE's decoder")
    decoder = Decoder(side=obs_shape[0], out_channels=obs_shape[2],
                      channels=config.conv_channels, dtype=dtype)
  return Networks(
      encoder=Encoder(channels=config.conv_channels, feature_dim=config.feature_dim,
                      dtype=dtype,
                      input_size=config.curl_crop if config.algo == "curl" else None),
      actor=Actor(action_size=action_size, hidden_dim=config.hidden_dim,
                  log_std_min=config.log_std_min, log_std_max=config.log_std_max,
                  dtype=dtype),
      critic=Critic(hidden_dim=config.hidden_dim, dtype=dtype),
      decoder=decoder)


@flax.struct.dataclass
class AgentState:
  """Everything one SAC+AUG agent learns: an immutable pytree (vmap it for K agents).

  Attributes:
    params: ``{"encoder", "critic", "actor"}`` flax parameter trees, and
      ``"curl"`` (``{"w": W}``) for CURL or ``"decoder"`` for SAC+AE.
    log_alpha: float32 scalar, log of the temperature α.
    target_params: ``{"encoder", "critic"}``, Polyak averages of the online ones.
    critic_opt_state: the one Adam state over ``{"encoder", "critic"}``.
    actor_opt_state: Adam state of the actor.
    alpha_opt_state: Adam state of log α.
    aux_opt_state: Adam state of the auxiliary step over ``{"encoder", "curl"}``
      (CURL) or ``{"encoder", "decoder"}`` (SAC+AE); None for SAC+AUG.
    step: int32, the number of critic updates done.
    aug_index: int32, which of `SACConfig.aug_names` this agent trains with.
    networks: the modules (static, not a pytree node).
  """
  params: dict[str, Params]
  log_alpha: jax.Array
  target_params: dict[str, Params]
  critic_opt_state: optax.OptState
  actor_opt_state: optax.OptState
  alpha_opt_state: optax.OptState
  aux_opt_state: optax.OptState | None
  step: jax.Array
  aug_index: jax.Array
  networks: Networks = flax.struct.field(pytree_node=False)


# --------------------------------------------------------------------------- #
# Optimisers.
# --------------------------------------------------------------------------- #


def critic_optimizer(config: SACConfig) -> optax.GradientTransformation:
  """One Adam over ``{"encoder", "critic"}`` with the two learning rates.

  Adam's moments are elementwise, so one `scale_by_adam` followed by a per-group
  step size is the same as Adam with `encoder_lr` on the encoder and `critic_lr`
  on the critic.

  Args:
    config: the hyperparameters.

  Returns:
    An optax transformation for a ``{"encoder": …, "critic": …}`` tree.
  """
  return optax.chain(
      optax.scale_by_adam(),
      optax.multi_transform({"encoder": optax.scale(-config.encoder_lr),
                             "critic": optax.scale(-config.critic_lr)},
                            {"encoder": "encoder", "critic": "critic"}))


def actor_optimizer(config: SACConfig) -> optax.GradientTransformation:
  """Adam with `config.actor_lr` for the actor's parameters."""
  return optax.adam(config.actor_lr)


def alpha_optimizer(config: SACConfig) -> optax.GradientTransformation:
  """Adam with `config.alpha_lr` for log α."""
  return optax.adam(config.alpha_lr)


def aux_optimizer(config: SACConfig) -> optax.GradientTransformation | None:
  """The auxiliary step's optimizer, its own Adam states as in the original code:
  the auxiliary task's `optimizer` (`dmcr_jax.train.curl`, `dmcr_jax.train.sac_ae`); None for SAC+AUG."""
  task = AUX_TASKS.get(config.algo)
  return None if task is None else task.optimizer(config)


# --------------------------------------------------------------------------- #
# Initialisation and acting.
# --------------------------------------------------------------------------- #



def init_agent(key: jax.Array, obs_shape: tuple[int, int, int], action_size: int,
               config: SACConfig, aug_index: int | jax.Array = 0) -> AgentState:
  """A fresh agent: random networks, targets equal to them, α = `init_alpha`.

  Args:
    key: a `jax.random` key.
    obs_shape: (H, W, 3·stack) of one observation.
    action_size: |A|.
    config: the hyperparameters.
    aug_index: which of `config.aug_names` the agent trains with (may be traced,
      e.g. under vmap).

  Returns:
    An `AgentState` with ``step == 0``.

  Raises:
    ValueError: for a bad `obs_shape` or `action_size`.
  """
  obs_shape = tuple(obs_shape)
  if (len(obs_shape) != 3 or not all(is_int(d) and d > 0 for d in obs_shape)
      or obs_shape[2] % 3):
    raise ValueError(f"obs_shape must be (H, W, 3·stack), got {obs_shape}")
  seen = min(obs_shape[:2])
  if config.algo == "curl":
    if seen < config.curl_crop:
      raise ValueError(f"CURL crops {config.curl_crop}×{config.curl_crop} windows out "
                       f"of the observations, but obs_shape is {obs_shape} (render "
                       f"larger, e.g. image_size = {config.curl_crop + 16})")
    seen = config.curl_crop
  if encoder_sides(seen)[-1] < 1:
    raise ValueError(f"obs_shape {obs_shape} is too small for the encoder's four "
                     f"3×3 VALID convolutions (need H, W ≥ 15)")
  if config.algo == "sac_ae" and obs_shape[0] != obs_shape[1]:
    raise ValueError(f"SAC+AE's decoder reconstructs square images, got {obs_shape}")
  if not is_int(action_size) or action_size < 1:
    raise ValueError(f"action_size must be a positive int, got {action_size!r}")
  networks = make_networks(action_size, config, obs_shape)
  k_encoder, k_actor, k_critic = jax.random.split(key, 3)
  features = jnp.zeros((1, config.feature_dim), jnp.float32)
  encoder = networks.encoder.init(k_encoder, jnp.zeros((1, *obs_shape), jnp.uint8))
  actor = networks.actor.init(k_actor, features)
  critic = networks.critic.init(k_critic, features,
                                jnp.zeros((1, action_size), jnp.float32))
  log_alpha = jnp.asarray(math.log(config.init_alpha), jnp.float32)
  copy = lambda tree: jax.tree_util.tree_map(jnp.array, tree)
  params = {"encoder": encoder, "critic": critic, "actor": actor}
  aux = {}
  if config.algo in AUX_TASKS:
    task = AUX_TASKS[config.algo]
    aux = {task.PARTNER: task.init_partner(jax.random.fold_in(key, 3), networks,
                                           features, config)}
  aux_opt = aux_optimizer(config)
  return AgentState(
      params={**params, **aux},
      log_alpha=log_alpha,
      target_params={"encoder": copy(encoder), "critic": copy(critic)},
      critic_opt_state=critic_optimizer(config).init(
          {"encoder": encoder, "critic": critic}),
      actor_opt_state=actor_optimizer(config).init(actor),
      alpha_opt_state=alpha_optimizer(config).init(log_alpha),
      aux_opt_state=None if aux_opt is None else aux_opt.init({"encoder": encoder, **aux}),
      step=jnp.zeros((), jnp.int32),
      aug_index=jnp.asarray(aug_index, jnp.int32),
      networks=networks)


def act(agent: AgentState, obs: jax.Array, key: jax.Array,
        deterministic: bool = False) -> jax.Array:
  """Actions for a batch of observations (pure; jit with `deterministic` static).

  Args:
    agent: the agent.
    obs: uint8 (B, H, W, 3·stack).
    key: a `jax.random` key (unused when `deterministic`).
    deterministic: if True, tanh(mean) (evaluation); else a policy sample.

  Returns:
    float32 (B, A) in [−1, 1].
  """
  nets, params = agent.networks, agent.params
  features = nets.encoder.apply(params["encoder"], obs)
  if deterministic:
    return nets.actor.apply(params["actor"], features, method=Actor.mode)
  action, _ = nets.actor.apply(params["actor"], features, key, method=Actor.sample)
  return action


# --------------------------------------------------------------------------- #
# Updates.
# --------------------------------------------------------------------------- #


def _check_batch(agent: AgentState, batch: Batch, config: SACConfig):
  obs, next_obs = batch.obs, batch.next_obs
  if obs.dtype != jnp.uint8 or next_obs.dtype != jnp.uint8:
    raise TypeError(f"Batch.obs and Batch.next_obs must be uint8, got {obs.dtype} "
                    f"and {next_obs.dtype}")
  if obs.ndim != 4 or next_obs.shape != obs.shape:
    raise ValueError(f"Batch.obs and Batch.next_obs must share a shape (B, H, W, C), "
                     f"got {obs.shape} and {next_obs.shape}")
  size, action_size = obs.shape[0], agent.networks.actor.action_size
  if size != config.batch_size:
    raise ValueError(f"batch of {size} transitions, but SACConfig.batch_size is "
                     f"{config.batch_size}")
  if batch.action.shape != (size, action_size):
    raise ValueError(f"Batch.action must be (B, A) = {(size, action_size)}, got "
                     f"{batch.action.shape}")
  if batch.reward.shape != (size,) or batch.discount.shape != (size,):
    raise ValueError(f"Batch.reward and Batch.discount must be (B,) = ({size},), got "
                     f"{batch.reward.shape} and {batch.discount.shape}")
  if agent.networks != make_networks(action_size, config, obs.shape[1:]):
    raise ValueError("the agent's networks do not match the config's (algo, "
                     "feature_dim, hidden_dim, conv_channels, log-std range, image size)")


def update(agent: AgentState, batch: Batch, key: jax.Array, config: SACConfig, *,
           update_actor: bool) -> tuple[AgentState, Metrics]:
  """One learner update (pure, jittable; `config` and `update_actor` static).

  Augments and β-mixes the batch (CURL: crops it, `dmcr_jax.train.curl.crops`), takes one
  Adam step of the encoder and critic on L_encoder = L_critic + L_λ; with
  `update_actor`, then one actor step on L_actor (with the new encoder and
  critic), one log α step on L_α, and the Polyak target updates
  (`dmcr_jax.train.losses`); then, for CURL and SAC+AE, one step of their auxiliary loss on the
  encoder and W or the decoder (`aux_step`). The key is split the same way
  either way, so the critic step does not depend on `update_actor`.

  Args:
    agent: the agent.
    batch: B = `config.batch_size` transitions.
    key: a `jax.random` key.
    config: the hyperparameters.
    update_actor: also update the actor, α and the targets.

  Returns:
    (new agent, metrics): scalars "critic_loss", "lam_loss", "q", "alpha"; with
    `update_actor` also "actor_loss", "alpha_loss", "entropy" (−mean log π);
    for CURL and SAC+AE "aux_loss" (and SAC+AE's "reconstruction_loss",
    "latent_loss").
  """
  _check_batch(agent, batch, config)
  aug_key, target_key, actor_key = jax.random.split(key, 3)
  positive = None
  if config.algo == "curl":
    anchor, next_obs, positive = curl.crops(aug_key, batch.obs, batch.next_obs,
                                            config.curl_crop)
    mixed, z_obs = batch._replace(obs=anchor, next_obs=next_obs), None
  else:
    mixed, z_obs = losses.augment_and_mix(
        aug_key, batch, losses.agent_augmentation(agent, config), config.beta)

  critic_params = {"encoder": agent.params["encoder"],
                   "critic": agent.params["critic"]}
  grads, metrics = jax.grad(losses.critic_loss, has_aux=True)(
      critic_params, agent, batch, mixed, z_obs, target_key, config)
  updates, critic_opt_state = critic_optimizer(config).update(
      grads, agent.critic_opt_state, critic_params)
  critic_params = optax.apply_updates(critic_params, updates)
  agent = agent.replace(params={**agent.params, **critic_params},
                        critic_opt_state=critic_opt_state, step=agent.step + 1)

  if update_actor:
    actor_params = agent.params["actor"]
    (loss, log_prob), grads = jax.value_and_grad(losses.actor_loss, has_aux=True)(
        actor_params, agent, mixed.obs, actor_key)
    updates, actor_opt_state = actor_optimizer(config).update(
        grads, agent.actor_opt_state, actor_params)
    actor_params = optax.apply_updates(actor_params, updates)

    target_entropy = config.entropy_target(agent.networks.actor.action_size)
    temp_loss, grad = jax.value_and_grad(losses.alpha_loss)(agent.log_alpha, log_prob,
                                                            target_entropy)
    updates, alpha_opt_state = alpha_optimizer(config).update(
        grad, agent.alpha_opt_state, agent.log_alpha)
    agent = agent.replace(params={**agent.params, "actor": actor_params},
                          actor_opt_state=actor_opt_state,
                          log_alpha=optax.apply_updates(agent.log_alpha, updates),
                          alpha_opt_state=alpha_opt_state)
    agent = losses.soft_update_targets(agent, config)
    metrics.update(actor_loss=loss, alpha_loss=temp_loss, entropy=-jnp.mean(log_prob))
  if config.algo != "sac_aug":
    aux_input = positive if config.algo == "curl" else mixed.obs
    agent, aux_metrics = aux_step(agent, mixed.obs, aux_input,
                                  jax.random.fold_in(key, 3), config)
    metrics.update(aux_metrics)
  metrics["alpha"] = jnp.exp(agent.log_alpha)
  return agent, metrics


def aux_step(agent: AgentState, obs: jax.Array, aux_input: jax.Array, key: jax.Array,
             config: SACConfig) -> tuple[AgentState, Metrics]:
  """One step of CURL's or SAC+AE's auxiliary loss on the encoder and its partner.

  Args:
    agent: the agent, after its SAC step.
    obs: uint8 (B, S, S, C), the critic's observations (CURL's anchors).
    aux_input: CURL: the positive crops; SAC+AE: the observations to reconstruct.
    key: a `jax.random` key (SAC+AE's dither).
    config: the hyperparameters; `algo` must be "curl" or "sac_ae".

  Returns:
    (new agent, metrics).
  """
  task = AUX_TASKS[config.algo]
  aux_params = {"encoder": agent.params["encoder"],
                task.PARTNER: agent.params[task.PARTNER]}
  grads, metrics = jax.grad(task.aux_loss, has_aux=True)(aux_params, agent, obs,
                                                         aux_input, key, config)
  updates, aux_opt_state = aux_optimizer(config).update(grads, agent.aux_opt_state,
                                                        aux_params)
  aux_params = optax.apply_updates(aux_params, updates)
  return agent.replace(params={**agent.params, **aux_params},
                       aux_opt_state=aux_opt_state), metrics


def update_pair(agent: AgentState, batches: Batch, key: jax.Array,
                config: SACConfig) -> tuple[AgentState, Metrics]:
  """A critic-only update, then a full one: "actor and target updates every 2 steps".

  Scanning this over pairs realises the paper's update schedule (Table 6) with no
  traced condition, so it vmaps over agents without computing both branches.

  Args:
    agent: the agent.
    batches: a `Batch` whose arrays have a leading axis of 2 (one batch per update).
    key: a `jax.random` key; update i uses ``fold_in(key, i)``.
    config: the hyperparameters.

  Returns:
    (new agent, metrics): "critic_loss", "lam_loss" and "q" averaged over the
    pair; the rest from its second (actor) update.
  """
  leading = {x.shape[0] if x.ndim else None for x in jax.tree_util.tree_leaves(batches)}
  if leading != {2}:
    raise ValueError(f"batches must have a leading axis of 2 (one batch per update) on "
                     f"every array, got leading sizes {sorted(map(str, leading))}")
  history = []
  for i in range(2):
    batch = jax.tree_util.tree_map(lambda x, i=i: x[i], batches)
    agent, metrics = update(agent, batch, jax.random.fold_in(key, i), config,
                            update_actor=i == 1)
    history.append(metrics)
  metrics = dict(history[-1])
  for name in ("critic_loss", "lam_loss", "q"):
    metrics[name] = jnp.mean(jnp.stack([m[name] for m in history]))
  return agent, metrics
