"""SAC+AUG, the DMCR paper's learner (Sec. 3.2, appendix, Table 6), as pure JAX functions;
with `SACConfig.algo`, also its baselines CURL and SAC+AE on the same SAC.

One immutable `AgentState`; `update` is pure and jittable, with ``update_actor``
static, so `jax.vmap` over K agents and `jax.lax.scan` over `update_pair` (a
critic-only update, then a full one: the paper's "actor and target updates every
2 steps", a fixed part of the algorithm here) stay cheap. The losses take uint8
observations; how the encoder computes on them is its own affair
(`dmcr_jax.train.networks.Encoder`). The losses, for a batch of B transitions (o, a, r, d, o′):

- β mixing (paper Sec. 3.2): z is the augmentation (`dmcr_jax.augment.get(aug)`,
  one draw per sample shared by o, o′ and the frames of the stack). The first
  n = ⌊β·B⌋ rows of o and o′ are replaced by z(o), z(o′); the rest stay as they are.
  This mixed batch (ô, a, r, d, ô′) serves the critic and the actor.
- Critic (paper eq. for L_critic, both heads, sum of their mean squared errors):
  y = sg(r + γ·d·(min_i Q′_i(e′(ô′), a′) − α·log π(a′|sg e(ô′)))), a′ ~ π(·|sg e(ô′)),
  L_critic = mean_b (Q_1(e(ô), a) − y)² + mean_b (Q_2(e(ô), a) − y)²,
  with e, Q the online encoder and critic, e′, Q′ their targets, α = exp(log α).
- Encoder (paper eq. for L_encoder): L_encoder = L_critic + L_λ,
  L_λ = λ · mean_b Σ_f (sg(e(o_b)) − e(z(o_b)))_f², over all B rows, gradient
  only through the augmented pass e(z(o)) as the paper's text says. (DESIGN.md
  and the issue put the stop-gradient on the other side by mistake; we follow the
  paper.) The encoder and critic take one Adam step on L_encoder; no other loss
  reaches the encoder.
- Actor (paper eq. for L_actor): ã ~ π(·|sg e(ô)) reparameterised,
  L_actor = mean_b (sg(α)·log π(ã|·) − min_i Q_i(sg e(ô), ã)); only the actor's
  parameters move.
- Temperature: L_α = mean_b (−α·(sg(log π(ã|·)) + H̄)), H̄ = −|A| by default,
  optimised over log α.
- Targets (Polyak): e′ ← (1 − τ_e)·e′ + τ_e·e with τ_e = .05, Q′ ← (1 − τ_Q)·Q′ +
  τ_Q·Q with τ_Q = .01, after every actor update.

In an update with ``update_actor=True`` the critic steps first; the actor then uses
the updated encoder and critic (as SAC-AE, CURL and DrQ do), then α, then targets.

CURL (``algo="curl"``, `dmcr_jax.train.curl`): instead of β mixing, every row of o and o′ is
a random crop of the larger rendered observation (anchor, o′), the SAC losses
above run on them (λ = 0), and after the targets one more Adam step on the
encoder and the bilinear W minimises InfoNCE between the anchors (online
encoder) and independent positive crops (target encoder, no gradient). SAC+AE
(``algo="sac_ae"``, `dmcr_jax.train.sac_ae`): the SAC losses on the (un-augmented by
default) batch, then one Adam step on the encoder and the decoder on the
reconstruction loss. Both auxiliary steps run every update, as in the original
code, with their own Adam states (`aux_optimizer`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import optax

from dmcr_jax import augment
from dmcr_jax.train import curl, sac_ae
from dmcr_jax.train.networks import (LOG_STD_MAX, LOG_STD_MIN, Actor, Critic, Decoder, Encoder,
                                     encoder_sides)
from dmcr_jax.train.replay import Batch  # what `replay.sample` returns and `update` consumes

Params = Any
Metrics = dict[str, jax.Array]

COMPUTE_DTYPES = ("float32", "bfloat16")
"""What `SACConfig.compute_dtype` accepts."""

ALGOS = ("sac_aug", "curl", "sac_ae")
"""What `SACConfig.algo` accepts: the paper's SAC+AUG, CURL and SAC+AE."""
AUX_TASKS = {"curl": curl, "sac_ae": sac_ae}
"""The auxiliary task of each learner that has one: a module with `PARTNER`,
`init_partner`, `optimizer` and `aux_loss(aux_params, agent, obs, aux_input, key,
config)`."""

