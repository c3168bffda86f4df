"""The SAC+AUG networks of the DMCR paper (its Table 6), in flax linen.

`Encoder` maps uint8 pixels (B, H, W, 3·stack) to features: /255, ReLU(Conv(32,
3×3, stride 2)), 3× ReLU(Conv(32, 3×3, stride 1)) (all VALID), flatten,
Dense(50), LayerNorm, tanh. `Actor` maps features to a tanh-squashed Gaussian
policy: 2× ReLU(Dense(1024)), Dense(2·|A|) → mean and log-std, the log-std
squashed into (−10, 2) by a rescaled tanh. `Critic` is twin Q: two independent
heads, each 2× ReLU(Dense(1024)) → Dense(1) on concat(features, action). The
policy's sampling and log-density are also plain functions
(`tanh_gaussian_sample`, `tanh_gaussian_log_prob`) so tests can check them.
Kernels use orthogonal initialisation and zero biases, as the SAC-AE / CURL /
DrQ code the paper builds on does (the paper does not say); every width is a
field, so tests use tiny networks. ``dtype`` is the compute dtype of the
convolutions and dense layers (parameters stay float32; LayerNorm, tanh and the
policy's log-densities are computed in float32). The encoder's convolutions and
dense layer are `dmcr_jax.train.layouts`' `Conv` and `Dense`, exactly nn.Conv and
nn.Dense computed in the layout its ``impl`` picks. `Decoder` is SAC+AE's
deconvolutional decoder, the encoder mirrored back to the observation's size;
`Encoder.input_size` center-crops larger inputs (CURL).
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from dmcr_jax.train import layouts

_DENSE_INIT = nn.initializers.orthogonal(1.0)
_CONV_INIT = nn.initializers.orthogonal(math.sqrt(2.0))  # ReLU gain

LOG_STD_MIN = -10.0
"""Lower end of the actor's log-std range (paper Table 6: "Action Log Std Range")."""
LOG_STD_MAX = 2.0
"""Upper end of the actor's log-std range (paper Table 6)."""


class Encoder(nn.Module):
  """Pixels → features: the paper's convolutional encoder (Table 6).

  Attributes:
    channels: filters of each of the four convolutions (paper: 32).
    feature_dim: size of the output features (paper: 50).
    num_layers: number of convolutions; the first has stride 2, the rest 1.
    dtype: compute dtype of the convolutions and the dense layer.
    input_size: None, or the side the convolutions see: larger inputs are
      center-cropped to it (CURL renders 100 and crops to 84).
    impl: how the layers compute (`dmcr_jax.train.layouts.IMPLS`: "pixels" or
      "blocks", the same function of the same parameters); None:
      `layouts.default_impl()`, blocks on GPUs and pixels elsewhere.
  """
  channels: int = 32
  feature_dim: int = 50
  num_layers: int = 4
  dtype: str = "float32"
  input_size: int | None = None
  impl: str | None = None

  @nn.compact
  def __call__(self, obs: jax.Array) -> jax.Array:
    """Encodes a batch of observations.

    Args:
      obs: uint8 (B, H, W, C), channels last (C = 3·frame stack). With
        `input_size` set, larger images are center-cropped to it first (CURL's
        acting and evaluation; its training crops are random and come in at
        `input_size` already).

    Returns:
      float32 (B, feature_dim), each entry in (−1, 1).
    """
    impl = layouts.resolve_impl(self.impl)
    if self.input_size is not None:
      obs = center_crop(obs, self.input_size)
    x = obs.astype(self.dtype) / 255.0
    for i in range(self.num_layers):
      x = layouts.Conv(self.channels, strides=2 if i == 0 else 1, impl=impl,
                       kernel_init=_CONV_INIT, dtype=self.dtype, name=f"conv{i}")(x)
      x = jax.tree.map(nn.relu, x)  # elementwise, in either layout
    x = layouts.Dense(self.feature_dim, kernel_init=_DENSE_INIT, dtype=self.dtype,
                      name="fc")(x)
    return jnp.tanh(nn.LayerNorm(name="norm")(x.astype(jnp.float32)))


def center_crop(images: jax.Array, size: int) -> jax.Array:
  """The central size × size window of (B, H, W, C) images (unchanged if H = W = size).

  Args:
    images: (B, H, W, C) with H, W ≥ size.
    size: the output side.

  Returns:
    (B, size, size, C); the window starts at ((H − size) // 2, (W − size) // 2),
    as CURL's `center_crop_image` does.
  """
  h, w = images.shape[1:3]
  if h < size or w < size:
    raise ValueError(f"cannot center-crop {h}×{w} images to {size}×{size}")
  top, left = (h - size) // 2, (w - size) // 2
  return images[:, top:top + size, left:left + size]


