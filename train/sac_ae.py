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
with their own Adam step after the SAC step, every update. The wiring into the
learner is in `train.sac`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


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
