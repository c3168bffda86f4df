"""A JAX ray caster for DMCR frames: MuJoCo's picture computed on the accelerator.

`render(scene, poses, look)` draws one env's frame (uint8 H × W × 3) from its body
poses (`jax_render_scene.poses(mjx_data)`) and its look (`DeviceLook`). It is a
pure, jittable function written for one env; batch it with `jax.vmap` (or use
`render_batch`). The scene (`jax_render_scene.build_scene`) holds the geoms and
sites MuJoCo's default camera draws, the lights and the texture bank on device.

What it reproduces of MuJoCo's fixed-function renderer (render_gl3.c, 3.x):
* camera: MuJoCo's fixed / track / trackcom modes from the look's camera fields,
  vertical field of view `fovy`, the image's aspect, pixel centres, znear clip;
* geometry: analytic nearest hits of planes (finite or infinite, front side),
  spheres, ellipsoids, capsules, cylinders (with caps) and boxes;
* shading, per pixel (MuJoCo lights per vertex): the headlight (a directional
  light along the camera's forward axis) and the model's lights (directional or
  spot with cutoff, exponent and attenuation; the light a look moves takes the
  look's diffuse and specular colour), each with ambient, diffuse and specular
  terms (local viewer, Blinn half vector, GL exponent 128 × shininess),
  material emission; colours clamp per pass as in GL;
* shadows (`shadows=True`): the shadow-casting light lights only the points a
  ray towards it reaches without hitting a geom (MuJoCo: shadow map); as in
  MuJoCo, that light reaches opaque surfaces only through the shadow pass;
* floor: the look's texture with the material's texrepeat (texuniform), bilinear
  within a mip level picked from the pixel's footprint, blended between levels
  (trilinear, as GL_LINEAR_MIPMAP_LINEAR);
* reflection (`reflection=True`): the floor adds `reflectance ×` the colour a
  mirrored ray sees (MuJoCo's stencil reflection: reflected geoms' colours are
  scaled by the reflectance, the sky is not reflected);
* transparency: objects with alpha < 0.995 are blended over what is behind
  them in two passes (front to back, then back to front, MuJoCo's order) for the
  two nearest transparent layers of each pixel;
* background: the look's skybox sampled by ray direction (cube map, MuJoCo's
  skybox axis convention), unlit.
Not reproduced: multisample anti-aliasing (`supersample=2` averages 2×2 rays per
pixel instead), per-vertex (Gouraud) shading and the tessellation of curved
geoms, the shadow map's resolution and bias, more than two transparent layers.
The floor texture's origin (the plane's (−x, +y) corner) is matched to
`mujoco.Renderer`'s frames (MuJoCo 3.17), not taken from its source.

Parity with MuJoCo's renderer (mean absolute pixel difference per frame and
per-body silhouette IoU against its segmentation render, per domain) is measured by
`dmcr_jax.benchmarks.jax_render_parity`; its table is benchmarks/results/jax_render_parity_cpu.md.
The frames differ most where MuJoCo's per-vertex lighting and tessellation show:
walker's reflection and shadow edges, reacher's spotlight low over the floor, and
the edge pixels of small spheres and ellipsoids.

How it is built: `pack_env` (`jax_render_pack`: per env, a few hundred numbers: object
frames, sizes and colours, camera, lights, floor and sky) and `trace_pixels`
(`jax_render_trace`: per pixel, reading those numbers and the texture bank through a
reader: `ArrayReader`, or the kernel's `RefReader` in `jax_render_kernel`), on the
intersections of `jax_render_geometry` and the shading and texturing of
`jax_render_shade`. The per-pixel code holds 3-vectors as (x, y, z) tuples, so it runs
both under XLA and inside one fused Pallas kernel. This module is the door: it
re-exports those modules' names.

On a GPU `render_batch` draws every env in one fused kernel (`jax_render_kernel`;
its frames equal this module's XLA path's); `kernel=False` takes the XLA path
(nearest hits as running minima, in chunks of envs). On the CPU the nearest hits are
taken from stacked distances (`running_minima`; both forms give the same frames).
Speeds of both paths: benchmarks/results/jax_render_h100.md.

Used by `dmcr_jax.make(..., renderer="jax")` (`dmcr_jax.jax_env`: physics, this
renderer and frame stacks in one jitted call) and `train --renderer jax`.
"""

from __future__ import annotations

import functools
from typing import Mapping

import jax
import jax.numpy as jnp

# The other modules' names, used here and re-exported for callers (the library's
# own modules import them from their homes).
from dmcr_jax.visuals.jax_render_geometry import INF, _normal_local, _v, intersect
from dmcr_jax.visuals.jax_render_pack import (ArrayReader, Layout, _objects, camera_frame,
                                              layout, look_layout, pack_env)
from dmcr_jax.visuals.jax_render_scene import (BodyPoses, DeviceLook, Scene, build_scene,
                                               device_looks, poses)
from dmcr_jax.visuals.jax_render_shade import _sky_color
from dmcr_jax.visuals.jax_render_trace import (MIP_COS_POWER, MIP_SCALE, TRANSPARENT_BELOW,
                                               _camera_rays, image_from_planes,
                                               running_minima, trace_pixels)