def encoder_sides(side: int, num_layers: int = 4) -> list[int]:
  """The spatial side after each of the encoder's convolutions (3×3 VALID; stride 2, then 1)."""
  sides = [(side - 3) // 2 + 1]
  for _ in range(num_layers - 1):
    sides.append(sides[-1] - 2)
  return sides


class Decoder(nn.Module):
  """Features → pixels: SAC+AE's deconvolutional decoder, the encoder mirrored.

  Dense(channels·s·s) on the features (s = the encoder's last side), ReLU,
  reshape, (num_layers − 1) × ReLU(ConvTranspose(channels, 3×3, stride 1)),
  then ConvTranspose(out_channels, 3×3, stride 2) back to the input side (the
  last layer's padding plays the part of PyTorch's ``output_padding``). No
  output activation: it regresses SAC+AE's pre-processed pixels in [−.5, .5).

  The stride-2 output layer is `layouts.StrideTwoConvTranspose`: the same function,
  with the same parameters (``out/kernel`` (3, 3, channels, out_channels),
  ``out/bias``) and initialisers, as ``nn.ConvTranspose(out_channels, (3, 3),
  strides=(2, 2), padding=((2, after), (2, after)))``, computed in phases without
  the zero-dilated input XLA would materialise.

  Attributes:
    side: the observation's side (H = W) to reconstruct.
    out_channels: the observation's channels (3·frame stack).
    channels: filters of the hidden deconvolutions (the encoder's, 32).
    num_layers: the encoder's number of convolutions (4).
    dtype: compute dtype of the layers (the output is float32).
  """
  side: int
  out_channels: int
  channels: int = 32
  num_layers: int = 4
  dtype: str = "float32"

  @nn.compact
  def __call__(self, features: jax.Array) -> jax.Array:
    """Reconstructs (B, side, side, out_channels) float32 images from (B, F) features."""
    sides = encoder_sides(self.side, self.num_layers)
    s = sides[-1]
    x = nn.Dense(self.channels * s * s, kernel_init=_DENSE_INIT, dtype=self.dtype,
                 name="fc")(features)
    x = nn.relu(x).reshape(features.shape[0], s, s, self.channels)
    for i in range(self.num_layers - 1):
      x = nn.relu(nn.ConvTranspose(self.channels, (3, 3), padding="VALID",
                                   kernel_init=_CONV_INIT, dtype=self.dtype,
                                   name=f"deconv{i}")(x))
    # Stride 2 from sides[0] back to `side`: the dilated input has 2·sides[0] − 1
    # pixels, the 3×3 kernel removes 2, so `side` needs side − 2·sides[0] + 3 of
    # padding: 2 before (a full transposed convolution) and the rest after.
    after = self.side - 2 * sides[0] + 1
    x = layouts.StrideTwoConvTranspose(self.out_channels, after=after,
                                       kernel_init=_DENSE_INIT, dtype=self.dtype,
                                       name="out")(x)
    return x.astype(jnp.float32)


class MLP(nn.Module):
  """ReLU(Dense(hidden)) × num_hidden, then a linear Dense(out_dim).

  Attributes:
    hidden_dim: width of the hidden layers.
    out_dim: size of the output.
    num_hidden: number of hidden layers (paper: 2).
    dtype: compute dtype of the layers (the output is cast to float32).
  """
  hidden_dim: int
  out_dim: int
  num_hidden: int = 2
  dtype: str = "float32"

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Applies the MLP to (B, D) inputs; returns float32 (B, out_dim)."""
    for i in range(self.num_hidden):
      x = nn.relu(nn.Dense(self.hidden_dim, kernel_init=_DENSE_INIT, dtype=self.dtype,
                           name=f"hidden{i}")(x))
    x = nn.Dense(self.out_dim, kernel_init=_DENSE_INIT, dtype=self.dtype, name="out")(x)
    return x.astype(jnp.float32)


def squash_log_std(raw: jax.Array, low: float = LOG_STD_MIN,
                   high: float = LOG_STD_MAX) -> jax.Array:
  """Maps an unbounded value into (low, high): low + (high − low)·(tanh(raw) + 1)/2.

  Args:
    raw: any float array.
    low: the lower bound.
    high: the upper bound.

  Returns:
    An array of the same shape with values in (low, high).
  """
  return low + 0.5 * (high - low) * (jnp.tanh(raw) + 1.0)


def tanh_log_det_jacobian(pre_tanh: jax.Array) -> jax.Array:
  """log(1 − tanh(u)²) elementwise, computed stably as 2·(log 2 − u − softplus(−2u)).

  Args:
    pre_tanh: u, the Gaussian sample before the tanh.

  Returns:
    An array of the same shape (≤ 0).
  """
  return 2.0 * (math.log(2.0) - pre_tanh - jax.nn.softplus(-2.0 * pre_tanh))


def tanh_gaussian_log_prob(pre_tanh: jax.Array, mean: jax.Array,
                           log_std: jax.Array) -> jax.Array:
  """log π(tanh(u)) for u ~ N(mean, exp(log_std)²), summed over the action axis.

  log π(a) = Σ_i [log N(u_i; mean_i, std_i) − log(1 − tanh(u_i)²)], a = tanh(u)
  (the change of variables of SAC, Haarnoja et al. 2018, appendix C).

  Args:
    pre_tanh: u, (..., A).
    mean: (..., A).
    log_std: (..., A).

  Returns:
    (...,): the log-density of the squashed action.
  """
  z = (pre_tanh - mean) * jnp.exp(-log_std)
  gaussian = -0.5 * jnp.square(z) - log_std - 0.5 * math.log(2.0 * math.pi)
  return jnp.sum(gaussian - tanh_log_det_jacobian(pre_tanh), axis=-1)


def tanh_gaussian_sample(key: jax.Array, mean: jax.Array,
                         log_std: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Draws a = tanh(mean + std·ε), ε ~ N(0, I) (reparameterised), and log π(a).

  Args:
    key: a `jax.random` key.
    mean: (..., A).
    log_std: (..., A).

  Returns:
    (action in (−1, 1) of shape (..., A), log-prob of shape (...)).
  """
  pre_tanh = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)
  return jnp.tanh(pre_tanh), tanh_gaussian_log_prob(pre_tanh, mean, log_std)


