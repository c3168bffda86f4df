"""dm_control's suite models and the name → id lookups in them, in one place.

`suite_xml(domain)` is dm_control's MJCF and assets for a suite domain,
`compile_suite_model` compiles a fresh `mujoco.MjModel` from them (for callers
that edit it) and `suite_model` the same compiled once and cached (read it, never
edit it); `suite_compile_quiet` compiles without the deprecation warning the
pinned MuJoCo prints for dm_control's own MJCF. `obj_id` and its shorthands look a named element up in a
`mujoco.MjModel` or an `mjx.Model` and raise a ValueError naming the element
when it is absent; `find_id` returns −1 instead. `field_id` looks up the element
of a model field (``"geom_pos"`` → the geom), as the task variables
``"<model field>:<element name>"`` name them. `sensor` reads a named sensor's
`sensordata` (static slice, so it traces into jitted code).
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import logging
import warnings

import mujoco
import numpy as np

_O = mujoco.mjtObj

FIELD_OBJECTS = {"geom": _O.mjOBJ_GEOM, "site": _O.mjOBJ_SITE, "body": _O.mjOBJ_BODY,
                 "mat": _O.mjOBJ_MATERIAL, "cam": _O.mjOBJ_CAMERA,
                 "light": _O.mjOBJ_LIGHT}
"""The element kind of a model field's prefix (``"geom"`` of ``"geom_pos"``)."""


def suite_xml(domain: str) -> tuple[str, dict[str, bytes]]:
  """dm_control's suite MJCF (text) and assets for `domain` (e.g. "walker")."""
  xml, assets = importlib.import_module(
      f"dm_control.suite.{domain}").get_model_and_assets()
  return (xml.decode() if isinstance(xml, bytes) else xml), dict(assets)


_SETTOTALMASS = "compiler attribute 'settotalmass' is deprecated"


def _not_settotalmass(record: logging.LogRecord) -> bool:
  return _SETTOTALMASS not in record.getMessage()


@contextlib.contextmanager
def suite_compile_quiet():
  """Context for compiling a suite model: drops MuJoCo's deprecation warning of
  the `settotalmass` compiler attribute (dm_control's cheetah sets it; the pinned
  MuJoCo still applies it, and a user cannot act on it). MuJoCo reports it as a
  Python warning, or on absl's log once dm_control has installed its warning
  callback; other warnings pass."""
  absl_log = logging.getLogger("absl")
  absl_log.addFilter(_not_settotalmass)
  try:
    with warnings.catch_warnings():
      warnings.filterwarnings("ignore", message=_SETTOTALMASS)
      yield
  finally:
    absl_log.removeFilter(_not_settotalmass)


def compile_suite_model(domain: str) -> mujoco.MjModel:
  """A freshly compiled dm_control suite model for `domain`, the caller's to edit."""
  with suite_compile_quiet():
    return mujoco.MjModel.from_xml_string(*suite_xml(domain))


@functools.cache
def suite_model(domain: str) -> mujoco.MjModel:
  """dm_control's suite model for `domain`, compiled once and shared: read-only."""
  return compile_suite_model(domain)


def find_id(m, obj: mujoco.mjtObj, name: str) -> int:
  """Id of the `obj` element called `name` in `m` (an `mujoco.MjModel` or an
  `mjx.Model`), −1 if there is none."""
  if isinstance(m, mujoco.MjModel):
    return int(mujoco.mj_name2id(m, obj, name))
  from dmcr_jax._mjx import mjx  # pylint: disable=g-import-not-at-top
  return int(mjx.name2id(m, obj, name))


def obj_id(m, obj: mujoco.mjtObj, name: str) -> int:
  """Id of the `obj` element called `name` in `m`; ValueError if there is none."""
  i = find_id(m, obj, name)
  if i < 0:
    kind = obj.name.removeprefix("mjOBJ_").lower()
    raise ValueError(f"No {kind} named {name!r} in the model.")
  return i


def field_id(m, field: str, name: str) -> int:
  """Id of the element called `name` whose model field is `field` (e.g.
  "geom_pos"); ValueError for a field prefix not in `FIELD_OBJECTS` or an absent
  name."""
  prefix = field.split("_")[0]
  if prefix not in FIELD_OBJECTS:
    raise ValueError(f"Model field {field!r} is not one of an element kind "
                     f"({', '.join(FIELD_OBJECTS)}).")
  return obj_id(m, FIELD_OBJECTS[prefix], name)


def body_id(m, name: str) -> int:
  """Id of the body called `name` (ValueError if absent)."""
  return obj_id(m, _O.mjOBJ_BODY, name)


def geom_id(m, name: str) -> int:
  """Id of the geom called `name` (ValueError if absent)."""
  return obj_id(m, _O.mjOBJ_GEOM, name)


def site_id(m, name: str) -> int:
  """Id of the site called `name` (ValueError if absent)."""
  return obj_id(m, _O.mjOBJ_SITE, name)


def joint_id(m, name: str) -> int:
  """Id of the joint called `name` (ValueError if absent)."""
  return obj_id(m, _O.mjOBJ_JOINT, name)


def qpos_adr(m, name: str) -> int:
  """Address in `qpos` of the joint called `name`."""
  return int(np.asarray(m.jnt_qposadr)[joint_id(m, name)])


def qvel_adr(m, name: str) -> int:
  """Address in `qvel` of the joint called `name`."""
  return int(np.asarray(m.jnt_dofadr)[joint_id(m, name)])


def sensor_indices(m, name: str) -> np.ndarray:
  """Static `sensordata` indices of the sensor called `name` (ValueError if absent)."""
  i = obj_id(m, _O.mjOBJ_SENSOR, name)
  adr = int(np.asarray(m.sensor_adr)[i])
  return np.arange(adr, adr + int(np.asarray(m.sensor_dim)[i]))


def sensor(m, d, name: str):
  """The `sensordata` of the sensor called `name` in data `d` of model `m` (a
  static slice, dm_control's ``physics.named.data.sensordata[name]``)."""
  i = obj_id(m, _O.mjOBJ_SENSOR, name)
  adr, dim = int(np.asarray(m.sensor_adr)[i]), int(np.asarray(m.sensor_dim)[i])
  return d.sensordata[adr:adr + dim]
