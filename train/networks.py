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
policy's log-densities are computed in float32): "bfloat16" halves the memory
traffic of the convolutions on GPUs (benchmarks/learner.py measures it).
The stride-2 first convolution is computed on 2×2 pixel blocks (`StrideTwoConv`:
the same function and parameters as `nn.Conv`, faster on GPUs); on GPUs the
stride-1 convolutions and the dense layer read 2×2 blocks too
(`BlockConv`, `BlockDense`: again the same function and parameters). `encoder_input`
does the encoder's input work (crop, /255, 2×2 blocks) once, as `Blocks`, so that
several passes over the same observations (online and target encoders) share it.
`Decoder` is SAC+AE's deconvolutional decoder, the encoder mirrored back to the
observation's size; `Encoder.input_size` center-crops larger inputs (CURL).
"""

from __future__ import annotations

import functools
import math

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

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
    blocks: compute the stride-1 convolutions and the dense layer on 2×2 pixel
      blocks (`BlockConv`, `BlockDense`; the same function of the same
      parameters); None: where that is faster (`stride_one_on_blocks`).
  """
  channels: int = 32
  feature_dim: int = 50
  num_layers: int = 4
  dtype: str = "float32"
  input_size: int | None = None
  blocks: bool | None = None

  @nn.compact
  def __call__(self, obs: jax.Array | Blocks) -> jax.Array:
    """Encodes a batch of observations.

    Args:
      obs: uint8 (B, H, W, C), channels last (C = 3·frame stack), or the same
        observations already prepared by `encoder_input(self, obs)` (the same
        result). With `input_size` set, larger images are center-cropped to it
        first (CURL's acting and evaluation; its training crops are random and
        come in at `input_size` already).

    Returns:
      float32 (B, feature_dim), each entry in (−1, 1).
    """
    x = obs if isinstance(obs, Blocks) else encoder_input(self, obs)
    # Stride 2, as blocks (see StrideTwoConv).
    x = nn.relu(StrideTwoConv(self.channels, kernel_init=_CONV_INIT, dtype=self.dtype,
                              name="conv0")(x))
    on_blocks = self.blocks if self.blocks is not None else stride_one_on_blocks()
    out_h, out_w = (side - 2 * (self.num_layers - 1) for side in x.shape[1:3])
    if on_blocks:
      x = space_to_depth(x, _round_up(x.shape[1], 2), _round_up(x.shape[2], 2))
    conv = BlockConv if on_blocks else functools.partial(nn.Conv, kernel_size=(3, 3),
                                                         padding="VALID")
    for i in range(1, self.num_layers):
      x = nn.relu(conv(self.channels, kernel_init=_CONV_INIT, bias_init=nn.initializers.zeros,
                       dtype=self.dtype, name=f"conv{i}")(x))
    if on_blocks:
      x = BlockDense(self.feature_dim, (out_h, out_w), kernel_init=_DENSE_INIT,
                     dtype=self.dtype, name="fc")(x)
    else:
      x = nn.Dense(self.feature_dim, kernel_init=_DENSE_INIT, dtype=self.dtype,
                   name="fc")(x.reshape(x.shape[0], -1))
    return jnp.tanh(nn.LayerNorm(name="norm")(x.astype(jnp.float32)))


@flax.struct.dataclass
class Blocks:
  """A `StrideTwoConv` input already cut into 2×2 blocks (`stride_two_blocks`).

  Attributes:
    data: (B, (H − 3)//2 + 2, (W − 3)//2 + 2, 4·P rounded up to a multiple of
      `block_channel_multiple`): `space_to_depth` of the image laid out with P
      channels per pixel (`pixel_slots`), zero channels last.
    channels: C, the channels of the image (static; the kernel's input channels).
    pixel_channels: P ≥ C, the channels per pixel before `space_to_depth` (static;
      C: the image's channels in order).
  """
  data: jax.Array
  channels: int = flax.struct.field(pytree_node=False)
  pixel_channels: int = flax.struct.field(pytree_node=False)

  @property
  def slots(self) -> np.ndarray:
    """The pixel channel of each image channel (`pixel_slots`)."""
    return pixel_slots(self.channels, self.pixel_channels)