__all__ = ["render", "render_batch", "render_with_ids", "build_scene", "device_looks",
           "poses", "intersect", "camera_frame", "running_minima", "Layout", "layout",
           "look_layout", "pack_env", "trace_pixels", "image_from_planes", "use_kernel"]


def _render(scene: Scene, bp: BodyPoses, look: DeviceLook, variables, *, height, width,
            shadows, reflection, supersample, running=None):
  """Colour planes (3, P) in [0, 1] and nearest object (P,) of one env (−1: none),
  under XLA; `running`: the nearest-hit form (None: `running_minima()`)."""
  running = running_minima() if running is None else running
  floats, ints = pack_env(scene, bp, look, variables)
  reader = ArrayReader(floats, ints, scene.floor_texels.reshape(-1), scene.skies.reshape(-1))
  pix = jnp.arange(height * supersample * width * supersample, dtype=jnp.int32)
  color, seg = trace_pixels(look_layout(scene, look), reader, pix, height=height, width=width,
                            shadows=shadows, reflection=reflection,
                            supersample=supersample, running=running)
  return jnp.stack(color), seg


@functools.partial(jax.jit, static_argnames=("height", "width", "shadows", "reflection",
                                             "supersample"))
def render(scene: Scene, bp: BodyPoses, look: DeviceLook,
           variables: Mapping[str, jax.Array] | None = None, *, height: int = 84,
           width: int = 84, shadows: bool = True, reflection: bool = True,
           supersample: int = 1) -> jax.Array:
  """Renders one env's frame (under XLA; `render_batch` renders many).

  Args:
    scene: the domain's `Scene` (`build_scene`).
    bp: the env's `BodyPoses` (`poses(mjx_data)`; positions must be current).
    look: the env's `DeviceLook` (one row of `device_looks`).
    variables: task model variables (`State.info`, "geom_pos:target" → value).
    height, width: image size (static).
    shadows: shadow rays towards shadow-casting lights (static).
    reflection: the floor's reflection (static).
    supersample: rays per pixel along each axis, averaged (static; 1 = none).

  Returns:
    uint8 (height, width, 3), top row first (as `mujoco.Renderer`).
  """
  color, _ = _render(scene, bp, look, variables, height=height, width=width,
                     shadows=shadows, reflection=reflection, supersample=supersample)
  return image_from_planes(color, height, width, supersample)


@functools.partial(jax.jit, static_argnames=("height", "width"))
def render_with_ids(scene: Scene, bp: BodyPoses, look: DeviceLook,
                    variables: Mapping[str, jax.Array] | None = None, *,
                    height: int = 84, width: int = 84):
  """`render` plus the body id seen at each pixel (−1: background), as
  MuJoCo's segmentation rendering (nearest geom or site, transparency ignored).

  Returns:
    (uint8 (H, W, 3), int32 (H, W)).
  """
  color, seg = _render(scene, bp, look, variables, height=height, width=width,
                       shadows=True, reflection=True, supersample=1)
  body = jnp.where(seg >= 0, scene.seg_body[jnp.maximum(seg, 0)], -1)
  return image_from_planes(color, height, width, 1), body.reshape(height, width)


def use_kernel(kernel: bool | None) -> bool:
  """Whether to render in the fused GPU kernel: None (the default) on a GPU only;
  True insists (ValueError unless JAX's default backend is a GPU); False never."""
  gpu = jax.default_backend() == "gpu"
  if kernel and not gpu:
    raise ValueError(f"the fused render kernel needs a GPU (Pallas on Triton); JAX's "
                     f"backend here is {jax.default_backend()!r}: render without it "
                     f"(kernel=False / render_kernel=False, or None: the kernel on a "
                     f"GPU only)")
  return gpu if kernel is None else bool(kernel)


def render_batch(scene: Scene, bp: BodyPoses, look: DeviceLook,
                 variables: Mapping[str, jax.Array] | None = None, *,
                 chunk: int | None = None, kernel: bool | None = None,
                 **kwargs) -> jax.Array:
  """`render` over a leading env axis of `bp`, `look` and `variables`.

  Args:
    scene, bp, look, variables: as for `render`, batched (the scene is shared).
    chunk: without the kernel, envs are rendered `chunk` at a time (`lax.map`
      over vmapped chunks; a remainder is one more, smaller chunk), which bounds
      memory and, on a GPU, keeps a chunk's arrays in cache. The kernel ignores it.
    kernel: render every env's pixels in one fused GPU kernel
      (`jax_render_kernel`: the same per-pixel code and the same frames, faster).
      None (default): on a GPU; see `use_kernel`.
    **kwargs: `render`'s static options (height, width, shadows, …).

  Returns:
    uint8 (N, H, W, 3).
  """
  if use_kernel(kernel):
    from dmcr_jax.visuals import jax_render_kernel
    return jax_render_kernel.render_batch(scene, bp, look, variables, **kwargs)
  fn = functools.partial(render, **kwargs)
  if chunk is None:
    return jax.vmap(fn, in_axes=(None, 0, 0, 0 if variables else None))(
        scene, bp, look, variables)
  one = lambda args: fn(scene, *args)
  return jax.lax.map(one, (bp, look, variables), batch_size=chunk)