class Actor(nn.Module):
  """Features → tanh-squashed Gaussian policy (paper Table 6).

  ``apply(params, features)`` returns (mean, log_std); ``method="sample"`` returns
  (action, log_prob) for a key; ``method="mode"`` the deterministic tanh(mean).

  Attributes:
    action_size: |A|.
    hidden_dim: width of the two hidden layers (paper: 1024).
    log_std_min: lower end of the log-std range (paper: −10).
    log_std_max: upper end of the log-std range (paper: 2).
    dtype: compute dtype of the dense layers.
  """
  action_size: int
  hidden_dim: int = 1024
  log_std_min: float = LOG_STD_MIN
  log_std_max: float = LOG_STD_MAX
  dtype: str = "float32"

  @nn.compact
  def __call__(self, features: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The Gaussian's parameters before the tanh.

    Args:
      features: (B, F).

    Returns:
      (mean, log_std), each (B, A); log_std in (log_std_min, log_std_max).
    """
    out = MLP(self.hidden_dim, 2 * self.action_size, dtype=self.dtype, name="mlp")(features)
    mean, raw_log_std = jnp.split(out, 2, axis=-1)
    return mean, squash_log_std(raw_log_std, self.log_std_min, self.log_std_max)

  def sample(self, features: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A reparameterised policy sample and its log-prob.

    Args:
      features: (B, F).
      key: a `jax.random` key.

    Returns:
      (action (B, A) in (−1, 1), log_prob (B,)).
    """
    mean, log_std = self(features)
    return tanh_gaussian_sample(key, mean, log_std)

  def mode(self, features: jax.Array) -> jax.Array:
    """The deterministic action tanh(mean), (B, A)."""
    mean, _ = self(features)
    return jnp.tanh(mean)


class Critic(nn.Module):
  """Twin Q: two independent heads on concat(features, action) (paper Table 6).

  Attributes:
    hidden_dim: width of each head's two hidden layers (paper: 1024).
    dtype: compute dtype of the dense layers.
  """
  hidden_dim: int = 1024
  dtype: str = "float32"

  @nn.compact
  def __call__(self, features: jax.Array, action: jax.Array
               ) -> tuple[jax.Array, jax.Array]:
    """Both heads' Q-values.

    Args:
      features: (B, F).
      action: (B, A).

    Returns:
      (q1, q2), each (B,).
    """
    x = jnp.concatenate([features, action], axis=-1)
    q1 = MLP(self.hidden_dim, 1, dtype=self.dtype, name="q1")(x)[..., 0]
    q2 = MLP(self.hidden_dim, 1, dtype=self.dtype, name="q2")(x)[..., 0]
    return q1, q2
