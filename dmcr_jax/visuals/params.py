"""Visual seeds → `VisualParams`: batched, jittable, one random stream per factor.

`sample(domain, seeds, vary)` turns a batch of integer visual seeds into a
`VisualParams` pytree whose arrays have a leading batch axis: everything the
renderer needs to draw that look (material colours, floor and skybox texture
ids, floor reflectance, headlight, light pose and colour, camera pose). Seed 0
is always dm_control's default look; so is every factor that `vary` leaves off
or that does not apply to the domain (the paper's Table 5, see `factors.py`).

Streams: factor `f` of seed `s` draws from its own fold-ins of the seed's key,
`fold_in(key(s), FACTOR_IDS[f] · 256 + j)` for j = 0, 1, … (a fixed number per
factor; each gives two 32-bit words, each word two 16-bit draws). Switching a factor on
or off never changes another factor's values, and different factors' draws are
independent (distinct threefry streams). Draws added to a factor after its first
release come from further fold-ins j of the same factor (`_EXTRA_WORDS`), after the
ones it had, so that no look drawn before changes: finger's light colour uses
j = 4, 5 of the light factor.

Bit-exact on every backend: each uniform is `low + k * step` with `k` a 16-bit
integer from the stream and `step` a float32 with at most 8 significant bits,
so the product is exact and the sum is rounded once (the same with or without
fused multiply-add); the few derived values (headlight and light colour jitter
sums, clipping, light direction = aim − position) are single IEEE operations.
`VisualParams` are therefore bit-identical on CPU, GPU and TPU, and everything
nonlinear (normalising the light direction, Euler angles to quaternions) happens
on the host in float64 when a look is applied (`render_model.prepare`).
"""

from __future__ import annotations

import functools
import math
from typing import Any, Iterable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from dmcr_jax.models.names import obj_id, suite_model
from dmcr_jax.visuals import ranges as R
from dmcr_jax.visuals.factors import (FACTOR_IDS, FACTOR_INDEX, FACTORS, active_factors,
                                      check_domain)
from dmcr_jax.visuals.texture_spec import NUM_BACKGROUNDS, NUM_FLOORS

MAX_SEED = 2**31 - 1
# Words drawn per factor stream (fixed, so a factor's values never depend on
# which other factors are on). Each 32-bit word gives two 16-bit draws.
_WORDS = {"camera": 4, "light": 8, "body": 4, "target": 2, "floor": 2,
          "background": 2, "reflectance": 2}
# Words added to a factor later: name -> (factor, words). They are the fold-ins
# j = _WORDS[factor] / 2, … of that factor (after its original ones; extras of one
# factor follow each other in this order), kept apart from `_WORDS` so that
# the draws that existed before keep their values (`_k16` interleaves a stream's
# words, so appending to it would move them). Never reorder or resize an entry.
_EXTRA_WORDS = {"light_colour": ("light", 4)}


