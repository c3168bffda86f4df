"""The JAX ray caster as one fused GPU kernel (Pallas on Triton).

Under XLA the ray caster (`jax_render`) is many mid-sized kernels per chunk of
envs, and its time goes to moving per-pixel arrays between them. Here the same
per-pixel code, `jax_render.trace_pixels`, runs inside one Pallas kernel: each
program draws one block of `block` pixels of one env, with every intermediate in
registers; only the env's packed numbers (`jax_render.pack_env`, computed by XLA
before the kernel, a few hundred floats per env), the texture bank and the final
colours touch memory.

The kernel reads memory through `RefReader`, the kernel-side twin of
`jax_render.ArrayReader`: scalars of the env's packed numbers, per-pixel gathers
of them by object id, and texel gathers. Nothing of the per-pixel math is written
twice; the frames equal `jax_render.render`'s up to float rounding (tested on the
CPU in Pallas' interpret mode, which runs the kernel's code without a GPU).

Each program also skips what none of its pixels needs (`skip_empty`, the default:
the opaque shading of an all-sky block, the sky of an all-surface block, the floor's
reflection without floor pixels, the transparent layers without transparent hits).

`python -m dmcr_jax.benchmarks.jax_render --mode check` compares the kernel's frames with
the XLA path's on a GPU; benchmarks/results/jax_render_h100.md holds that check, the
frames/s of both paths and the kernel's compile time, which is its cost (the
per-pixel code is unrolled over the scene's objects).
"""

from __future__ import annotations

from typing import Mapping

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from dmcr_jax.visuals.jax_render_pack import Layout, look_layout, pack_env
from dmcr_jax.visuals.jax_render_scene import BodyPoses, DeviceLook, Scene
from dmcr_jax.visuals.jax_render_trace import image_from_planes, trace_pixels

BLOCK = 128
"""Pixels per kernel program (a power of two, as Triton's blocks must be)."""
NUM_WARPS = 4
"""Warps per program: with 128 pixels, one pixel per GPU thread."""
SKIP_EMPTY = True
"""Programs skip the work none of their pixels needs (module doc; same frames)."""


class RefReader:
  """`jax_render.ArrayReader`'s reads from a kernel's memory references, for env
  `env` (a program id)."""

  def __init__(self, env, floats, ints, texels, skies):
    self.env, self.floats, self.ints, self.texels, self.skies = (
        env, floats, ints, texels, skies)

  def f(self, i: int):
    return self.floats[self.env, i]

  def f_at(self, i: int, index):
    return self.floats[self.env, i + index]

  def i(self, i: int):
    return self.ints[self.env, i]

  def i_at(self, i: int, index):
    return self.ints[self.env, i + index]

  def texel(self, index):
    return self.texels[index]

  def sky(self, index):
    return self.skies[index]

  def fence(self, values):
    """`values` as given: a kernel program has no XLA fusion to fence."""
    return values


def _compiler_params(num_warps: int):
  from jax.experimental.pallas import triton as pl_triton
  return pl_triton.CompilerParams(num_warps=num_warps, num_stages=1)


def trace_batch(layout: Layout, floats: jax.Array, ints: jax.Array, texels: jax.Array,
                skies: jax.Array, *, height: int, width: int, shadows: bool,
                reflection: bool, supersample: int = 1, block: int = BLOCK,
                num_warps: int = NUM_WARPS, skip_empty: bool = SKIP_EMPTY,
                interpret: bool = False):
  """Colour planes and object ids of N envs' rays in one kernel.

  Args:
    layout: the scene's `jax_render.Layout`.
    floats, ints: (N, …) every env's packed numbers (`jax_render.pack_env`, vmapped).
    texels, skies: the scene's floor texels and skies, flattened (uint8).
    height, width, shadows, reflection, supersample: as `jax_render.render`.
    block: pixels per program (power of two).
    num_warps: Triton warps per program.
    skip_empty: each program skips the work none of its pixels needs
      (`trace_pixels`' `skip_empty`; same frames, module doc).
    interpret: run the kernel's code without a GPU (Pallas' interpreter).

  Returns:
    float32 (N, 3, P′) colours in [0, 1] and int32 (N, P′) object ids (−1: none),
    P′ = the ray count H·s·W·s rounded up to a multiple of `block`.
  """
  if block & (block - 1):
    raise ValueError(f"block must be a power of two, not {block}")
  n = floats.shape[0]
  rays = height * supersample * width * supersample
  blocks = -(-rays // block)
  padded = blocks * block

  def kernel(floats_ref, ints_ref, texels_ref, skies_ref, r_ref, g_ref, b_ref, seg_ref):
    env, blk = pl.program_id(0), pl.program_id(1)
    start = blk * block
    pix = start + jnp.arange(block, dtype=jnp.int32)
    reader = RefReader(env, floats_ref, ints_ref, texels_ref, skies_ref)
    (r, g, b), seg = trace_pixels(layout, reader, pix, height=height, width=width,
                                  shadows=shadows, reflection=reflection,
                                  supersample=supersample, running=True,
                                  skip_empty=skip_empty)
    at = (env, pl.ds(start, block))
    r_ref[at] = r
    g_ref[at] = g
    b_ref[at] = b
    seg_ref[at] = seg

  plane = jax.ShapeDtypeStruct((n, padded), jnp.float32)
  r, g, b, seg = pl.pallas_call(
      kernel, grid=(n, blocks),
      out_shape=(plane, plane, plane, jax.ShapeDtypeStruct((n, padded), jnp.int32)),
      compiler_params=None if interpret else _compiler_params(num_warps),
      interpret=interpret, name="dmcr_ray_cast")(floats, ints, texels, skies)
  return jnp.stack([r, g, b], axis=1), seg


def render_batch(scene: Scene, bp: BodyPoses, look: DeviceLook,
                 variables: Mapping[str, jax.Array] | None = None, *, height: int = 84,
                 width: int = 84, shadows: bool = True, reflection: bool = True,
                 supersample: int = 1, block: int = BLOCK, num_warps: int = NUM_WARPS,
                 skip_empty: bool = SKIP_EMPTY, interpret: bool = False) -> jax.Array:
  """`jax_render.render_batch` in one fused kernel: uint8 (N, H, W, 3).

  Args:
    scene, bp, look, variables: as `jax_render.render_batch` (batched).
    height, width, shadows, reflection, supersample: as `jax_render.render`.
    block, num_warps, skip_empty, interpret: as `trace_batch`.
  """
  pack = jax.vmap(pack_env, in_axes=(None, 0, 0, 0 if variables else None))
  floats, ints = pack(scene, bp, look, variables or None)
  colour, _ = trace_batch(look_layout(scene, look), floats, ints, scene.floor_texels.reshape(-1),
                          scene.skies.reshape(-1), height=height, width=width,
                          shadows=shadows, reflection=reflection, supersample=supersample,
                          block=block, num_warps=num_warps, skip_empty=skip_empty,
                          interpret=interpret)
  return image_from_planes(colour, height, width, supersample)
