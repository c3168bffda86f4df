"""The encoder's convolutions and dense layer, and the decoder's output layer, each
exactly its flax layer but computed in a layout chosen for speed.

`Conv` is ``nn.Conv(features, (3, 3), strides, padding="VALID")`` and `Dense` is
``nn.Dense(features)`` of the images flattened in (H, W, C) order: the same
parameter names, shapes, dtypes and initial values (one key initialises them as
it does the flax layer), the same function of them up to float rounding. `Conv`
has two implementations, picked by ``impl`` as MJX picks its backends:

- ``"pixels"``: (B, H, W, C) arrays and ``lax.conv_general_dilated``, as flax.
- ``"blocks"``: 2×2 pixel blocks. The stride-2 layer is a stride-1 convolution
  over the blocks of its input (`stride_two_conv`), 4·C_in channels padded with
  zero channels to tensor-core sizes; stride-1 layers map `Blocks` to `Blocks`
  with a 2×2 kernel over 4× the channels (`block_conv`, 16/9 of the
  multiply-adds), so a chain of them never cuts the blocks back into pixels;
  `Dense` reads `Blocks` with its kernel rows laid out as the blocks are
  (`block_dense`).

`default_impl` is "blocks" on GPUs, where cuDNN runs them faster
(benchmarks/results/README.md), "pixels" elsewhere. Every layer and `to_pixels`
take images in either layout (an array or `Blocks`); `Conv` returns its output in
its implementation's layout, and elementwise functions apply to either with
`jax.tree.map` (`Blocks.data` is its only array). `StrideTwoConvTranspose` is
``nn.ConvTranspose(features, (3, 3), strides=(2, 2), padding=((2, a), (2, a)))``
computed in phases, without the zero-dilated input XLA would build.
"""

from __future__ import annotations

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

IMPLS = ("pixels", "blocks")
"""What `Conv.impl` accepts (None: `default_impl`)."""

_DIMS = ("NHWC", "HWIO", "NHWC")


def default_impl(platform: str | None = None) -> str:
  """The implementation `Conv` uses when its ``impl`` is None.

  Args:
    platform: the backend the layers run on (default: JAX's default backend).

  Returns:
    "blocks" on GPUs, "pixels" elsewhere (on CPUs the blocks' extra multiply-adds
    cost more than they save).
  """
  return "blocks" if (platform or jax.default_backend()) == "gpu" else "pixels"


def resolve_impl(impl: str | None) -> str:
  """`impl`, or `default_impl()` for None; raises ValueError for another name."""
  if impl is None:
    return default_impl()
  if impl not in IMPLS:
    raise ValueError(f"impl must be one of {', '.join(IMPLS)} (or None), got {impl!r}")
  return impl


# --------------------------------------------------------------------------- #
# The block layout.
# --------------------------------------------------------------------------- #


@flax.struct.dataclass
class Blocks:
  """A batch of (H, W, C) images held as 2×2 pixel blocks.

  Attributes:
    data: (B, ⌈H/2⌉, ⌈W/2⌉, 4·C): block (i, j), channel (2a + b)·C + c holds
      pixel (2i + a, 2j + b), channel c (`space_to_depth`). The pixels past the
      image (the extra row or column of an odd side) hold arbitrary values.
    height: H (static).
    width: W (static).
  """
  data: jax.Array
  height: int = flax.struct.field(pytree_node=False)
  width: int = flax.struct.field(pytree_node=False)

  @property
  def channels(self) -> int:
    """C, the channels per pixel."""
    return self.data.shape[-1] // 4

  @property
  def dtype(self) -> jnp.dtype:
    """The data's dtype."""
    return self.data.dtype

  @property
  def shape(self) -> tuple[int, int, int, int]:
    """(B, H, W, C), the shape of the images as pixels."""
    return (self.data.shape[0], self.height, self.width, self.channels)


