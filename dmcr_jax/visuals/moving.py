"""Looks that move within an episode: a pure function of (visual seed, episode step).

`look_at(params, step, moving, intensity)` takes the static looks of a batch
(`VisualParams`, one per env) and each env's episode step and returns the looks
to draw at that step: the factors named in `moving` drift smoothly inside a range
that `intensity` ∈ [0, 1] scales, as the Distracting Control Suite's difficulty
scales its ranges (DCS: `suite_utils.DIFFICULTY_SCALE` easy .1, medium .2, hard
.3). Everything else of the look, and all of the physics, is untouched. Both
renderers call this one function: the ray caster inside its jitted step
(`jax_render_scene.LookMaker`), the render pool's env on the host before each
render call (`env.PixelVectorEnv`), so both draw the same look at a step.

Factors (`MOVING_FACTORS`) and their ranges at intensity I:

* camera — orbits the point it looks at (on its view axis, at the distance of the
  agent's centre of mass at qpos0) by a vertical and a horizontal angle, rolls, and
  zooms: angles within ±90°·I (DCS: `vertical_delta = horizontal_delta =
  roll_delta = π/2 · scale`), distance × [1 − .5·I, 1 + 1.5·I] (DCS's
  `max_zoom_in/out_percent`);
* light — the headlight's ambient, diffuse and specular intensities ±I (clipped
  to [0, 1]), and where the domain's look moves a light (`ranges.DomainRanges.
  light_pos`), its position ± I × the half-width of the domain's light range per
  axis, still aimed at its aim point;
* body — the RGB of the agent's body and effector materials ±I, clipped to
  [0, 1] (DCS's colour distraction: `max_delta = scale`);
* floor — the RGB of the floor's material (which multiplies its texture) ±I,
  clipped to [0, 1] (DCS colours every material, the floor's included);
* background — the sky cross-fades towards another sky of the bank and back once
  every `BACKGROUND_PERIOD` steps, the other sky's weight reaching I at the middle
  of each period (a new sky each period), where DCS plays a video.

Trajectories: each moving coordinate is x(t) = clip(G · Σₖ aₖ sin(2π t / Pₖ + φₖ)
/ Σₖ aₖ, −1, 1), k = 1…`WAVES`, with periods Pₖ drawn from the factor's
`PERIODS` range (agent steps: the camera faster than the colours, as in DCS), weights aₖ ∈ [.5, 1] and phases drawn from the factor's own stream
(`fold_in(key(seed), (MOTION_STREAM + FACTOR_IDS[f]) · 256)`, apart from every
stream `params` draws from), so factors move independently of each other and of
which others move. x is bounded (|x| ≤ 1, so a value never leaves its range) and
smooth (|x(t + 1) − x(t)| ≤ 2π·G / Pmin, `max_step_change`). DCS instead random-walks a
velocity and clips the position (`camera.py`, `color.py`); a sum of waves is a
bounded smooth process too, and is a closed-form function of t, so a step's look
costs the same at any step, needs no state carried between steps, and is the same
in every renderer and batch. Seed 0 moves around dm_control's look; intensity 0
(or no factor) returns the static looks unchanged.
"""

from __future__ import annotations

import functools
import math
from typing import Iterable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dmcr_jax.models.names import obj_id, suite_model
from dmcr_jax.visuals import ranges as R
from dmcr_jax.visuals.factors import APPLICABLE, FACTOR_IDS, FACTOR_INDEX, check_domain
from dmcr_jax.visuals.params import VisualParams
from dmcr_jax.visuals.texture_spec import NUM_BACKGROUNDS

MOVING_FACTORS: tuple[str, ...] = ("camera", "light", "body", "floor", "background")
"""The factors that can move within an episode, in this (canonical) order."""
MOTION_STREAM = 64
"""Fold-in base of the motion streams: factor f moves with `fold_in(key(seed),
(MOTION_STREAM + FACTOR_IDS[f]) · 256)`; the look's own draws use ids below 8 · 256."""
WAVES = 3
PERIODS = {"camera": (100.0, 400.0), "light": (200.0, 800.0), "body": (200.0, 800.0),
           "floor": (200.0, 800.0)}
"""Range of the waves' periods of each factor, in agent steps."""
GAIN = 1.5
BACKGROUND_PERIOD = 100
"""Agent steps of one background cross-fade (to another sky and back)."""
MAX_ANGLE = 90.0     # degrees at intensity 1 (DCS: π/2 · scale)
ZOOM_IN, ZOOM_OUT = 0.5, 1.5


