"""Per-domain visual data: which camera, light and floor move, and their ranges.

Everything a domain needs to turn uniform draws into a look lives here, in one
table. The camera and light ranges start from the original DMCR implementation
(see `shared/DESIGN.md`): camera 0 is the camera that moves; positions are the
camera's / light's `pos` in its body frame (as in dm_control's MJCF), intervals
are `(low, high)` of a uniform draw. Camera rotations are intrinsic x-y-z Euler
offsets in degrees applied on top of the camera's default orientation (only
hopper and pendulum tilt). Walker and hopper move no light (only the headlight
varies). A moved light points at `light_aim`, a point in the light's body frame
(the point its default direction hits), so the agent stays lit.

Colours come from the full RGB cube with alpha in [0.75, 1] (the original's
distribution); the floor's reflectance is uniform in [0, 0.5] (dm_control's
default is 0.2); headlight channels are a shared base plus a per-channel jitter.

The light factor also changes the colour of the domain's moved light where the
original did: only finger (the original's `finger.get_model` draws the light's
diffuse as a scalar U(.5, 1.1) plus a per-channel U(−.02, .02) and its specular as
a scalar U(0, 1.2) plus a per-channel U(−.02, .02), neither clipped; no other
domain's `get_model` touches its light's colour). `light_diffuse` and
`light_specular` hold those (base interval, jitter half-width) pairs, None where
the light keeps dm_control's colour.

The camera factor draws the original's camera pose, while seed 0 (and every
look with the camera factor off) keeps dm_control's. The two agree in every
domain but ball_in_cup and pendulum, whose MJCF the original edited (paper,
appendix: "some tasks alter the default camera angle"): its ball_in_cup camera
0 sits at z .9 (dm_control .8, the low edge of the range U(.8, 1.0)); its
pendulum camera at (.1, −1, 1.5) with xyaxes (1 0 0 0 .5 1) (dm_control: (0,
−1.5, 2) with xyaxes (1 0 0 0 1 1), outside the position range). The
original's held-out pendulum cameras have xyaxes (1 0 0 0 t 1), t ~ U(.4, .6):
from dm_control's orientation (t = 1) that is a turn about the camera's x axis
by atan(1) − atan(t), 14.0° to 23.2°, drawn here uniform in angle (same
support; t's density then varies by 17 % across the range). Hopper's offsets
are the original's Euler angles (U(85, 95), ±5, ±5) less its default (90, 0,
0): intrinsic x-y-z, so the default composed with the offset is the original's
rotation.

`floor_tile` is the size in metres of one repeat of a floor texture on that
domain's floor (texture coordinates are uniform in space, as dm_control's grid).
"""

from __future__ import annotations

import dataclasses
import math

Interval = tuple[float, float]
Vec3Ranges = tuple[Interval, Interval, Interval]

# Colours: r, g, b ~ U(0, 1), alpha ~ U(0.75, 1) (original DMCR).
RGB: Interval = (0.0, 1.0)
ALPHA: Interval = (0.75, 1.0)
# Floor reflectance ~ U(0, 0.5) (dm_control default 0.2).
REFLECTANCE: Interval = (0.0, 0.5)
# Headlight: base ~ U(lo, hi), plus U(−j, j) per channel, clipped to [0, 1].
HEADLIGHT_AMBIENT: tuple[Interval, float] = ((0.1, 0.8), 0.05)    # default 0.4
HEADLIGHT_DIFFUSE: tuple[Interval, float] = ((0.4, 0.9), 0.1)     # default 0.8
HEADLIGHT_SPECULAR: tuple[Interval, float] = ((0.05, 0.3), 0.02)  # default 0.1
# Finger's light (original DMCR): base ~ U(lo, hi), plus U(−j, j) per channel, not
# clipped (diffuse up to 1.12, specular down to −.02).
FINGER_LIGHT_DIFFUSE: tuple[Interval, float] = ((0.5, 1.1), 0.02)   # default 0.6
FINGER_LIGHT_SPECULAR: tuple[Interval, float] = ((0.0, 1.2), 0.02)  # default 0.3

_NO_ROT: Vec3Ranges = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))


@dataclasses.dataclass(frozen=True)
class DomainRanges:
  """The visual data of one domain.

  Attributes:
    camera: name of the camera that moves (camera 0).
    cam_pos: ranges of its body-frame position (x, y, z).
    cam_rot: ranges of its Euler offsets in degrees (x, y, z, intrinsic).
    light: name of the light that moves.
    light_pos: ranges of its body-frame position, or None (headlight only).
    light_aim: body-frame point a moved light points at.
    floor: name of the floor geom.
    floor_tile: metres per repeat of a floor texture.
    body: materials coloured by the `body` factor (first colour).
    effector: materials coloured with the body factor's second colour.
    target: materials coloured by the `target` factor.
    light_diffuse, light_specular: (base interval, per-channel jitter half-width)
      of the moved light's diffuse and specular colour (RGB, unitless GL light
      intensities; not clipped), or None: the light keeps the model's colour.
  """
  camera: str
  cam_pos: Vec3Ranges
  cam_rot: Vec3Ranges
  light: str
  light_pos: Vec3Ranges | None
  light_aim: tuple[float, float, float]
  floor: str
  floor_tile: float
  body: tuple[str, ...] = ("self", "self_default")
  effector: tuple[str, ...] = ("effector", "effector_default")
  target: tuple[str, ...] = ("target", "target_default")
  light_diffuse: tuple[Interval, float] | None = None
  light_specular: tuple[Interval, float] | None = None