def _round_up(n: int, multiple: int) -> int:
  """The least multiple of `multiple` that is ≥ n."""
  return -(-n // multiple) * multiple


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


def to_blocks(x: jax.Array | Blocks) -> Blocks:
  """(B, H, W, C) images as `Blocks` (an odd side padded by a zero pixel); `Blocks` as given."""
  if isinstance(x, Blocks):
    return x
  if x.ndim != 4:
    raise ValueError(f"expected (B, H, W, C) images, got shape {x.shape}")
  height, width = x.shape[1:3]
  return Blocks(space_to_depth(x, _round_up(height, 2), _round_up(width, 2)), height, width)


def to_pixels(x: jax.Array | Blocks) -> jax.Array:
  """The (B, H, W, C) images `x` holds (an array is returned as given)."""
  if not isinstance(x, Blocks):
    return x
  b, h, w, c4 = x.data.shape
  pixels = x.data.reshape(b, h, w, 2, 2, c4 // 4).transpose(0, 1, 3, 2, 4, 5)
  return pixels.reshape(b, 2 * h, 2 * w, c4 // 4)[:, :x.height, :x.width]


# --------------------------------------------------------------------------- #
# Stride 2 on the blocks of its input.
# --------------------------------------------------------------------------- #


def block_channel_multiple(dtype, platform: str | None = None) -> int:
  """The multiple `stride_two_blocks` pads the block channels to, with zero channels.

  Args:
    dtype: the blocks' dtype (the layer's compute dtype).
    platform: the backend the convolution runs on (default: JAX's default backend).

  Returns:
    32 for 16-bit floats on GPUs, where cuDNN's tensor-core kernels run the first
    layer faster on 64 channels than on 40; 8 otherwise, the channel multiple
    those kernels need.
  """
  platform = platform or jax.default_backend()
  return 32 if platform == "gpu" and jnp.dtype(dtype).itemsize == 2 else 8


def pixel_layout(channels: int, channel_multiple: int) -> int:
  """The channels per pixel `stride_two_blocks` lays an image's C channels out in.

  Frames of 3 channels (C = 3·S) take 4 channels each, and S is rounded up to a
  power of two, when the blocks then have no more channels than C in order padded
  at the end: every block channel's pixel, frame and colour are then bit fields of
  its index. Otherwise C.

  Args:
    channels: C, the image's channels (3 per frame for frame stacks).
    channel_multiple: the multiple the block channels are padded to.

  Returns:
    P, the channels per pixel: 4·(S rounded up to a power of two), or C.
  """
  if channels % 3:
    return channels
  grouped = 4 * (1 << (channels // 3 - 1).bit_length())
  padded = lambda per_pixel: _round_up(4 * per_pixel, channel_multiple)
  return grouped if padded(grouped) <= padded(channels) else channels


def pixel_slots(channels: int, pixel_channels: int) -> np.ndarray:
  """Where each image channel sits among a pixel's P channels (`pixel_layout`).

  Returns:
    int (C,): c itself if P = C, else 4·(c // 3) + c % 3.
  """
  c = np.arange(channels)
  return c if pixel_channels == channels else 4 * (c // 3) + c % 3


def stride_two_blocks(x: jax.Array, channel_multiple: int) -> tuple[jax.Array, int]:
  """The blocks `stride_two_conv` convolves, for (B, H, W, C) images (H, W ≥ 3).

  The channels laid out per pixel (`pixel_layout`), `space_to_depth` to
  (out_h + 1, out_w + 1) blocks (out = (side − 3)//2 + 1, the convolution's output
  side), zero channels appended up to a multiple of `channel_multiple`; the dtype
  is kept. Zero channels meet zero kernel rows: the convolution is unchanged.

  Returns:
    (blocks (B, out_h + 1, out_w + 1, 4·P rounded up), P the channels per pixel).
  """
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
  return blocks, per_pixel


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


def stride_two_conv(x: jax.Array, kernel: jax.Array, channel_multiple: int | None = None,
                    precision: jax.lax.PrecisionLike = None) -> jax.Array:
  """A 3×3 stride-2 VALID convolution (no bias), computed as a stride-1 one on 2×2 blocks.

  Per axis, y[o] = Σ_k x[2o + k]·K[k], k < 3; writing k = 2p + a (a < 2) and
  padding K with a zero fourth tap, y[o] = Σ_p X[o + p]·K'[p] with X[i] = (x[2i],
  x[2i + 1]) the blocks and K'[p] = (K[2p], K[2p + 1]): a 2×2 stride-1
  convolution over 4·C_in channels (`space_to_depth_kernel`), which cuDNN runs on
  its tensor-core kernels where the 9 channels of a 3-frame stack would get a
  generic one.

  Args:
    x: (B, H, W, C_in), H, W ≥ 3, in the compute dtype.
    kernel: (3, 3, C_in, C_out), HWIO, in the compute dtype.
    channel_multiple: the blocks' channel multiple (default:
      `block_channel_multiple` of x's dtype).
    precision: as `lax.conv_general_dilated`'s.

  Returns:
    (B, (H − 3)//2 + 1, (W − 3)//2 + 1, C_out).
  """
  if x.ndim != 4 or min(x.shape[1:3]) < 3:
    raise ValueError(f"expected (B, H, W, C) inputs with H, W ≥ 3, got shape {x.shape}")
  if channel_multiple is None:
    channel_multiple = block_channel_multiple(x.dtype)
  channels = x.shape[-1]
  data, per_pixel = stride_two_blocks(x, channel_multiple)
  if per_pixel != channels:  # kernel rows where the blocks' channels are
    kernel = jnp.zeros(kernel.shape[:2] + (per_pixel,) + kernel.shape[3:],
                       kernel.dtype).at[:, :, pixel_slots(channels, per_pixel)].set(kernel)
  block_kernel = space_to_depth_kernel(kernel)
  extra = data.shape[-1] - block_kernel.shape[2]  # the blocks' zero channels
  if extra:
    block_kernel = jnp.pad(block_kernel, ((0, 0), (0, 0), (0, extra), (0, 0)))
  return jax.lax.conv_general_dilated(data, block_kernel, (1, 1), "VALID",
                                      dimension_numbers=_DIMS, precision=precision)


# --------------------------------------------------------------------------- #
# Stride 1 and the dense layer on blocks.
# --------------------------------------------------------------------------- #


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


def block_conv(x: Blocks, kernel: jax.Array,
               precision: jax.lax.PrecisionLike = None) -> Blocks:
  """A 3×3 stride-1 VALID convolution (no bias) from `Blocks` to `Blocks`.

  (B, H, W, C_in) images as ⌈H/2⌉ × ⌈W/2⌉ blocks give their (H − 2, W − 2)
  convolution as ⌈H/2⌉ − 1 × ⌈W/2⌉ − 1 blocks: a 2×2 convolution with
  `stride_one_block_kernel` (an odd side's extra row or column is computed partly
  from the padding, and stays past the image).

  Args:
    x: `Blocks` of images with H, W ≥ 3, in the compute dtype.
    kernel: (3, 3, C_in, C_out), HWIO, in the compute dtype.
    precision: as `lax.conv_general_dilated`'s.

  Returns:
    `Blocks` of (B, H − 2, W − 2, C_out).
  """
  if min(x.height, x.width) < 3:
    raise ValueError(f"expected images with H, W ≥ 3, got shape {x.shape}")
  y = jax.lax.conv_general_dilated(x.data, stride_one_block_kernel(kernel), (1, 1), "VALID",
                                   dimension_numbers=_DIMS, precision=precision)
  return Blocks(y, x.height - 2, x.width - 2)


def block_dense(x: Blocks, kernel: jax.Array,
                precision: jax.lax.PrecisionLike = None) -> jax.Array:
  """x's images flattened in (H, W, C) order times `kernel`, read from the blocks.

  The kernel's rows are laid out as the blocks are (zero rows for the pixels past
  the image) instead of the blocks being cut back into pixels.

  Args:
    x: `Blocks` of (B, H, W, C) images, in the compute dtype.
    kernel: (H·W·C, F), in the compute dtype.
    precision: as `jnp.matmul`'s.

  Returns:
    (B, F).
  """
  (b, h, w, c4), (height, width), c = x.data.shape, (x.height, x.width), x.channels
  features = kernel.shape[-1]
  rows = jnp.pad(kernel.reshape(height, width, c, features),
                 ((0, 2 * h - height), (0, 2 * w - width), (0, 0), (0, 0)))
  rows = rows.reshape(h, 2, w, 2, c, features).transpose(0, 2, 1, 3, 4, 5)
  return jnp.matmul(x.data.reshape(b, -1), rows.reshape(-1, features), precision=precision)


# --------------------------------------------------------------------------- #
# The layers.
# --------------------------------------------------------------------------- #


def _params(module: nn.Module, kernel_shape: tuple[int, ...]):
  """A layer's float32 {"kernel": kernel_shape, "bias": (features,)}, as flax names,
  shapes and initialises them (kernel first, from `kernel_init`, then the bias)."""
  kernel = module.param("kernel", module.kernel_init, kernel_shape, jnp.float32)
  bias = module.param("bias", module.bias_init, (module.features,), jnp.float32)
  return kernel, bias


class Conv(nn.Module):
  """``nn.Conv(features, (3, 3), strides=(s, s), padding="VALID")`` in either layout.

  Parameters {"kernel": (3, 3, C_in, features), "bias": (features,)}, float32,
  initialised as nn.Conv's; the compute dtype as nn.Conv's ``dtype``.

  Attributes:
    features: output channels.
    strides: 1 or 2 (both axes).
    impl: "pixels" (an array in, an array out), "blocks" (`Blocks` out: stride 2 by
      `stride_two_conv`, stride 1 by `block_conv`), or None: `default_impl()`.
      Either takes an array or `Blocks` (converted to its layout).
    dtype: compute dtype (None: promoted from the input and the parameters).
    precision: as `lax.conv_general_dilated`'s.
    kernel_init: initialiser of the (3, 3, C_in, features) kernel.
    bias_init: initialiser of the bias.
  """
  features: int
  strides: int = 1
  impl: str | None = None
  dtype: str | None = None
  precision: jax.lax.PrecisionLike = None
  kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()
  bias_init: nn.initializers.Initializer = nn.initializers.zeros_init()

  @nn.compact
  def __call__(self, x: jax.Array | Blocks) -> jax.Array | Blocks:
    """Maps (B, H, W, C_in) images to (B, (H − 3)//s + 1, (W − 3)//s + 1, features)."""
    if self.strides not in (1, 2):
      raise ValueError(f"Conv.strides must be 1 or 2, got {self.strides!r}")
    impl = resolve_impl(self.impl)
    c_in = x.shape[-1]
    kernel, bias = _params(self, (3, 3, c_in, self.features))
    if impl == "blocks" and self.strides == 1:
      data, kernel, bias = nn.dtypes.promote_dtype(to_blocks(x).data, kernel, bias,
                                                   dtype=self.dtype)
      y = block_conv(Blocks(data, x.shape[1], x.shape[2]), kernel, self.precision)
      return y.replace(data=y.data + jnp.tile(bias, 4))
    x, kernel, bias = nn.dtypes.promote_dtype(to_pixels(x), kernel, bias, dtype=self.dtype)
    if impl == "blocks":  # stride 2
      return to_blocks(stride_two_conv(x, kernel, precision=self.precision) + bias)
    y = jax.lax.conv_general_dilated(x, kernel, (self.strides,) * 2, "VALID",
                                     dimension_numbers=_DIMS, precision=self.precision)
    return y + bias


class Dense(nn.Module):
  """``nn.Dense(features)`` of (B, H, W, C) images flattened in (H, W, C) order.

  Parameters {"kernel": (H·W·C, features), "bias": (features,)}, float32,
  initialised as nn.Dense's. An array input is flattened; `Blocks` are read as
  they are (`block_dense`).

  Attributes:
    features: output size.
    dtype: compute dtype (None: promoted from the input and the parameters).
    precision: as `jnp.matmul`'s.
    kernel_init: initialiser of the (H·W·C, features) kernel.
    bias_init: initialiser of the bias.
  """
  features: int
  dtype: str | None = None
  precision: jax.lax.PrecisionLike = None
  kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()
  bias_init: nn.initializers.Initializer = nn.initializers.zeros_init()

  @nn.compact
  def __call__(self, x: jax.Array | Blocks) -> jax.Array:
    """Maps (B, …) to (B, features)."""
    kernel, bias = _params(self, (int(np.prod(x.shape[1:])), self.features))
    if isinstance(x, Blocks):
      data, kernel, bias = nn.dtypes.promote_dtype(x.data, kernel, bias, dtype=self.dtype)
      return block_dense(x.replace(data=data), kernel, self.precision) + bias
    x, kernel, bias = nn.dtypes.promote_dtype(x.reshape(x.shape[0], -1), kernel, bias,
                                              dtype=self.dtype)
    return jnp.matmul(x, kernel, precision=self.precision) + bias


# --------------------------------------------------------------------------- #
# The decoder's stride-2 transposed convolution, in phases.
# --------------------------------------------------------------------------- #


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
    kernel, bias = _params(self, (3, 3, x.shape[-1], self.features))
    x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
    batch, height, width, _ = x.shape
    out_h, out_w = 2 * height - 1 + self.after, 2 * width - 1 + self.after
    if out_h < 1 or out_w < 1:
      raise ValueError(f"padding after {self.after} leaves no output for {x.shape}")
    y = jax.lax.conv_general_dilated(x, phase_kernel(kernel), (1, 1), ((1, 1), (1, 1)),
                                     dimension_numbers=_DIMS, precision=self.precision)
    # (B, H + 1, W + 1, [a, b, c]) → (B, [H + 1, a], [W + 1, b], c): y[2p + a, 2q + b].
    y = y.reshape(batch, height + 1, width + 1, 2, 2, self.features)
    y = y.transpose(0, 1, 3, 2, 4, 5).reshape(batch, 2 * height + 2, 2 * width + 2,
                                              self.features)
    y = y[:, :out_h, :out_w]
    if out_h > y.shape[1] or out_w > y.shape[2]:  # padding past the last input pixel
      y = jnp.pad(y, ((0, 0), (0, out_h - y.shape[1]), (0, out_w - y.shape[2]), (0, 0)))
    return y + bias