def check_moving(domain: str, moving: str | Iterable[str] | None,
                 intensity: float = 0.0) -> tuple[tuple[str, ...], float]:
  """Validates a `moving` and `intensity` a user passes (`make`, `dmcr-train`).

  Args:
    domain: a DMCR domain or task name.
    moving: None, "" or "none" (static looks), "all" (every moving factor that
      applies to the domain), a comma-separated string ("camera,background") or an
      iterable of names from `MOVING_FACTORS`.
    intensity: a number in [0, 1]: the fraction of each factor's largest range.

  Returns:
    (factors, intensity): the factors in `MOVING_FACTORS` order (empty: static)
    and the intensity as a float.

  Raises:
    ValueError: an unknown factor (naming the valid ones), a factor that does not
      apply to the domain (the paper's Table 5), or an intensity outside [0, 1].
  """
  domain = check_domain(domain)
  if isinstance(intensity, bool) or not isinstance(intensity, (int, float, np.number)) \
      or not 0.0 <= float(intensity) <= 1.0:
    raise ValueError(f"intensity must be a number in [0, 1] (DCS's difficulties are .1, "
                     f".2, .3), got {intensity!r}")
  own = [f for f in MOVING_FACTORS if f in APPLICABLE[domain]]
  if moving is None:
    return (), float(intensity)
  if isinstance(moving, str):
    items = [s for s in (p.strip().lower() for p in moving.split(",")) if s]
  else:
    items = [str(s).strip().lower() for s in moving]
  if items in ([], ["none"]):
    return (), float(intensity)
  if items == ["all"]:
    return tuple(own), float(intensity)
  unknown = [s for s in items if s not in MOVING_FACTORS]
  if unknown:
    raise ValueError(f"Unknown moving factor(s) {', '.join(map(repr, unknown))}. Valid "
                     f"moving factors: {', '.join(MOVING_FACTORS)} (or 'all' / 'none').")
  missing = [s for s in items if s not in own]
  if missing:
    raise ValueError(f"moving: {', '.join(missing)} do(es) not apply to {domain} (the "
                     f"paper's Table 5); {domain}'s moving factors: {', '.join(own)}")
  return tuple(f for f in MOVING_FACTORS if f in items), float(intensity)


@functools.cache
def _consts(domain: str) -> dict[str, np.ndarray]:
  """Camera 0's default orientation and orbit distance, the light's range and aim."""
  r = R.DOMAIN_RANGES[domain]
  m = suite_model(domain)
  cam = obj_id(m, mujoco.mjtObj.mjOBJ_CAMERA, r.camera)
  dist = float(np.linalg.norm(m.cam_poscom0[cam]))
  half = [(b - a) / 2 for a, b in r.light_pos] if r.light_pos is not None else [0.0] * 3
  return {"cam_quat": np.asarray(m.cam_quat[cam], np.float32),
          "distance": np.float32(dist),
          "light_half": np.asarray(half, np.float32),
          "light_aim": np.asarray(r.light_aim, np.float32),
          "light_moves": np.asarray(r.light_pos is not None)}


def _key(seed: jax.Array, factor: str) -> jax.Array:
  key = jax.random.key(seed, impl="threefry2x32")
  return jax.random.fold_in(key, (MOTION_STREAM + FACTOR_IDS[factor]) * 256)


def wave(seed: jax.Array, factor: str, dims: int, step: jax.Array) -> jax.Array:
  """The factor's `dims` smooth bounded coordinates x(step) ∈ [−1, 1] of one env.

  Args:
    seed: int32 visual seed (scalar).
    factor: a name of `MOVING_FACTORS` (its stream).
    dims: how many coordinates.
    step: int episode step (scalar).

  Returns:
    float32 (dims,).
  """
  u = jax.random.uniform(_key(seed, factor), (dims, WAVES, 3), jnp.float32)
  lo, hi = PERIODS[factor]
  period = lo + u[..., 0] * (hi - lo)
  weight = 0.5 + 0.5 * u[..., 1]
  phase = 2 * math.pi * u[..., 2]
  t = jnp.asarray(step, jnp.float32)
  s = jnp.sum(weight * jnp.sin(2 * math.pi * t / period + phase), -1) / jnp.sum(weight, -1)
  return jnp.clip(GAIN * s, -1.0, 1.0)


