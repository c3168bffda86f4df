"""The task protocol every DMCR domain implements, and the MJX stepping it shares.

A `Task` is built from a domain's `TaskSpec` (pure JAX functions ported from
dm_control's Python task) and dm_control's own MJCF model. It offers the
brax/Playground protocol: `reset(key) -> State` and `step(state, action) -> State`,
both pure, jittable and vmappable, written for one env (batch with `jax.vmap`).

One `step` is one dm_control control step: the action is clipped to the actuator
bounds and written to `ctrl`, the physics advances `n_sub_steps` MJX steps, and
then the position and velocity stages (and their sensors) are recomputed, as
dm_control's legacy stepping (`mj_step2` … `mj_step1`) leaves them. Acceleration
stage quantities (touch sensors, contact forces) therefore describe the start of
the last substep, exactly as in dm_control.

Task variables that dm_control stores in the *model* (a reacher target's
`geom_pos`, a finger target's `site_pos`, …) live in `State.info` under keys of the
form ``"<model field>:<element name>"`` (e.g. ``"geom_pos:target"``). They never
touch the physics (those elements do not collide) and a renderer applies them by
writing `model.<field>[<id of name>] = value`.

Non-finite actions: `step` cannot raise inside `jit`, so NaN entries become 0 and
±inf become the nearest bound (after `jnp.nan_to_num` and clipping); the
observation is never NaN because of an action. Host-side wrappers (the env)
reject non-finite actions with an error before they get here.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

Info = dict[str, jax.Array]
Observation = Mapping[str, jax.Array]


@struct.dataclass
class State:
  """The state of one env after `reset` or `step` (a frozen pytree).

  Attributes:
    data: the MJX physics data, synced like dm_control's after a step.
    obs: the flat float32 observation: dm_control's state features,
      concatenated (each raveled) in dm_control's order.
    reward: float32 scalar reward of the last step (0 after reset).
    done: bool scalar, True once the time limit is reached (DMC tasks never
      terminate early).
    step_count: int32 number of control steps since reset.
    info: task variables (targets, model overrides) as named arrays.
  """
  data: mjx.Data
  obs: jax.Array
  reward: jax.Array
  done: jax.Array
  step_count: jax.Array
  info: Info


@dataclasses.dataclass(frozen=True)
class TaskSpec:
  """What a domain module supplies for one task; `build_task` turns it into a `Task`.

  Attributes:
    domain: dm_control domain name, e.g. "walker".
    task: dm_control task name, e.g. "walk".
    initialize: `(key, model, data) -> (data, info)`: the initial-state
      distribution, a port of the dm_control task's `initialize_episode`.
      `data` arrives freshly reset (`mjx.make_data`); `mjx.forward` runs after.
    observation: `(model, data, info) -> dict` of named arrays in dm_control's
      order (a port of `get_observation`).
    reward: `(model, data, info) -> scalar` (a port of `get_reward`).
    control_timestep: dm_control's control timestep in seconds, or None when the
      environment steps the physics once per control step.
    time_limit: episode length in seconds (dm_control's default time limit).
    model_variables: `(field, name)` pairs of model entries that the task
      randomises per episode; each is kept in `info["field:name"]`.
    mjx_fix: optional `(mujoco.MjModel) -> None` that edits the model in place
      to make it simulable in MJX without changing its dynamics (documented in
      the domain module).
  """
  domain: str
  task: str
  initialize: Callable[[jax.Array, mjx.Model, mjx.Data], tuple[mjx.Data, Info]]
  observation: Callable[[mjx.Model, mjx.Data, Info], Observation]
  reward: Callable[[mjx.Model, mjx.Data, Info], jax.Array]
  control_timestep: float | None = None
  time_limit: float = 1000.0
  model_variables: tuple[tuple[str, str], ...] = ()
  mjx_fix: Callable[[mujoco.MjModel], None] | None = None

  @property
  def name(self) -> str:
    return f"{self.domain}-{self.task}"


def _suite_module(domain: str):
  import importlib
  return importlib.import_module(f"dm_control.suite.{domain}")


def load_mj_model(spec: TaskSpec) -> mujoco.MjModel:
  """Compiles dm_control's suite MJCF for `spec.domain` and applies MJX fixes.

  The only edits are those that MJX needs and that leave the dynamics unchanged:
  the `energy` flag is switched off (it only computes diagnostics), and the
  domain's own `mjx_fix`, if any.
  """
  xml, assets = _suite_module(spec.domain).get_model_and_assets()
  model = mujoco.MjModel.from_xml_string(xml, assets)
  model.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_ENERGY)
  if spec.mjx_fix is not None:
    spec.mjx_fix(model)
  return model


def sync(m: mjx.Model, d: mjx.Data) -> mjx.Data:
  """Recomputes position- and velocity-stage quantities and their sensors.

  This is what `mj_step1` leaves behind in dm_control's legacy stepping: body and
  geom poses, centre-of-mass quantities, tendon lengths, body velocities and the
  position/velocity sensors all describe the current `qpos`, `qvel`.
  """
  d = mjx.kinematics(m, d)
  d = mjx.com_pos(m, d)
  d = mjx.tendon(m, d)
  d = mjx.sensor_pos(m, d)
  d = mjx.com_vel(m, d)
  d = mjx.sensor_vel(m, d)
  return d


def physics_steps(m: mjx.Model, d: mjx.Data, n: int) -> mjx.Data:
  """Advances the physics `n` MJX steps (a `fori_loop`, so compile size is O(1))."""
  if n == 1:
    return mjx.step(m, d)
  return jax.lax.fori_loop(0, n, lambda _, x: mjx.step(m, x), d)


def flatten_observation(obs: Observation) -> jax.Array:
  """Concatenates named observation arrays, each raveled, in their given order."""
  return jnp.concatenate([jnp.ravel(jnp.asarray(v, jnp.float32)) for v in obs.values()])


def _model_id(model: mujoco.MjModel, field: str, name: str) -> int:
  obj = {"geom": mujoco.mjtObj.mjOBJ_GEOM, "site": mujoco.mjtObj.mjOBJ_SITE,
         "body": mujoco.mjtObj.mjOBJ_BODY, "mat": mujoco.mjtObj.mjOBJ_MATERIAL,
         "cam": mujoco.mjtObj.mjOBJ_CAMERA, "light": mujoco.mjtObj.mjOBJ_LIGHT}[
             field.split("_")[0]]
  i = mujoco.mj_name2id(model, obj, name)
  if i < 0:
    raise ValueError(f"No {field.split('_')[0]} named {name!r} in the model.")
  return i


class Task:
  """One DMCR task: dm_control's model stepped by MJX with a JAX-ported task.

  Attributes:
    name: registry name, e.g. "walker-walk".
    spec: the domain's `TaskSpec`.
    mj_model: the compiled `mujoco.MjModel` (dm_control's MJCF, MJX fixes applied).
    mjx_model: the same model on the default device.
    n_sub_steps: physics steps per control step.
    time_limit: control steps per episode.
    action_low, action_high: float32 action bounds, shape (action_size,).
    observation_shapes: dm_control's observation names and their shapes.
    observation_size, action_size: flat sizes.
  """

  def __init__(self, spec: TaskSpec):
    self.spec = spec
    self.name = spec.name
    self.mj_model = load_mj_model(spec)
    self.mjx_model = mjx.put_model(self.mj_model)
    dt = float(self.mj_model.opt.timestep)
    if spec.control_timestep is None:
      self.n_sub_steps = 1
      control_dt = dt
    else:
      self.n_sub_steps = int(round(spec.control_timestep / dt))
      control_dt = spec.control_timestep
    self.control_timestep = control_dt
    self.time_limit = int(round(spec.time_limit / control_dt)) if np.isfinite(
        spec.time_limit) else np.iinfo(np.int32).max
    limited = self.mj_model.actuator_ctrllimited.astype(bool)
    rng = self.mj_model.actuator_ctrlrange
    self.action_low = np.where(limited, rng[:, 0], -np.inf).astype(np.float32)
    self.action_high = np.where(limited, rng[:, 1], np.inf).astype(np.float32)
    self.action_size = int(self.mj_model.nu)
    self.model_variable_ids = {
        f"{field}:{name}": (field, _model_id(self.mj_model, field, name))
        for field, name in spec.model_variables}
    state = jax.eval_shape(self.reset, jax.random.key(0))
    names: list[str] = []

    def parts(s):  # a list keeps dm_control's order (pytree dicts are key-sorted)
      obs = spec.observation(self.mjx_model, s.data, s.info)
      names[:] = list(obs)
      return list(obs.values())

    shapes = jax.eval_shape(parts, state)
    self.observation_shapes = {k: tuple(v.shape) for k, v in zip(names, shapes)}
    self.observation_size = int(state.obs.shape[0])

  def __repr__(self):
    return (f"Task({self.name!r}, obs={self.observation_size}, "
            f"act={self.action_size}, n_sub_steps={self.n_sub_steps}, "
            f"time_limit={self.time_limit})")

  # The protocol -------------------------------------------------------------

  def reset(self, key: jax.Array) -> State:
    """Samples an initial state (dm_control's `initialize_episode`, then `mj_forward`).

    Args:
      key: a `jax.random` key (the dynamics seed).

    Returns:
      The initial `State` with reward 0 and step_count 0.
    """
    m = self.mjx_model
    d = mjx.make_data(m)
    d, info = self.spec.initialize(key, m, d)
    d = mjx.forward(m, d)
    obs = flatten_observation(self.spec.observation(m, d, info))
    return State(data=d, obs=obs, reward=jnp.zeros((), jnp.float32),
                 done=jnp.zeros((), bool), step_count=jnp.zeros((), jnp.int32),
                 info=info)

  def step(self, state: State, action: jax.Array) -> State:
    """Advances one control step.

    Args:
      state: the current `State`.
      action: float array of shape (action_size,); clipped to the bounds,
        NaN → 0 (see the module docstring).

    Returns:
      The next `State`.
    """
    m = self.mjx_model
    action = jnp.nan_to_num(jnp.asarray(action, jnp.float32), nan=0.0)
    action = jnp.clip(action, self.action_low, self.action_high)
    d = state.data.replace(ctrl=action)
    d = physics_steps(m, d, self.n_sub_steps)
    d = sync(m, d)
    obs = flatten_observation(self.spec.observation(m, d, state.info))
    reward = jnp.asarray(self.spec.reward(m, d, state.info), jnp.float32)
    count = state.step_count + 1
    return state.replace(data=d, obs=obs, reward=reward,
                         done=count >= self.time_limit, step_count=count)

  # Helpers for tests, renderers and converters --------------------------------

  def info_from_physics(self, physics: Any) -> Info:
    """Reads the task variables of a dm_control `Physics` into an `info` dict."""
    info = {}
    for key, (field, i) in self.model_variable_ids.items():
      info[key] = jnp.asarray(np.array(getattr(physics.model, field)[i]),
                              jnp.float32)
    return info

  def apply_model_variables(self, model: mujoco.MjModel, info: Mapping) -> None:
    """Writes `info`'s model variables into a (renderer's) `mujoco.MjModel`."""
    for key, (field, i) in self.model_variable_ids.items():
      getattr(model, field)[i] = np.asarray(info[key])


@functools.cache
def _cached_task(spec: TaskSpec) -> Task:
  return Task(spec)


def build_task(spec: TaskSpec) -> Task:
  """Builds (once per spec, cached) the `Task` for a `TaskSpec`."""
  return _cached_task(spec)