ALGO_DEFAULTS = {
    "sac_aug": dict(batch_size=256, aug="drq", beta=0.9, lam=1e-5),
    "curl": dict(batch_size=256, aug="none", beta=1.0, lam=0.0),
    "sac_ae": dict(batch_size=128, aug="none", beta=1.0, lam=0.0),
}
"""What a `SACConfig` field left as None becomes, per algorithm (paper Table 6:
batch 128 for SAC+AE; CURL and SAC+AE train without `dmcr_jax.augment`)."""


# --------------------------------------------------------------------------- #
# Configuration.
# --------------------------------------------------------------------------- #


def _is_int(x) -> bool:
  return isinstance(x, int) and not isinstance(x, bool)


def _is_real(x) -> bool:
  return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@dataclasses.dataclass(frozen=True)
class SACConfig:
  """Learner hyperparameters; defaults are the paper's Table 6 (and Sec. 3.2).

  Fields given as None take the algorithm's value from `ALGO_DEFAULTS`.

  Attributes:
    algo: "sac_aug" (the paper's SAC+AUG, default), "curl" (SAC with CURL's
      contrastive loss, `dmcr_jax.train.curl`) or "sac_ae" (SAC with SAC+AE's decoder,
      `dmcr_jax.train.sac_ae`).
    batch_size: transitions per update (256; SAC+AE 128).
    gamma: discount factor (.99).
    critic_lr: Adam learning rate of the critic heads (1e-3).
    actor_lr: Adam learning rate of the actor (1e-3).
    encoder_lr: Adam learning rate of the encoder (1e-3).
    alpha_lr: Adam learning rate of log α (1e-4).
    init_alpha: initial temperature α (.1).
    target_entropy: H̄ of the temperature loss; None means −|A| (Table 6).
    encoder_tau: Polyak rate of the target encoder (.05).
    critic_tau: Polyak rate of the target critic (.01).
    beta: fraction of each batch that is augmented (Sec. 3.2: .9; 1 for CURL
      and SAC+AE, which augment every row when they augment).
    lam: weight λ of the feature-matching term (Sec. 3.2: 1e-5; 0 for CURL and
      SAC+AE).
    aug: augmentation name, any name `dmcr_jax.augment.get` accepts ("drq";
      "none" for CURL, whose random crops are part of the algorithm, and for
      SAC+AE, which the paper trains without augmentation); or
      several separated by commas ("drq,cj+drq"): then each agent uses the one
      its `AgentState.aug_index` picks (K agents with different augmentations
      vmap together; see `aug_names`).
    feature_dim: encoder output size (50).
    hidden_dim: width of the actor's and critics' hidden layers (1024).
    conv_channels: filters of each convolution (32).
    log_std_min: lower end of the actor's log-std range (−10).
    log_std_max: upper end of the actor's log-std range (2).
    compute_dtype: "float32" (default) or "bfloat16", the compute dtype of the
      networks' convolutions and dense layers (parameters, optimizer states,
      losses and the policy's log-densities stay float32).
    curl_crop: CURL's crop side, the encoder's input (84); observations are
      rendered larger (`TrainConfig.image_size`, 100 for CURL).
    decoder_latent_lambda: SAC+AE's weight λ_z of the latent L2 penalty (1e-6).
    decoder_weight_lambda: SAC+AE's decoder weight decay λ_w (1e-7).
    decoder_bits: bits per value of SAC+AE's reconstruction target (5).

  The actor, α and the targets update every second critic update (Table 6), as
  `update_pair` runs them.
  """
  algo: str = "sac_aug"
  batch_size: int | None = None
  gamma: float = 0.99
  critic_lr: float = 1e-3
  actor_lr: float = 1e-3
  encoder_lr: float = 1e-3
  alpha_lr: float = 1e-4
  init_alpha: float = 0.1
  target_entropy: float | None = None
  encoder_tau: float = 0.05
  critic_tau: float = 0.01
  beta: float | None = None
  lam: float | None = None
  aug: str | None = None
  feature_dim: int = 50
  hidden_dim: int = 1024
  conv_channels: int = 32
  log_std_min: float = LOG_STD_MIN
  log_std_max: float = LOG_STD_MAX
  compute_dtype: str = "float32"
  curl_crop: int = 84
  decoder_latent_lambda: float = 1e-6
  decoder_weight_lambda: float = 1e-7
  decoder_bits: int = 5

  def __post_init__(self):
    def fail(field, value, want):
      raise ValueError(f"SACConfig.{field} must be {want}, got {value!r}")

    if self.algo not in ALGOS:
      fail("algo", self.algo, f"one of {', '.join(ALGOS)}")
    for field, value in ALGO_DEFAULTS[self.algo].items():
      if getattr(self, field) is None:
        object.__setattr__(self, field, value)

    for field in ("batch_size", "feature_dim", "hidden_dim", "conv_channels", "curl_crop"):
      value = getattr(self, field)
      if not _is_int(value) or value < 1:
        fail(field, value, "a positive int")
    for field in ("critic_lr", "actor_lr", "encoder_lr", "alpha_lr", "init_alpha"):
      value = getattr(self, field)
      if not _is_real(value) or value <= 0:
        fail(field, value, "a positive finite number")
    for field in ("encoder_tau", "critic_tau"):
      value = getattr(self, field)
      if not _is_real(value) or not 0 < value <= 1:
        fail(field, value, "in (0, 1]")
    for field in ("gamma", "beta"):
      value = getattr(self, field)
      if not _is_real(value) or not 0 <= value <= 1:
        fail(field, value, "in [0, 1]")
    if not _is_real(self.lam) or self.lam < 0:
      fail("lam", self.lam, "a finite number ≥ 0")
    if self.target_entropy is not None and not _is_real(self.target_entropy):
      fail("target_entropy", self.target_entropy, "None or a finite number")
    if not (_is_real(self.log_std_min) and _is_real(self.log_std_max)
            and self.log_std_min < self.log_std_max):
      raise ValueError(f"SACConfig needs finite log_std_min < log_std_max, got "
                       f"({self.log_std_min!r}, {self.log_std_max!r})")
    if not isinstance(self.aug, str):
      fail("aug", self.aug, "an augmentation name (str)")
    names = self.aug_names
    if len(set(names)) != len(names):
      fail("aug", self.aug, "distinct comma-separated augmentation names")
    for name in names:
      try:
        augment.get(name)
      except ValueError as e:
        raise ValueError(f"SACConfig.aug: {e}") from None
    if self.compute_dtype not in COMPUTE_DTYPES:
      fail("compute_dtype", self.compute_dtype, f"one of {', '.join(COMPUTE_DTYPES)}")
    for field in ("decoder_latent_lambda", "decoder_weight_lambda"):
      value = getattr(self, field)
      if not _is_real(value) or value < 0:
        fail(field, value, "a finite number ≥ 0")
    if not _is_int(self.decoder_bits) or not 1 <= self.decoder_bits <= 8:
      fail("decoder_bits", self.decoder_bits, "an int in 1 … 8")
    if self.algo == "curl" and (self.aug != "none" or self.beta != 1 or self.lam != 0):
      raise ValueError(
          "SACConfig(algo='curl'): CURL crops every row itself (observations rendered "
          "larger, random crops of curl_crop), so aug, beta and lam do not apply; got "
          f"aug={self.aug!r}, beta={self.beta!r}, lam={self.lam!r} (leave them unset)")
    if self.lam > 0 and self.aug_names == ("none",):
      raise ValueError(f"SACConfig.lam = {self.lam!r} needs an augmentation (with "
                       "aug='none' the λ term is identically 0); set lam=0 or an aug")

  @property
  def aug_names(self) -> tuple[str, ...]:
    """The augmentation names of `aug` ("drq,cj+drq" → ("drq", "cj+drq"))."""
    return tuple(name.strip() for name in self.aug.split(","))

  def entropy_target(self, action_size: int) -> float:
    """H̄ for the temperature loss: `target_entropy`, or −action_size if None.

    Args:
      action_size: |A|.

    Returns:
      The target entropy as a Python float.
    """
    if self.target_entropy is None:
      return -float(action_size)
    return float(self.target_entropy)

  @classmethod
  def from_dict(cls, fields: dict[str, Any]) -> SACConfig:
    """The config `dataclasses.asdict` gave `fields` (a run's config.json).

    The names of `DROPPED_FIELDS` are dropped if they hold a value the learner
    computes.

    Raises:
      ValueError: for a dropped field with another value; TypeError for an
        unknown field.
    """
    fields = dict(fields)
    for name, only in DROPPED_FIELDS.items():
      if name in fields:
        value = fields.pop(name)
        if only is not None and value != only:
          raise ValueError(f"SACConfig.{name} = {value!r} is not supported: the learner "
                           f"runs {name} = {only!r} only")
    return cls(**fields)