def max_step_change(factor: str) -> float:
  """The largest |x(t + 1) − x(t)| of a coordinate of `factor` (a fraction of its
  half-range; background: of its largest weight), whatever the seed."""
  if factor == "background":
    return math.pi / BACKGROUND_PERIOD
  return 2 * math.pi * GAIN / PERIODS[factor][0]


def _qmul(a, b):
  w1, x1, y1, z1 = a[0], a[1], a[2], a[3]
  w2, x2, y2, z2 = b[0], b[1], b[2], b[3]
  return jnp.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                    w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                    w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                    w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _backward(quat0, rot_deg):
  """Camera frame's z axis (backward) in its body frame, for offsets `rot_deg`
  (intrinsic x-y-z Euler degrees, as `render_model.prepare` applies them)."""
  q = quat0
  half = jnp.deg2rad(rot_deg) / 2
  for axis in range(3):
    turn = jnp.zeros(4).at[0].set(jnp.cos(half[axis])).at[1 + axis].set(jnp.sin(half[axis]))
    q = _qmul(q, turn)
  w, x, y, z = q / jnp.sqrt(jnp.sum(q * q))
  return jnp.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


def _one(p: dict, step, c: dict, moving: tuple[str, ...], intensity,
         num_backgrounds: int, on: dict | None = None) -> dict:
  """`look_at` of one env (vmapped): `p` its static look's fields.

  `on` None: every factor of `moving` moves (at the static `intensity`). Else
  {factor: traced bool} per factor of `moving` and a traced `intensity`: the env
  moves the factors it marks, and the others keep the static look's values (an
  unmoved floor gets a zero `floor_delta`, an unmoved sky a zero `background_mix`).
  """
  out = dict(p)
  seed, varied = p["seed"], p["varied"]
  I = jnp.float32(intensity)
  pick = (lambda f, new, old: new) if on is None else (
      lambda f, new, old: jnp.where(on[f], new, old))
  if "camera" in moving:
    x = wave(seed, "camera", 4, step)
    rot = p["cam_rot"] + jnp.stack([x[0], x[1], x[2]]) * (MAX_ANGLE * I)
    zoom = 1 + I * jnp.where(x[3] >= 0, ZOOM_OUT * x[3], ZOOM_IN * x[3])
    d = c["distance"]
    look = p["cam_pos"] - d * _backward(c["cam_quat"], p["cam_rot"])
    out["cam_pos"] = pick("camera", look + (zoom * d) * _backward(c["cam_quat"], rot),
                          p["cam_pos"])
    out["cam_rot"] = pick("camera", rot, p["cam_rot"])
    i = FACTOR_INDEX["camera"]
    varied = varied.at[i].set(pick("camera", True, varied[i]))
  if "light" in moving:
    x = wave(seed, "light", 6, step)
    for j, name in enumerate(("headlight_ambient", "headlight_diffuse", "headlight_specular")):
      out[name] = pick("light", jnp.clip(p[name] + x[j] * I, 0.0, 1.0), p[name])
    pos = p["light_pos"] + x[3:6] * I * c["light_half"]   # half-width 0: no light moves
    out["light_pos"] = pick("light", jnp.where(c["light_moves"], pos, p["light_pos"]),
                            p["light_pos"])
    out["light_dir"] = pick("light", jnp.where(c["light_moves"], c["light_aim"] - pos,
                                               p["light_dir"]), p["light_dir"])
    i = FACTOR_INDEX["light"]
    varied = varied.at[i].set(pick("light", True, varied[i]))
  if "body" in moving:
    x = wave(seed, "body", 6, step)
    for name, xs in (("body_rgba", x[0:3]), ("effector_rgba", x[3:6])):
      out[name] = pick("body", p[name].at[:3].set(jnp.clip(p[name][:3] + xs * I, 0.0, 1.0)),
                       p[name])
    i = FACTOR_INDEX["body"]
    varied = varied.at[i].set(pick("body", True, varied[i]))
  if "floor" in moving:
    out["floor_delta"] = pick("floor", wave(seed, "floor", 3, step) * I,
                              jnp.zeros(3, jnp.float32))
  if "background" in moving:
    t = jnp.asarray(step, jnp.int32)
    period = jnp.int32(BACKGROUND_PERIOD)
    k, phase = t // period, (t % period).astype(jnp.float32) / BACKGROUND_PERIOD
    key = jax.random.fold_in(_key(seed, "background"), k)
    out["background2_id"] = pick("background",
                                 jax.random.randint(key, (), 0, num_backgrounds, jnp.int32),
                                 jnp.int32(0))
    out["background_mix"] = pick("background", I * (1 - jnp.cos(2 * math.pi * phase)) / 2,
                                 jnp.float32(0))
  out["varied"] = varied
  return out


