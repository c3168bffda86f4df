"""SAC+AE's auxiliary task (Yarats et al. 2019) as pure JAX functions.

A deconvolutional decoder (`networks.Decoder`) reconstructs the observation from
the encoder's features h = e(o). The target is SAC+AE's pre-processed
observation: each uint8 value v is reduced to `bits` bits, scaled to [0, 1),
dithered with uniform noise of one bin, and shifted by −.5:

    t = floor(v / 2^(8 − bits)) / 2^bits + U[0, 1/2^bits) − .5        (bits = 5)

The loss is L_rec = mean((t − D(h))²) over every pixel and channel, plus the
L2 penalty on the latent, λ_z · mean_b ½‖h_b‖² (λ_z = 1e-6); the decoder's
optimizer adds weight decay λ_w·θ to its gradient (λ_w = 1e-7, PyTorch Adam's
``weight_decay``). L_rec + the latent penalty train the encoder and the decoder
with their own Adam step after the SAC step, every update.

The auxiliary task's interface, shared with `dmcr_jax.train.curl`: `PARTNER` (the
parameters trained beside the encoder), `init_partner`, `optimizer` and
`aux_loss`. The wiring into the learner is in `dmcr_jax.train.sac`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

PARTNER = "decoder"
"""The key of the decoder's parameters in the agent's params."""


def reconstruction_target(key: jax.Array, obs: jax.Array, bits: int = 5) -> jax.Array:
  """SAC+AE's pre-processed pixels: `bits`-bit quantised, dithered, centred.

  Args:
    key: a `jax.random` key for the dither.
    obs: uint8 (B, H, W, C).
    bits: bits kept per value (1 … 8).

  Returns:
    float32 (B, H, W, C) in [−.5, .5).
  """
  if not 1 <= bits <= 8:
    raise ValueError(f"bits must be in 1 … 8, got {bits}")
  bins = 2.0 ** bits
  x = jnp.floor(obs.astype(jnp.float32) / 2.0 ** (8 - bits)) / bins
  return x + jax.random.uniform(key, obs.shape, jnp.float32) / bins - 0.5


def latent_penalty(features: jax.Array) -> jax.Array:
  """mean_b ½‖h_b‖², the L2 penalty on the encoder's output."""
  return jnp.mean(0.5 * jnp.sum(jnp.square(features), axis=-1))


def loss(reconstruction: jax.Array, target: jax.Array, features: jax.Array,
         latent_lambda: float) -> tuple[jax.Array, dict[str, jax.Array]]:
  """L_rec + λ_z · latent penalty, and both terms as metrics.

  Args:
    reconstruction: float32 (B, H, W, C), the decoder's output.
    target: float32 (B, H, W, C), `reconstruction_target` of the observations.
    features: (B, F), the encoder's features the decoder read.
    latent_lambda: λ_z.

  Returns:
    (loss, {"reconstruction_loss", "latent_loss"}).
  """
  rec = jnp.mean(jnp.square(target - reconstruction))
  latent = latent_penalty(features)
  return rec + latent_lambda * latent, {"reconstruction_loss": rec, "latent_loss": latent}


def init_partner(key: jax.Array, networks, features: jax.Array, config) -> dict:
  """The decoder's parameters (`networks.decoder` initialised on `features`, (1, F))."""
  del config
  return networks.decoder.init(key, features)


def optimizer(config) -> optax.GradientTransformation:
  """Adam(`config.encoder_lr`) for the encoder and, for the decoder, weight decay
  λ_w·θ (`config.decoder_weight_lambda`) added to the gradient before Adam
  (PyTorch Adam's ``weight_decay``)."""
  return optax.multi_transform(
      {"encoder": optax.adam(config.encoder_lr),
       PARTNER: optax.chain(optax.add_decayed_weights(config.decoder_weight_lambda),
                            optax.adam(config.encoder_lr))},
      {"encoder": "encoder", PARTNER: PARTNER})


def aux_loss(aux_params, agent, obs: jax.Array, aux_input: jax.Array, key: jax.Array,
             config) -> tuple[jax.Array, dict[str, jax.Array]]:
  """SAC+AE's L_rec + λ_z·latent penalty, a function of ``{"encoder", "decoder"}``.

  Args:
    aux_params: ``{"encoder": …, "decoder": …}``, the differentiated parameters.
    agent: the `dmcr_jax.train.sac.AgentState` (its encoder and decoder modules).
    obs: the critic's observations (unused: the signature shared with
      `dmcr_jax.train.curl.aux_loss`).
    aux_input: uint8 (B, H, W, C), the observations to reconstruct.
    key: a `jax.random` key for the target's dither.
    config: the hyperparameters (`decoder_bits`, `decoder_latent_lambda`).

  Returns:
    (loss, {"aux_loss", "reconstruction_loss", "latent_loss"}).
  """
  del obs
  nets = agent.networks
  target = reconstruction_target(key, aux_input, config.decoder_bits)
  features = nets.encoder.apply(aux_params["encoder"], aux_input)
  reconstruction = nets.decoder.apply(aux_params[PARTNER], features)
  total, metrics = loss(reconstruction, target, features, config.decoder_latent_lambda)
  return total, {"aux_loss": total, **metrics}