@struct.dataclass
class VisualParams:
  """Everything a batch of visual seeds decides (arrays with a leading batch axis N).

  Attributes:
    seed: int32 (N,) the visual seeds.
    varied: bool (N, 7) whether each factor (in `FACTORS` order) was drawn for
      this env; False means dm_control's default (seed 0, factor off, or not
      applicable to the domain). Renderers write the model's exact default
      values for factors that are not varied.
    cam_pos: float32 (N, 3) position of the domain's camera 0 in its body frame.
    cam_rot: float32 (N, 3) intrinsic x-y-z Euler offsets (degrees) applied on
      top of camera 0's default orientation.
    light_pos: float32 (N, 3) position of the domain's light in its body frame.
    light_dir: float32 (N, 3) direction the light points (not normalised;
      normalised in float64 when applied).
    light_diffuse, light_specular: float32 (N, 3) RGB diffuse and specular
      intensity of that light (GL light colours, unitless, not clipped: the
      original's finger draws reach 1.12 and −.02). The model's own values
      unless the light factor varies and the domain's ranges give a colour
      (finger only, `ranges.DomainRanges.light_diffuse`).
    headlight_ambient, headlight_diffuse, headlight_specular: float32 (N, 3).
    body_rgba: float32 (N, 4) colour of the agent's body ("self" materials).
    effector_rgba: float32 (N, 4) colour of its effectors ("effector" materials).
    target_rgba: float32 (N, 4) colour of the target ("target" materials).
    floor_id: int32 (N,) floor texture in the bank, −1 = dm_control's grid.
    background_id: int32 (N,) skybox in the bank, −1 = dm_control's skybox.
    floor_reflectance: float32 (N,) reflectance of the floor material.
    floor_delta: float32 (N, 3) RGB offset of the floor material's colour (clipped
      to [0, 1] when applied), or None: a look that moves (`moving.look_at`).
    background2_id: int32 (N,) the sky the picture cross-fades towards, or None.
    background_mix: float32 (N,) that sky's weight in [0, 1], or None.
    domain: the domain these looks belong to (static).
  """
  seed: jax.Array
  varied: jax.Array
  cam_pos: jax.Array
  cam_rot: jax.Array
  light_pos: jax.Array
  light_dir: jax.Array
  light_diffuse: jax.Array
  light_specular: jax.Array
  headlight_ambient: jax.Array
  headlight_diffuse: jax.Array
  headlight_specular: jax.Array
  body_rgba: jax.Array
  effector_rgba: jax.Array
  target_rgba: jax.Array
  floor_id: jax.Array
  background_id: jax.Array
  floor_reflectance: jax.Array
  floor_delta: jax.Array | None = None
  background2_id: jax.Array | None = None
  background_mix: jax.Array | None = None
  domain: str = struct.field(pytree_node=False, default="")

  def __len__(self) -> int:
    return int(self.seed.shape[0])

  def take(self, index) -> "VisualParams":
    """The looks at `index` (an int keeps a batch axis of 1; slices/arrays too)."""
    if isinstance(index, (int, np.integer)):
      index = slice(int(index), int(index) + 1) if index != -1 else slice(-1, None)
    return jax.tree.map(lambda x: x[index], self)

  def is_varied(self, factor: str) -> jax.Array:
    """Bool (N,): whether `factor` was drawn (not dm_control's default)."""
    return self.varied[:, FACTOR_INDEX[factor]]


# ---------------------------------------------------------------------------
# Defaults (dm_control's model) and exact uniform draws
# ---------------------------------------------------------------------------


@functools.cache
def defaults(domain: str) -> dict[str, np.ndarray]:
  """dm_control's default value of every `VisualParams` field for `domain`.

  Args:
    domain: a DMCR domain.

  Returns:
    A dict from field name to a float32/int32 array without the batch axis.
  """
  domain = check_domain(domain)
  r = R.DOMAIN_RANGES[domain]
  m = suite_model(domain)
  O = mujoco.mjtObj
  cam = obj_id(m, O.mjOBJ_CAMERA, r.camera)
  light = obj_id(m, O.mjOBJ_LIGHT, r.light)
  floor = obj_id(m, O.mjOBJ_GEOM, r.floor)
  mat = lambda names: m.mat_rgba[obj_id(m, O.mjOBJ_MATERIAL, names[0])]
  hl = m.vis.headlight
  f32 = lambda x: np.asarray(x, np.float32).copy()
  return {
      "cam_pos": f32(m.cam_pos[cam]), "cam_rot": np.zeros(3, np.float32),
      "light_pos": f32(m.light_pos[light]), "light_dir": f32(m.light_dir[light]),
      "light_diffuse": f32(m.light_diffuse[light]),
      "light_specular": f32(m.light_specular[light]),
      "headlight_ambient": f32(hl.ambient), "headlight_diffuse": f32(hl.diffuse),
      "headlight_specular": f32(hl.specular),
      "body_rgba": f32(mat(r.body)), "effector_rgba": f32(mat(r.effector)),
      "target_rgba": f32(mat(r.target)),
      "floor_id": np.int32(-1), "background_id": np.int32(-1),
      "floor_reflectance": f32(m.mat_reflectance[m.geom_matid[floor]]),
  }