DROPPED_FIELDS = {"stage_inputs": None, "update_delay": 2}
"""Names a run's config.json may hold that are not `SACConfig` fields, which
`SACConfig.from_dict` drops: name → the only value it accepts (None: any).
`stage_inputs`: any value, the update is the same; `update_delay`: 2, the schedule
of `update_pair`."""


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
  if (len(obs_shape) != 3 or not all(_is_int(d) and d > 0 for d in obs_shape)
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
  if not _is_int(action_size) or action_size < 1:
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
  critic), one log α step on L_α, and the Polyak target updates (module
  docstring); then, for CURL and SAC+AE, one step of their auxiliary loss on the
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
    mixed, z_obs = augment_and_mix(aug_key, batch, agent_augmentation(agent, config),
                                   config.beta)

  critic_params = {"encoder": agent.params["encoder"],
                   "critic": agent.params["critic"]}
  grads, metrics = jax.grad(critic_loss, has_aux=True)(
      critic_params, agent, batch, mixed, z_obs, target_key, config)
  updates, critic_opt_state = critic_optimizer(config).update(
      grads, agent.critic_opt_state, critic_params)
  critic_params = optax.apply_updates(critic_params, updates)
  agent = agent.replace(params={**agent.params, **critic_params},
                        critic_opt_state=critic_opt_state, step=agent.step + 1)

  if update_actor:
    actor_params = agent.params["actor"]
    (loss, log_prob), grads = jax.value_and_grad(actor_loss, has_aux=True)(
        actor_params, agent, mixed.obs, actor_key)
    updates, actor_opt_state = actor_optimizer(config).update(
        grads, agent.actor_opt_state, actor_params)
    actor_params = optax.apply_updates(actor_params, updates)

    target_entropy = config.entropy_target(agent.networks.actor.action_size)
    temp_loss, grad = jax.value_and_grad(alpha_loss)(agent.log_alpha, log_prob,
                                                     target_entropy)
    updates, alpha_opt_state = alpha_optimizer(config).update(
        grad, agent.alpha_opt_state, agent.log_alpha)
    agent = agent.replace(params={**agent.params, "actor": actor_params},
                          actor_opt_state=actor_opt_state,
                          log_alpha=optax.apply_updates(agent.log_alpha, updates),
                          alpha_opt_state=alpha_opt_state)
    agent = soft_update_targets(agent, config)
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
