"""`SACConfig`, the hyperparameters of the DMCR paper's learner (its Table 6 and
Sec. 3.2) and of its baselines CURL and SAC+AE, with their validation: every field
is checked when a config is made, with one clear error naming the valid choices,
so nothing invalid reaches `dmcr_jax.train.sac` or a compiled update. Fields left
as None take the algorithm's value from `ALGO_DEFAULTS`; `SACConfig.from_dict`
reads a run's config.json, dropping the non-field names of `DROPPED_FIELDS`.
`dmcr_jax.train.sac` re-exports these names (`sac.SACConfig`, `sac.ALGOS`, …),
the ones the rest of the code uses.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from dmcr_jax import augment
from dmcr_jax.train.networks import LOG_STD_MAX, LOG_STD_MIN

COMPUTE_DTYPES = ("float32", "bfloat16")
"""What `SACConfig.compute_dtype` accepts."""

ALGOS = ("sac_aug", "curl", "sac_ae")
"""What `SACConfig.algo` accepts: the paper's SAC+AUG, CURL and SAC+AE."""

ALGO_DEFAULTS = {
    "sac_aug": dict(batch_size=256, aug="drq", beta=0.9, lam=1e-5),
    "curl": dict(batch_size=256, aug="none", beta=1.0, lam=0.0),
    "sac_ae": dict(batch_size=128, aug="none", beta=1.0, lam=0.0),
}
"""What a `SACConfig` field left as None becomes, per algorithm (paper Table 6:
batch 128 for SAC+AE; CURL and SAC+AE train without `dmcr_jax.augment`)."""


def is_int(x) -> bool:
  """Whether `x` is a Python int (bools excluded)."""
  return isinstance(x, int) and not isinstance(x, bool)


def is_real(x) -> bool:
  """Whether `x` is a finite Python int or float (bools excluded)."""
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
      if not is_int(value) or value < 1:
        fail(field, value, "a positive int")
    for field in ("critic_lr", "actor_lr", "encoder_lr", "alpha_lr", "init_alpha"):
      value = getattr(self, field)
      if not is_real(value) or value <= 0:
        fail(field, value, "a positive finite number")
    for field in ("encoder_tau", "critic_tau"):
      value = getattr(self, field)
      if not is_real(value) or not 0 < value <= 1:
        fail(field, value, "in (0, 1]")
    for field in ("gamma", "beta"):
      value = getattr(self, field)
      if not is_real(value) or not 0 <= value <= 1:
        fail(field, value, "in [0, 1]")
    if not is_real(self.lam) or self.lam < 0:
      fail("lam", self.lam, "a finite number ≥ 0")
    if self.target_entropy is not None and not is_real(self.target_entropy):
      fail("target_entropy", self.target_entropy, "None or a finite number")
    if not (is_real(self.log_std_min) and is_real(self.log_std_max)
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
      if not is_real(value) or value < 0:
        fail(field, value, "a finite number ≥ 0")
    if not is_int(self.decoder_bits) or not 1 <= self.decoder_bits <= 8:
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