def _round8(r: float) -> float:
  """`r` rounded to 8 significant bits (so that 16-bit × step products are exact)."""
  if r == 0:
    return 0.0
  mant, exp = math.frexp(r)
  return math.ldexp(round(mant * 256) / 256, exp)


def _affine(ranges) -> tuple[np.ndarray, np.ndarray]:
  """(low, step) float32 arrays of exact uniform draws `low + k * step`, k < 65536."""
  lo = np.array([a for a, _ in ranges], np.float32)
  step = np.array([_round8(b - a) / 65536.0 for a, b in ranges], np.float32)
  return lo, step


def _uniform(k: jax.Array, lo, step) -> jax.Array:
  """k: float32 integers in [0, 65536) → low + k·step (exact product, one rounding)."""
  return lo + k * step


_RGBA = _affine([R.RGB] * 3 + [R.ALPHA])
_HEAD = [(_affine([rng]), _affine([(-j, j)] * 3)) for rng, j in
         (R.HEADLIGHT_AMBIENT, R.HEADLIGHT_DIFFUSE, R.HEADLIGHT_SPECULAR)]
_REFL = _affine([R.REFLECTANCE])


@functools.cache
def _domain_consts(domain: str) -> dict[str, np.ndarray]:
  """The per-domain constants the (shared) sampler reads, as NumPy arrays."""
  r = R.DOMAIN_RANGES[domain]
  c = {f"default_{k}": np.asarray(v) for k, v in defaults(domain).items()}
  c["cam_lo"], c["cam_step"] = _affine(r.cam_pos)
  c["rot_lo"], c["rot_step"] = _affine(r.cam_rot)
  moves = r.light_pos is not None
  c["light_lo"], c["light_step"] = _affine(r.light_pos if moves else [(0, 0)] * 3)
  c["light_moves"] = np.asarray(moves)
  c["light_aim"] = np.asarray(r.light_aim, np.float32)
  coloured = r.light_diffuse is not None
  for name in ("diffuse", "specular"):
    (lo, hi), jit = getattr(r, f"light_{name}") if coloured else ((0, 0), 0)
    c[f"l{name}_lo"], c[f"l{name}_step"] = _affine([(lo, hi)])
    c[f"l{name}_jlo"], c[f"l{name}_jstep"] = _affine([(-jit, jit)] * 3)
  c["light_coloured"] = np.asarray(coloured)
  return c


def _streams(seed: jax.Array) -> dict[str, jax.Array]:
  """Each factor's random words, from its own `fold_in` stream.

  Word pair j of factor f is `key_data(fold_in(key(seed), FACTOR_IDS[f] · 256 + j))`
  (threefry2x32): a distinct fold-in per (factor, j), so factors never share
  or shift each other's draws and are statistically independent. All pairs are
  one vectorised `fold_in` (fast to compile and to run); the key
  implementation is fixed explicitly, independent of JAX's global PRNG config.
  Keys: the factors, each with its `_WORDS` words (j = 0, 1, …), and the
  `_EXTRA_WORDS` names, each with the factor's next fold-ins.
  """
  key = jax.random.key(seed, impl="threefry2x32")
  spans, data, nxt = [], [], dict.fromkeys(FACTORS, 0)   # nxt: next j per factor
  for name, (f, words) in [*((f, (f, _WORDS[f])) for f in FACTORS),
                           *_EXTRA_WORDS.items()]:
    n = words // 2
    spans.append((name, len(data), n))
    data += [FACTOR_IDS[f] * 256 + nxt[f] + j for j in range(n)]
    nxt[f] += n
  pairs = jax.random.key_data(jax.vmap(jax.random.fold_in, (None, 0))(
      key, jnp.asarray(np.array(data, np.uint32))))
  return {name: pairs[start:start + n].reshape(-1) for name, start, n in spans}


def _k16(words: jax.Array) -> jax.Array:
  """n uint32 words → 2n draws: high halves then low halves, as float32 integers
  in [0, 65536)."""
  return jnp.concatenate([words >> 16, words & 0xFFFF]).astype(jnp.float32)