def pixel_slots(channels: int, pixel_channels: int) -> np.ndarray:
  """Where each image channel sits among a pixel's channels in `Blocks`.

  Args:
    channels: C, the image's channels.
    pixel_channels: P: C (the channels in order), or the frame layout of
      `pixel_layout` (frames of 3 channels, 4 channels each).

  Returns:
    int (C,): c itself, or 4·(c // 3) + c % 3.
  """
  c = np.arange(channels)
  return c if pixel_channels == channels else 4 * (c // 3) + c % 3


def pixel_layout(channels: int, channel_multiple: int) -> int:
  """The channels per pixel `stride_two_blocks` lays an image's C channels out in.

  Frames of 3 channels (C = 3·S) take 4 channels each, and S is rounded up to a
  power of two, when the blocks then have no more channels than C in order padded
  at the end: every block channel's pixel, frame and colour are then bit fields of
  its index. Otherwise C.

  Args:
    channels: C, the image's channels (3 per frame for frame stacks).
    channel_multiple: the multiple the block channels are padded to
      (`block_channel_multiple`).

  Returns:
    P, the channels per pixel: 4·(S rounded up to a power of two), or C.
  """
  if channels % 3:
    return channels
  grouped = 4 * (1 << (channels // 3 - 1).bit_length())
  padded = lambda per_pixel: _round_up(4 * per_pixel, channel_multiple)
  return grouped if padded(grouped) <= padded(channels) else channels


def _round_up(n: int, multiple: int) -> int:
  """The least multiple of `multiple` that is ≥ n: the block channels with their zero channels."""
  return -(-n // multiple) * multiple


def stride_two_blocks(x: jax.Array, channel_multiple: int | None = None) -> Blocks:
  """The blocks `StrideTwoConv` convolves, for (B, H, W, C) images (H, W ≥ 3).

  The channels laid out per pixel (`pixel_layout`), `space_to_depth` to
  (out_h + 1, out_w + 1) blocks (out = (side − 3)//2 + 1, the convolution's output
  side), zero channels appended up to a multiple of `channel_multiple` (default:
  `block_channel_multiple` of x's dtype); the dtype is kept. Zero channels meet
  zero kernel rows: the convolution is unchanged.
  """
  if x.ndim != 4 or min(x.shape[1:3]) < 3:
    raise ValueError(f"expected (B, H, W, C) inputs with H, W ≥ 3, got shape {x.shape}")
  if channel_multiple is None:
    channel_multiple = block_channel_multiple(x.dtype)
  channels = x.shape[-1]
  per_pixel = pixel_layout(channels, channel_multiple)
  if per_pixel != channels:  # frames of 3 channels as 4, frames to a power of two
    frames = channels // 3
    x = x.reshape(*x.shape[:3], frames, 3)
    x = jnp.pad(x, ((0, 0),) * 3 + ((0, per_pixel // 4 - frames), (0, 1)))
    x = x.reshape(*x.shape[:3], per_pixel)
  out_h, out_w = (x.shape[1] - 3) // 2 + 1, (x.shape[2] - 3) // 2 + 1
  blocks = space_to_depth(x, 2 * (out_h + 1), 2 * (out_w + 1))
  extra = _round_up(blocks.shape[-1], channel_multiple) - blocks.shape[-1]
  if extra:
    blocks = jnp.pad(blocks, ((0, 0), (0, 0), (0, 0), (0, extra)))
  return Blocks(blocks, channels, per_pixel)


def encoder_input(encoder: Encoder, obs: jax.Array) -> Blocks:
  """What `encoder` computes from uint8 observations before its first convolution.

  Center crop (if `encoder.input_size`), cast to `encoder.dtype`, /255, then
  `stride_two_blocks`. ``encoder.apply(p, encoder_input(encoder, obs))`` equals
  ``encoder.apply(p, obs)``; computing it once serves every pass over `obs`.

  Args:
    encoder: the `Encoder` (only its fields are read; no parameters).
    obs: uint8 (B, H, W, C).

  Returns:
    `Blocks` in `encoder.dtype`.
  """
  if encoder.input_size is not None:
    obs = center_crop(obs, encoder.input_size)
  return stride_two_blocks(obs.astype(encoder.dtype) / 255.0)


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


def space_to_depth_kernel(kernel: jax.Array) -> jax.Array:
  """The stride-1 kernel on 2×2 blocks equal to a stride-2 kernel on pixels.

  Args:
    kernel: (kh, kw, C_in, C_out), HWIO, of a stride-2 VALID convolution.

  Returns:
    (⌈kh/2⌉, ⌈kw/2⌉, 4·C_in, C_out): tap (p, q), input channel (2·a + b)·C_in + c
    is the old tap (2p + a, 2q + b) of channel c (zero past the old kernel), the
    channel order of `space_to_depth`.
  """
  kh, kw, c_in, c_out = kernel.shape
  bh, bw = (kh + 1) // 2, (kw + 1) // 2
  padded = jnp.pad(kernel, ((0, 2 * bh - kh), (0, 2 * bw - kw), (0, 0), (0, 0)))
  blocks = padded.reshape(bh, 2, bw, 2, c_in, c_out).transpose(0, 2, 1, 3, 4, 5)
  return blocks.reshape(bh, bw, 4 * c_in, c_out)


def space_to_depth(x: jax.Array, height: int, width: int) -> jax.Array:
  """(B, H, W, C) → (B, height/2, width/2, 4·C): 2×2 pixel blocks as channels.

  The image is first cropped or zero-padded to (height, width) (both even);
  block channel (2·a + b)·C + c holds pixel (2i + a, 2j + b), channel c.
  """
  x = x[:, :height, :width]
  x = jnp.pad(x, ((0, 0), (0, height - x.shape[1]), (0, width - x.shape[2]), (0, 0)))
  b, c = x.shape[0], x.shape[3]
  blocks = x.reshape(b, height // 2, 2, width // 2, 2, c).transpose(0, 1, 3, 2, 4, 5)
  return blocks.reshape(b, height // 2, width // 2, 4 * c)


def block_channel_multiple(dtype, platform: str | None = None) -> int:
  """The multiple `stride_two_blocks` pads the block channels to, with zero channels.

  Args:
    dtype: the blocks' dtype (the encoder's compute dtype).
    platform: the backend the convolution runs on (default: JAX's default backend).

  Returns:
    32 for 16-bit floats on GPUs: cuDNN's tensor-core kernels run the first layer
    on 64 channels faster than on 40 (benchmarks/results/training_h200.md, eleventh
    section); 8 otherwise, the channel multiple those kernels need.
  """
  platform = platform or jax.default_backend()
  return 32 if platform == "gpu" and jnp.dtype(dtype).itemsize == 2 else 8


def stride_one_on_blocks(platform: str | None = None) -> bool:
  """Whether `Encoder` computes its stride-1 layers on 2×2 blocks (`BlockConv`).

  Args:
    platform: the backend the convolutions run on (default: JAX's default backend).

  Returns:
    True on GPUs, where cuDNN runs the blocks' 4× channels faster than the pixels'
    (32 in the paper's encoder, in bfloat16 and in float32) although they take 16/9
    of the multiply-adds (benchmarks/results/training_h200.md, twenty-second
    section); False elsewhere (on CPUs the extra multiply-adds cost more than
    they save).
  """
  return (platform or jax.default_backend()) == "gpu"


def stride_one_block_kernel(kernel: jax.Array) -> jax.Array:
  """The 2×2 kernel on 2×2 blocks equal to a 3×3 stride-1 kernel on pixels.

  Output pixel (2i + a, 2j + b) of a VALID convolution reads input pixels
  (2i + a + u, 2j + b + v), u, v < 3, all inside blocks i…i + 1 and j…j + 1: input
  pixel (2p + q, 2r + s) of that window (block offset p, r; pixel q, s in the block)
  meets tap (2p + q − a, 2r + s − b), zero where that is outside 0…2.

  Args:
    kernel: (3, 3, C_in, C_out), HWIO.

  Returns:
    (2, 2, 4·C_in, 4·C_out): tap (p, r), input channel (2q + s)·C_in + c, output
    channel (2a + b)·C_out + d, the channel order of `space_to_depth`.
  """
  if kernel.shape[:2] != (3, 3):
    raise ValueError(f"expected a (3, 3, C_in, C_out) kernel, got shape {kernel.shape}")
  c_in, c_out = kernel.shape[2:]
  padded = jnp.pad(kernel, ((0, 1), (0, 1), (0, 0), (0, 0)))  # tap 3 reads zeros
  p, q, a = np.meshgrid(np.arange(2), np.arange(2), np.arange(2), indexing="ij")
  tap = 2 * p + q - a
  tap = np.where((tap >= 0) & (tap <= 2), tap, 3)  # per axis: (block, pixel in, pixel out)
  k = padded[tap[:, None, :, None, :, None], tap[None, :, None, :, None, :]]
  k = k.transpose(0, 1, 2, 3, 6, 4, 5, 7)  # (p, r, q, s, C_in, a, b, C_out)
  return k.reshape(2, 2, 4 * c_in, 4 * c_out)


class BlockConv(nn.Module):
  """A 3×3 stride-1 VALID convolution of images held as 2×2 blocks, to 2×2 blocks.

  Takes `space_to_depth` of (B, H, W, C_in) with H, W even, (B, H/2, W/2, 4·C_in),
  and gives `space_to_depth` of ``nn.Conv(features, (3, 3), padding="VALID")`` of
  it, (B, H/2 − 1, W/2 − 1, 4·features): the convolution's H − 2 by W − 2 pixels.
  (An odd side, padded by a zero pixel to be cut into blocks, gives one row or
  column more than the unpadded image's convolution, read partly from the padding;
  a chain of these layers carries it along the bottom or right edge, and
  `BlockDense` ignores it.) The parameters are nn.Conv's (names, shapes,
  initialisers); the kernel is applied as `stride_one_block_kernel`: a 2×2
  convolution on 4× the channels, 16/9 of the multiply-adds.

  Attributes:
    features: output channels (per pixel).
    dtype: compute dtype (None: promoted from the input and the parameters);
      the parameters are float32.
    kernel_init: initialiser of the (3, 3, C_in, features) kernel.
    bias_init: initialiser of the bias.
  """
  features: int
  dtype: str | None = None
  kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()
  bias_init: nn.initializers.Initializer = nn.initializers.zeros_init()

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Maps (B, h, w, 4·C_in) blocks to (B, h − 1, w − 1, 4·features) blocks."""
    if x.shape[-1] % 4:
      raise ValueError(f"expected 2×2 blocks (4·C_in channels), got shape {x.shape}")
    x, kernel, bias = _conv3x3_params(self, x, x.shape[-1] // 4)
    y = jax.lax.conv_general_dilated(x, stride_one_block_kernel(kernel), (1, 1), "VALID",
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return y + jnp.tile(bias, 4)


class BlockDense(nn.Module):
  """``nn.Dense`` of flattened (B, H, W, C) images, read from their 2×2 blocks.

  Takes (B, h, w, 4·C) blocks of which the first H × W pixels are the image (the
  rest, e.g. the row and column an odd side's padding adds to a chain of
  `BlockConv`, meet zero kernel rows) and gives
  ``nn.Dense(features)`` of the image flattened in (H, W, C) order, with nn.Dense's
  parameters (names, shapes, initialisers): the kernel's rows are laid out as the
  blocks are instead of the blocks being cut back into pixels.

  Attributes:
    features: output size.
    image_shape: (H, W), with H ≤ 2h and W ≤ 2w.
    dtype: compute dtype (None: promoted from the input and the parameters);
      the parameters are float32.
    kernel_init: initialiser of the (H·W·C, features) kernel.
    bias_init: initialiser of the bias.
  """
  features: int
  image_shape: tuple[int, int]
  dtype: str | None = None
  kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()
  bias_init: nn.initializers.Initializer = nn.initializers.zeros_init()

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Maps (B, h, w, 4·C) blocks to (B, features)."""
    (height, width), (b, h, w, c4) = self.image_shape, x.shape
    if c4 % 4 or height > 2 * h or width > 2 * w:
      raise ValueError(f"blocks of shape {x.shape} do not hold a {height}×{width} image")
    c = c4 // 4
    kernel = self.param("kernel", self.kernel_init, (height * width * c, self.features),
                        jnp.float32)
    bias = self.param("bias", self.bias_init, (self.features,), jnp.float32)
    x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
    rows = jnp.pad(kernel.reshape(height, width, c, self.features),
                   ((0, 2 * h - height), (0, 2 * w - width), (0, 0), (0, 0)))
    rows = rows.reshape(h, 2, w, 2, c, self.features).transpose(0, 2, 1, 3, 4, 5)
    return x.reshape(b, -1) @ rows.reshape(-1, self.features) + bias


def _conv3x3_params(module: nn.Module, x: jax.Array, in_channels: int | None = None):
  """A 3×3 layer's float32 parameters, as nn.Conv names and shapes them
  ({"kernel": (3, 3, C_in, features), "bias": (features,)}), and the input and
  both cast to the module's compute dtype (``nn.dtypes.promote_dtype``).

  Called inside the `nn.compact` method of a module with `features`, `dtype`,
  `kernel_init` and `bias_init` (`StrideTwoConv`, `BlockConv`,
  `StrideTwoConvTranspose`); C_in is `in_channels`, by default x's last axis.
  """
  c_in = x.shape[-1] if in_channels is None else in_channels
  kernel = module.param("kernel", module.kernel_init, (3, 3, c_in, module.features),
                        jnp.float32)
  bias = module.param("bias", module.bias_init, (module.features,), jnp.float32)
  return nn.dtypes.promote_dtype(x, kernel, bias, dtype=module.dtype)


class StrideTwoConv(nn.Module):
  """A 3×3 stride-2 VALID convolution, computed as a stride-1 one on 2×2 blocks.

  The same function of the same parameters, with the same names, shapes and
  initialisers ({"kernel": (3, 3, C_in, features), "bias": (features,)}), as
  ``nn.Conv(features, (3, 3), strides=(2, 2), padding="VALID")``. Per axis,
  y[o] = Σ_k x[2o + k]·K[k], k < 3; writing k = 2p + a (a < 2) and padding K with a
  zero fourth tap, y[o] = Σ_p X[o + p]·K'[p] with X[i] = (x[2i], x[2i + 1]) the
  blocks (`space_to_depth`) and K'[p] = (K[2p], K[2p + 1]): a 2×2 stride-1
  convolution over 4·C_in channels (`space_to_depth_kernel`). Why: the encoder's
  first layer sees 9 input channels, for which cuDNN picks a generic, slow kernel on
  GPUs; 36 channels, padded with zero channels (`block_channel_multiple`), go to
  its tensor-core kernels (profiles: benchmarks/results/learner_h100.md).

  Attributes:
    features: output channels.
    dtype: compute dtype (None: promoted from the input and the parameters);
      the parameters are float32.
    precision: as `lax.conv_general_dilated`'s.
    kernel_init: initialiser of the (3, 3, C_in, features) kernel.
    bias_init: initialiser of the bias.
  """
  features: int
  dtype: str | None = None
  precision: jax.lax.PrecisionLike = None
  kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()
  bias_init: nn.initializers.Initializer = nn.initializers.zeros_init()

  @nn.compact
  def __call__(self, x: jax.Array | Blocks) -> jax.Array:
    """Maps (B, H, W, C_in) to (B, (H − 3)//2 + 1, (W − 3)//2 + 1, features).

    `x` may also be `stride_two_blocks` of the input (the same result; its dtype
    is then kept as given, as `dtype` would make it).
    """
    blocks = x if isinstance(x, Blocks) else stride_two_blocks(x)
    data, kernel, bias = _conv3x3_params(self, blocks.data, blocks.channels)
    if blocks.pixel_channels != blocks.channels:  # kernel rows where the blocks' channels are
      kernel = jnp.zeros(kernel.shape[:2] + (blocks.pixel_channels,) + kernel.shape[3:],
                         kernel.dtype).at[:, :, blocks.slots].set(kernel)
    block_kernel = space_to_depth_kernel(kernel)
    extra = data.shape[-1] - block_kernel.shape[2]  # the blocks' zero channels
    if extra:
      block_kernel = jnp.pad(block_kernel, ((0, 0), (0, 0), (0, extra), (0, 0)))
    y = jax.lax.conv_general_dilated(data, block_kernel, (1, 1), "VALID",
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                     precision=self.precision)
    return y + bias


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

  The stride-2 output layer is `StrideTwoConvTranspose`: the same function, with
  the same parameters (``out/kernel`` (3, 3, channels, out_channels), ``out/bias``)
  and initialisers, as ``nn.ConvTranspose(out_channels, (3, 3), strides=(2, 2),
  padding=((2, after), (2, after)))``, but computed in phases (sub-pixel): one
  2×2 stride-1 convolution giving each of the four output-pixel parities, then
  interleaved. XLA computes the transposed convolution by convolving the
  zero-dilated input, which it materialises (three quarters of it zeros); the
  phases never dilate.

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
    x = StrideTwoConvTranspose(self.out_channels, after=after, kernel_init=_DENSE_INIT,
                               dtype=self.dtype, name="out")(x)
    return x.astype(jnp.float32)


# Which tap of the 3-tap kernel each of the two taps of a phase's 2-tap kernel
# is, per output parity; 3 indexes a zero tap. See `StrideTwoConvTranspose`.
_PHASE_TAPS = np.array([[0, 2],   # even outputs: x[p − 1]·K[0] + x[p]·K[2]
                        [3, 1]])  # odd outputs:  x[p]·K[1]


def phase_kernel(kernel: jax.Array) -> jax.Array:
  """The 2×2 kernel whose output channels are the four phases of a 3×3 one.

  Args:
    kernel: (3, 3, C_in, C_out), HWIO, of a stride-2 transposed convolution
      with padding 2 before (see `StrideTwoConvTranspose`).

  Returns:
    (2, 2, C_in, 4·C_out): channel (2·a + b)·C_out + c is output channel c of
    phase (row parity a, column parity b); its taps are those of `_PHASE_TAPS`
    (zeros where the phase has only one tap per axis).
  """
  c_in, c_out = kernel.shape[2:]
  padded = jnp.pad(kernel, ((0, 1), (0, 1), (0, 0), (0, 0)))  # tap 3 is zero
  rows = _PHASE_TAPS[:, :, None, None]  # (a, u, 1, 1)
  cols = _PHASE_TAPS[None, None, :, :]  # (1, 1, b, v)
  taps = padded[rows, cols]  # (a, u, b, v, C_in, C_out)
  return taps.transpose(1, 3, 4, 0, 2, 5).reshape(2, 2, c_in, 4 * c_out)


class StrideTwoConvTranspose(nn.Module):
  """A 3×3 stride-2 transposed convolution, padded (2, after), computed in phases.

  The same function of the same parameters, with the same names, shapes and
  initialisers ({"kernel": (3, 3, C_in, features), "bias": (features,)}), as
  ``nn.ConvTranspose(features, (3, 3), strides=(2, 2), padding=((2, after),
  (2, after)))``, i.e. ``lax.conv_general_dilated`` of the input dilated by 2
  (zeros between pixels) with the kernel unflipped, but without the dilation.

  Per axis, with xd the dilated input (xd[2i] = x[i], zero at odd positions) and
  x = 0 out of range: y[o] = Σ_k xd[o + k − 2]·K[k], so y[2p] = x[p − 1]·K[0] +
  x[p]·K[2] and y[2p + 1] = x[p]·K[1]. Padding x by one on each side, the even
  outputs are a 2-tap VALID correlation with [K[0], K[2]] and the odd ones a
  2-tap correlation with [0, K[1]], s + 1 outputs each for an input side s. In
  2-D the four (row parity, column parity) phases are one stride-1 convolution
  with a 2×2 kernel of 4·features channels (`phase_kernel`); interleaving them
  (depth to space) gives 2s + 2 rows and columns, cropped (or, for after > 3,
  zero-extended) to the transposed convolution's 2s − 1 + after.

  Attributes:
    features: output channels.
    after: padding after each spatial axis (the Decoder's: 2 for odd sides, 3
      for even ones); the output side is 2·input side − 1 + after.
    dtype: compute dtype (None: promoted from the input and the parameters);
      the parameters are float32.
    precision: as `lax.conv_general_dilated`'s.
    kernel_init: initialiser of the (3, 3, C_in, features) kernel.
    bias_init: initialiser of the bias.
  """
  features: int
  after: int
  dtype: str | None = None
  precision: jax.lax.PrecisionLike = None
  kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()
  bias_init: nn.initializers.Initializer = nn.initializers.zeros_init()

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Maps (B, H, W, C_in) to (B, 2H − 1 + after, 2W − 1 + after, features)."""
    if x.ndim != 4:
      raise ValueError(f"expected (B, H, W, C) inputs, got shape {x.shape}")
    x, kernel, bias = _conv3x3_params(self, x)
    batch, height, width, _ = x.shape
    out_h, out_w = 2 * height - 1 + self.after, 2 * width - 1 + self.after
    if out_h < 1 or out_w < 1:
      raise ValueError(f"padding after {self.after} leaves no output for {x.shape}")
    y = jax.lax.conv_general_dilated(x, phase_kernel(kernel), (1, 1), ((1, 1), (1, 1)),
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                     precision=self.precision)
    # (B, H + 1, W + 1, [a, b, c]) → (B, [H + 1, a], [W + 1, b], c): y[2p + a, 2q + b].
    y = y.reshape(batch, height + 1, width + 1, 2, 2, self.features)
    y = y.transpose(0, 1, 3, 2, 4, 5).reshape(batch, 2 * height + 2, 2 * width + 2,
                                              self.features)
    y = y[:, :out_h, :out_w]
    if out_h > y.shape[1] or out_w > y.shape[2]:  # padding past the last input pixel
      y = jnp.pad(y, ((0, 0), (0, out_h - y.shape[1]), (0, out_w - y.shape[2]), (0, 0)))
    return y + bias


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