def _pm(a: float) -> Interval:
  return (-a, a)


def _tilt(t: Interval, t_default: float) -> Interval:
  """Turns about the camera's x axis (degrees) that take xyaxes (1 0 0 0 t_default 1)
  to (1 0 0 0 t 1) for t in `t` (a larger t turns less)."""
  deg = lambda v: math.degrees(math.atan(v))
  return (deg(t_default) - deg(t[1]), deg(t_default) - deg(t[0]))


DOMAIN_RANGES: dict[str, DomainRanges] = {
    "walker": DomainRanges(
        camera="side", cam_pos=(_pm(.3), (-2.05, -1.95), (.6, .8)), cam_rot=_NO_ROT,
        light="light", light_pos=None, light_aim=(0, 0, 0),
        floor="floor", floor_tile=2.0),
    "hopper": DomainRanges(
        camera="cam0", cam_pos=(_pm(.15), (-3.0, -2.6), (.6, 1.0)),
        cam_rot=(_pm(5), _pm(5), _pm(5)),          # euler (U(85, 95), ±5, ±5)
        light="top", light_pos=None, light_aim=(0, 0, 0),
        floor="floor", floor_tile=2.0),
    "cheetah": DomainRanges(
        camera="side", cam_pos=(_pm(.25), (-3.2, -2.8), _pm(.25)), cam_rot=_NO_ROT,
        light="light", light_pos=(_pm(2), _pm(2), (1, 5)), light_aim=(0, 0, 0),
        floor="ground", floor_tile=2.0),
    "cartpole": DomainRanges(
        camera="fixed", cam_pos=(_pm(.15), (-5, -3), (.8, 1.2)), cam_rot=_NO_ROT,
        light="light", light_pos=(_pm(1), _pm(1), (4.5, 7.5)), light_aim=(0, 0, 0),
        floor="floor", floor_tile=2.0),
    "finger": DomainRanges(
        camera="cam0", cam_pos=(_pm(.02), (-1.01, -.99), (.7, 1.0)), cam_rot=_NO_ROT,
        light="light", light_pos=(_pm(.8), _pm(.8), (1, 3)), light_aim=(0, 0, 0),
        floor="ground", floor_tile=1.0,
        light_diffuse=FINGER_LIGHT_DIFFUSE, light_specular=FINGER_LIGHT_SPECULAR),
    "fish": DomainRanges(
        camera="tracking_top", cam_pos=(_pm(.05), _pm(.05), (.8, 1.2)), cam_rot=_NO_ROT,
        light="light", light_pos=(_pm(.3), _pm(.3), (0, 1)), light_aim=(0, 0, -.5),
        floor="ground", floor_tile=1.0),
    "humanoid": DomainRanges(
        camera="back", cam_pos=((-3.5, -2.5), _pm(.5), (.5, 1.5)), cam_rot=_NO_ROT,
        light="top", light_pos=(_pm(.7), _pm(.7), (1.2, 1.8)), light_aim=(0, 0, 0),
        floor="floor", floor_tile=2.0),
    "pendulum": DomainRanges(
        camera="fixed", cam_pos=((0, .2), (-1.1, -.97), (1.3, 1.6)),
        cam_rot=(_tilt((.4, .6), 1), (0, 0), (0, 0)),  # xyaxes (1 0 0 0 t 1), t ~ U(.4, .6)
        light="light", light_pos=(_pm(.5), _pm(.2), (1.2, 2.8)), light_aim=(0, 0, 0),
        floor="floor", floor_tile=1.0),
    "reacher": DomainRanges(
        camera="fixed", cam_pos=(_pm(.05), _pm(.05), (.7, .8)), cam_rot=_NO_ROT,
        light="light", light_pos=(_pm(.2), _pm(.2), (.15, .75)), light_aim=(0, 0, 0),
        floor="ground", floor_tile=0.6),
    "ball_in_cup": DomainRanges(
        camera="cam0", cam_pos=(_pm(.05), (-1.1, -.9), (.8, 1.0)), cam_rot=_NO_ROT,
        light="light", light_pos=(_pm(.5), _pm(.5), (1.2, 2.7)), light_aim=(0, 0, 0),
        floor="ground", floor_tile=1.0),
}