_FIELD_FACTOR = {
    "cam_pos": "camera", "cam_rot": "camera", "light_pos": "light",
    "light_dir": "light", "light_diffuse": "light", "light_specular": "light",
    "headlight_ambient": "light",
    "headlight_diffuse": "light", "headlight_specular": "light",
    "body_rgba": "body", "effector_rgba": "body", "target_rgba": "target",
    "floor_id": "floor", "background_id": "background",
    "floor_reflectance": "reflectance"}


def _draw_one(seed: jax.Array, mask: jax.Array, c: dict[str, jax.Array],
              nf: jax.Array, nb: jax.Array) -> dict[str, jax.Array]:
  """Draws one seed's looks (vmapped). `mask` (7,) says which factors vary."""
  words = _streams(seed)
  on = {f: (seed != 0) & mask[i] for i, f in enumerate(FACTORS)}
  out: dict[str, Any] = {}

  k = _k16(words["camera"])
  out["cam_pos"] = _uniform(k[0:3], c["cam_lo"], c["cam_step"])
  out["cam_rot"] = _uniform(k[3:6], c["rot_lo"], c["rot_step"])

  k = _k16(words["light"])
  pos = _uniform(k[0:3], c["light_lo"], c["light_step"])
  out["light_pos"] = jnp.where(c["light_moves"], pos, c["default_light_pos"])
  out["light_dir"] = jnp.where(c["light_moves"], c["light_aim"] - pos,
                               c["default_light_dir"])
  for j, name in enumerate(("ambient", "diffuse", "specular")):
    (blo, bstep), (jlo, jstep) = _HEAD[j]
    base = _uniform(k[3 + j:4 + j], blo, bstep)
    jitter = _uniform(k[6 + 3 * j:9 + 3 * j], jlo, jstep)
    out[f"headlight_{name}"] = jnp.clip(base + jitter, 0.0, 1.0)
  # The moved light's colour (finger): scalar base + per-channel jitter, unclipped.
  k = _k16(words["light_colour"])
  for j, name in enumerate(("diffuse", "specular")):
    base = _uniform(k[j:j + 1], c[f"l{name}_lo"], c[f"l{name}_step"])
    jitter = _uniform(k[2 + 3 * j:5 + 3 * j], c[f"l{name}_jlo"], c[f"l{name}_jstep"])
    out[f"light_{name}"] = jnp.where(c["light_coloured"], base + jitter,
                                     c[f"default_light_{name}"])

  k = _k16(words["body"])
  out["body_rgba"] = _uniform(k[0:4], *_RGBA)
  out["effector_rgba"] = _uniform(k[4:8], *_RGBA)
  out["target_rgba"] = _uniform(_k16(words["target"])[0:4], *_RGBA)
  out["floor_id"] = (words["floor"][0] % nf).astype(jnp.int32)
  out["background_id"] = (words["background"][0] % nb).astype(jnp.int32)
  out["floor_reflectance"] = _uniform(_k16(words["reflectance"])[0:1], *_REFL)[0]

  res = {name: jnp.where(on[_FIELD_FACTOR[name]], val, c[f"default_{name}"])
         for name, val in out.items()}
  res["varied"] = jnp.stack([on[f] for f in FACTORS])
  res["seed"] = seed
  return res


@jax.jit
def _sample_jit(seeds, mask, consts, nf, nb):
  """One compiled sampler for every domain and `vary` (traced constants)."""
  return jax.vmap(_draw_one, (0, None, None, None, None))(seeds, mask, consts, nf, nb)