@functools.partial(jax.jit, static_argnames=("moving", "intensity", "num_backgrounds"))
def _look_at_jit(fields, step, consts, *, moving, intensity, num_backgrounds):
  """One compilation per (moving, intensity, bank size), for every domain."""
  fn = functools.partial(_one, c=consts, moving=moving, intensity=intensity,
                         num_backgrounds=num_backgrounds)
  return jax.vmap(fn, (0, 0))(fields, step)


def look_at(params: VisualParams, step, moving: tuple[str, ...], intensity: float, *,
            num_backgrounds: int = NUM_BACKGROUNDS) -> VisualParams:
  """The looks of N envs at their episode steps (jittable; see the module docstring).

  Args:
    params: the N envs' static `VisualParams` (`sample`; their seeds pick the
      motion).
    step: int (N,) or scalar: each env's agent step in its episode (0: the frame
      after reset).
    moving: the moving factors, as `check_moving` returns them (static).
    intensity: float in [0, 1] (static).
    num_backgrounds: the sky bank's size (the other skies are drawn from it).

  Returns:
    `VisualParams`: the moved factors' fields changed and marked varied; with
    "floor", `floor_delta` (N, 3) is the RGB offset of the floor's material; with
    "background", `background2_id` (N,) is the sky the picture fades towards and
    `background_mix` (N,) its weight. With no factor or intensity 0, `params`
    itself.
  """
  if not moving or intensity == 0:
    return params
  n = params.seed.shape[0]
  step = jnp.broadcast_to(jnp.asarray(step, jnp.int32), (n,))
  out = _look_at_jit(_fields(params), step, _consts(check_domain(params.domain)),
                     moving=tuple(moving), intensity=float(intensity),
                     num_backgrounds=int(num_backgrounds))
  return params.replace(**out)


_FIELDS = ("seed", "varied", "cam_pos", "cam_rot", "light_pos", "light_dir",
           "headlight_ambient", "headlight_diffuse", "headlight_specular", "body_rgba",
           "effector_rgba")


def _fields(params: VisualParams) -> dict:
  """The fields of `params` that `_one` reads."""
  return {k: getattr(params, k) for k in _FIELDS}


@functools.partial(jax.jit, static_argnames=("moving", "num_backgrounds"))
def _look_at_each_jit(fields, step, consts, on, intensity, *, moving, num_backgrounds):
  """One compilation per (moving, bank size), for every domain."""
  def one(f, t, o, i):
    return _one(f, t, consts, moving, i, num_backgrounds,
                on={name: o[j] for j, name in enumerate(moving)})
  return jax.vmap(one)(fields, step, on, intensity)


def look_at_each(params: VisualParams, step, moving: tuple[str, ...], on, intensity, *,
                 num_backgrounds: int = NUM_BACKGROUNDS) -> VisualParams:
  """`look_at` with motion of each env's own: env e moves the factors of `moving` that
  `on[e]` marks, at `intensity[e]` (jittable; one program serves envs of many moving
  conditions, as `dmcr_jax.protocol` runs them).

  An env's look equals `look_at(params[e], step[e], its factors, intensity[e])`:
  the same computation, with every factor of `moving` it does not mark left at its
  static value (and, where `moving` has "floor" or "background", a zero
  `floor_delta` or `background_mix`, which draw the static floor and sky).

  Args:
    params: the N envs' static `VisualParams`.
    step: int (N,) or scalar: each env's agent step in its episode.
    moving: the factors any env moves, in `MOVING_FACTORS` order (static).
    on: bool (N, len(moving)), which of them each env moves.
    intensity: float (N,) each env's intensity in [0, 1] (an env at 0 should mark
      no factor: `look_at` draws the static look there).
    num_backgrounds: the sky bank's size.

  Returns:
    `VisualParams` as `look_at`'s, for every env; `params` itself when `moving` is
    empty.
  """
  if not moving:
    return params
  n = params.seed.shape[0]
  step = jnp.broadcast_to(jnp.asarray(step, jnp.int32), (n,))
  out = _look_at_each_jit(_fields(params), step, _consts(check_domain(params.domain)),
                          jnp.asarray(on, bool).reshape(n, len(moving)),
                          jnp.broadcast_to(jnp.asarray(intensity, jnp.float32), (n,)),
                          moving=tuple(moving), num_backgrounds=int(num_backgrounds))
  return params.replace(**out)