def check_seeds(seeds: Any) -> jax.Array:
  """Validates visual seeds and returns them as an int32 (N,) array.

  Args:
    seeds: an int, a sequence of ints, or an integer array with at most one
      axis. Concrete values must lie in [0, 2**31 − 1]. Traced values (inside
      `jit`) are only checked for dtype and shape.

  Returns:
    int32 array of shape (N,).

  Raises:
    TypeError: for non-integer seeds (floats, bools, strings, …).
    ValueError: for seeds out of range or with more than one axis.
  """
  if isinstance(seeds, jax.core.Tracer):
    if not jnp.issubdtype(seeds.dtype, jnp.integer):
      raise TypeError(f"Visual seeds must be integers, got dtype {seeds.dtype}.")
    if seeds.ndim > 1:
      raise ValueError(f"Visual seeds must be a scalar or 1-D, got shape {seeds.shape}.")
    return jnp.atleast_1d(seeds).astype(jnp.int32)
  if isinstance(seeds, (bool, np.bool_)):
    raise TypeError("Visual seeds must be integers, got a bool.")
  if isinstance(seeds, range):
    seeds = list(seeds)
  arr = np.asarray(seeds)
  if arr.dtype == object or arr.dtype.kind not in "iu":
    raise TypeError(
        f"Visual seeds must be integers in [0, 2**31 - 1], got {seeds!r:.80} "
        f"(dtype {arr.dtype}).")
  if arr.ndim > 1:
    raise ValueError(f"Visual seeds must be a scalar or 1-D, got shape {arr.shape}.")
  arr = np.atleast_1d(arr)
  if arr.size and (arr.min() < 0 or arr.max() > MAX_SEED):
    bad = arr[(arr < 0) | (arr > MAX_SEED)][0]
    raise ValueError(
        f"Visual seeds must be in [0, 2**31 - 1] (non-negative, below 2**31); "
        f"got {int(bad)}.")
  return jnp.asarray(arr.astype(np.int32))


def sample(domain: str, seeds: Any, vary: str | Iterable[str] | None = "all", *,
           num_floors: int = NUM_FLOORS,
           num_backgrounds: int = NUM_BACKGROUNDS) -> VisualParams:
  """Builds the `VisualParams` of a batch of visual seeds.

  Jittable (seeds may be traced; the configuration is static): the draws are a
  vmapped threefry computation.

  Args:
    domain: a DMCR domain ("walker") or task name ("walker-walk").
    seeds: visual seeds, non-negative ints below 2**31 (int, sequence, range or
      1-D integer array). Seed 0 is dm_control's default look.
    vary: the factors to vary: "all" (default), "none", a comma-separated
      string ("floor,background") or an iterable of names from `FACTORS`.
      Factors that do not apply to the domain (paper, Table 5) are ignored.
    num_floors: size of the floor bank the ids index (the procedural bank's by
      default; use `render_model.bank.num_floors` with a user folder).
    num_backgrounds: size of the skybox bank.

  Returns:
    A `VisualParams` with leading axis N = number of seeds.

  Raises:
    ValueError: unknown domain or factor (the message lists valid ones), seeds
      out of range, non-positive bank sizes.
    TypeError: non-integer seeds.
  """
  domain = check_domain(domain)
  for name, n in (("num_floors", num_floors), ("num_backgrounds", num_backgrounds)):
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
      raise ValueError(f"{name} must be a positive int, got {n!r}.")
  return sample_masked(domain, check_seeds(seeds), factor_mask(domain, vary),
                       num_floors, num_backgrounds)


def factor_mask(domain: str, vary: str | Iterable[str] | None) -> np.ndarray:
  """Bool (7,) in `FACTORS` order: the factors `vary` switches on for `domain`."""
  factors = active_factors(domain, vary)
  return np.array([f in factors for f in FACTORS])


def sample_masked(domain: str, seeds: jax.Array, mask: jax.Array, num_floors: int,
                  num_backgrounds: int) -> VisualParams:
  """`sample` with the factors as a bool (7,) mask (`factor_mask`), which may be
  traced: one compilation serves every `vary`. No checks (`sample` makes them).

  Args:
    domain: a checked DMCR domain.
    seeds: int32 (N,) visual seeds (may be traced).
    mask: bool (7,) factors on, in `FACTORS` order.
    num_floors, num_backgrounds: the bank sizes the texture ids index.
  """
  fields = _sample_jit(seeds, mask, _domain_consts(domain), np.uint32(num_floors),
                       np.uint32(num_backgrounds))
  return VisualParams(domain=domain, **fields)
