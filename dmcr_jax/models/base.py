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

Solver budget: the solver keeps dm_control's iteration limit and tolerance, but
the line search is capped at `DEFAULT_LS_ITERATIONS` (16; dm_control asks for 50).
The cap is an MJX fix, not a physics change: MuJoCo C stops a line search once it
converges, while MJX runs it as a fixed-length scan whose every step costs the
same under `vmap`, so the cap bounds the cost of every physics step. It lies above
the most cost evaluations dm_control's line search uses in random episodes of
every task, so trajectories stay close to those of the uncapped search and
their drift from dm_control is unchanged (`dmcr_jax.benchmarks.solver_budget`; results in
benchmarks/results/solver_budget_*.md). `load(name, solver_iterations=...,
ls_iterations=...)` overrides either budget; smaller solver budgets are faster but
do drift (mjx.benchmark's 1 / 4 makes walker diverge).

Compiling physics for the CPU: `physics_jit` is `jax.jit` with
`physics_compiler_options()`, which turn off XLA:CPU's YNNPACK library fusions.
Past a batch size that depends on the model and the CPU, XLA hands the physics'
batched small matrix products to YNNPACK, which computes them several times slower
than XLA's own loops: the physics of a larger batch then costs more per env than
that of a smaller one (benchmarks/results/physics_cpu_ynn.md). The option only affects
XLA's CPU backend; networks and renderers keep XLA's default.

Matrix-product precision: every physics part (`sync`, `physics_steps` and a
task's `initialize`, `forward`, `advance`, `observe`) is traced under
`jax.default_matmul_precision(PHYSICS_MATMUL_PRECISION)` ("highest": float32
products). JAX's default lets a GPU with tensor cores compute float32 products in
TensorFloat-32 (a 10-bit mantissa), which makes MJX drift from dm_control by
orders of magnitude more than float32 does; the drift and the speed of both
precisions: benchmarks/results/solver_budget_h100.md, physics_h100_precision.md. Networks
and other callers keep their own precision. `physics_matmul_precision(...)` sets
another precision for physics traced inside it (for measuring this:
`dmcr_jax.benchmarks.solver_budget --precisions`, `dmcr_jax.benchmarks.physics --matmul-precision`).

Non-finite actions: `step` cannot raise inside `jit`, so NaN entries become 0 and
±inf become the nearest bound (after `jnp.nan_to_num` and clipping); the
observation is never NaN because of an action. Host-side wrappers (the env)
reject non-finite actions with an error before they get here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from dmcr_jax._mjx import mjx  # mujoco.mjx, quietly

from dmcr_jax.models.names import compile_suite_model, field_id

Info = dict[str, jax.Array]

# Line-search cap (MJX runs the line search as a fixed-length scan); see above.
DEFAULT_LS_ITERATIONS = 16
# Precision of the physics' matrix products; see "Matrix-product precision" above.
PHYSICS_MATMUL_PRECISION = "highest"
# The names `jax.default_matmul_precision` accepts.
MATMUL_PRECISIONS = ("default", "high", "highest", "bfloat16", "tensorfloat32", "float32")
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
    model_edit: optional `(mujoco.MjModel) -> None` that edits the compiled
      model in place: either a fix that lets MJX simulate it without changing
      its dynamics, or a constant that the dm_control task writes into the
      model every episode (documented in the domain module). Tasks with the
      same domain and `model_edit` share their physics.
  """
  domain: str
  task: str
  initialize: Callable[[jax.Array, mjx.Model, mjx.Data], tuple[mjx.Data, Info]]
  observation: Callable[[mjx.Model, mjx.Data, Info], Observation]
  reward: Callable[[mjx.Model, mjx.Data, Info], jax.Array]
  control_timestep: float | None = None
  time_limit: float = 1000.0
  model_variables: tuple[tuple[str, str], ...] = ()
  model_edit: Callable[[mujoco.MjModel], None] | None = None

  @property
  def name(self) -> str:
    return f"{self.domain}-{self.task}"



def task_variants(variants: Mapping[str, Mapping[str, Mapping[str, Any]]],
                  **common: Any) -> dict[str, TaskSpec]:
  """The tasks of a domain that differ only in arguments of the same functions.

  dm_control builds such tasks from one task class with constructor arguments
  (walker's `move_speed`, cartpole's `swing_up` and `sparse`). Here every task is
  `TaskSpec(task=name, **common)` with, for each field its entry names, that
  field's function given those keyword arguments (`functools.partial`).

  Args:
    variants: {task name: {field ("initialize", "observation" or "reward"):
      {keyword: value}}}; an empty entry takes `common` as it is.
    **common: the `TaskSpec` fields the tasks share (all but `task`).

  Returns:
    {task name: TaskSpec}, in the order of `variants`.
  """
  return {task: TaskSpec(task=task, **{
      **common, **{f: functools.partial(common[f], **kw) for f, kw in bound.items()}})
          for task, bound in variants.items()}

def load_mj_model(spec: TaskSpec) -> mujoco.MjModel:
  """Compiles dm_control's suite MJCF for `spec.domain` and applies MJX fixes.

  The only edits are those that MJX needs and that leave the dynamics unchanged:
  the `energy` flag is switched off (it only computes diagnostics), and the
  task's own `model_edit`, if any.
  """
  model = compile_suite_model(spec.domain)
  model.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_ENERGY)
  if spec.model_edit is not None:
    spec.model_edit(model)
  return model


def full_precision(fn: Callable) -> Callable:
  """`fn` traced under `jax.default_matmul_precision(PHYSICS_MATMUL_PRECISION)`.

  The precision is fixed when a product is traced, so this holds inside any
  caller's `jit`, `vmap` or `scan`; products that name a precision keep it.
  """
  @functools.wraps(fn)
  def wrapped(*args, **kwargs):
    with jax.default_matmul_precision(PHYSICS_MATMUL_PRECISION):
      return fn(*args, **kwargs)
  return wrapped


@contextlib.contextmanager
def physics_matmul_precision(precision: str):
  """Physics traced inside the block computes its products at `precision` (one of
  `MATMUL_PRECISIONS`; "default" is JAX's, TensorFloat-32 on GPUs with tensor cores) instead of
  `PHYSICS_MATMUL_PRECISION`. For measuring what float32 buys; functions traced
  before or after the block are unaffected."""
  global PHYSICS_MATMUL_PRECISION
  if precision not in MATMUL_PRECISIONS:
    raise ValueError(f"matmul precision {precision!r} is not one of "
                     f"{', '.join(MATMUL_PRECISIONS)}")
  saved, PHYSICS_MATMUL_PRECISION = PHYSICS_MATMUL_PRECISION, precision
  try:
    yield
  finally:
    PHYSICS_MATMUL_PRECISION = saved


NO_YNN_FUSIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}
"""XLA compile options with an empty list of YNNPACK fusion types (module doc)."""


@functools.cache
def physics_compiler_options() -> dict[str, str]:
  """`jax.jit`'s `compiler_options` for functions that step MJX physics.

  `NO_YNN_FUSIONS` when this jaxlib knows the option (checked once, by compiling
  an identity for JAX's default backend), else {}. The options are read by XLA's
  CPU backend only, so a jit for any device may take them.
  """
  try:
    jax.jit(lambda x: x, compiler_options=NO_YNN_FUSIONS).lower(np.float32(0)).compile()
  except jax.errors.JaxRuntimeError:  # an older or newer jaxlib: "No such compile option"
    return {}
  return dict(NO_YNN_FUSIONS)


def physics_jit(fn: Callable, **jit_kwargs) -> Callable:
  """`jax.jit(fn, **jit_kwargs)` with `physics_compiler_options()` (module doc): for
  jitted functions whose work is MJX physics, batched or not."""
  return jax.jit(fn, compiler_options=physics_compiler_options() or None, **jit_kwargs)


@full_precision
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


@full_precision
def physics_steps(m: mjx.Model, d: mjx.Data, n: int) -> mjx.Data:
  """Advances the physics `n` MJX steps (a `fori_loop`, so compile size is O(1))."""
  if n == 1:
    return mjx.step(m, d)
  return jax.lax.fori_loop(0, n, lambda _, x: mjx.step(m, x), d)


def flatten_observation(obs: Observation) -> jax.Array:
  """Concatenates named observation arrays, each raveled, in their given order."""
  return jnp.concatenate([jnp.ravel(jnp.asarray(v, jnp.float32)) for v in obs.values()])


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

  def __init__(self, spec: TaskSpec, solver_iterations: int | None = None,
               ls_iterations: int | None = None):
    self.spec = spec
    self.name = spec.name
    self.mj_model = load_mj_model(spec)
    if ls_iterations is None:
      ls_iterations = min(int(self.mj_model.opt.ls_iterations), DEFAULT_LS_ITERATIONS)
    for field, value in (("iterations", solver_iterations), ("ls_iterations", ls_iterations)):
      if value is not None:
        if not isinstance(value, (int, np.integer)) or value < 1:
          raise ValueError(f"{field} must be a positive int or None (the default), got {value!r}")
        setattr(self.mj_model.opt, field, int(value))
    self.solver_iterations = int(self.mj_model.opt.iterations)
    self.ls_iterations = int(self.mj_model.opt.ls_iterations)
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
        f"{field}:{name}": (field, field_id(self.mj_model, field, name))
        for field, name in spec.model_variables}
    # Shapes only: `forward` does not change them, so it is not traced here.
    initial = jax.eval_shape(self.initialize, jax.random.key(0))
    names: list[str] = []

    def parts(data, info):  # a list keeps dm_control's order (dicts get key-sorted)
      obs = spec.observation(self.mjx_model, data, info)
      names[:] = list(obs)
      return list(obs.values())

    shapes = jax.eval_shape(parts, *initial)
    self.observation_shapes = {k: tuple(v.shape) for k, v in zip(names, shapes)}
    self.observation_size = int(sum(np.prod(v.shape, dtype=int) for v in shapes))

  def __repr__(self):
    return (f"Task({self.name!r}, obs={self.observation_size}, "
            f"act={self.action_size}, n_sub_steps={self.n_sub_steps}, "
            f"time_limit={self.time_limit}, solver={self.solver_iterations}/"
            f"{self.ls_iterations})")

  # The protocol -------------------------------------------------------------

  def reset(self, key: jax.Array) -> State:
    """Samples an initial state (dm_control's `initialize_episode`, then `mj_forward`).

    Args:
      key: a `jax.random` key (the dynamics seed).

    Returns:
      The initial `State` with reward 0 and step_count 0.
    """
    data, info = self.initialize(key)
    return self.first_state(self.forward(data), info)

  def step(self, state: State, action: jax.Array) -> State:
    """Advances one control step.

    Args:
      state: the current `State`.
      action: float array of shape (action_size,); clipped to the bounds,
        NaN → 0 (see the module docstring).

    Returns:
      The next `State`.
    """
    return self.next_state(state, self.advance(state.data, action))

  # The parts of reset and step ----------------------------------------------
  #
  # `reset` and `step` compose a task part (cheap: initial-state sampling,
  # observation, reward) with a physics part (`forward`, `advance`) that depends
  # only on `physics_key`, so tools that batch several tasks of one domain (and
  # the tests) can compile the physics once per domain.

  @property
  def physics_key(self) -> tuple:
    """Tasks with equal keys have identical `forward` and `advance`."""
    return (self.spec.domain, self.spec.model_edit, self.n_sub_steps,
            self.solver_iterations, self.ls_iterations)

  @full_precision
  def initialize(self, key: jax.Array) -> tuple[mjx.Data, Info]:
    """The task's initial-state draw on fresh data (before `forward`).

    The data keeps `mjx.make_data`'s dtypes exactly (no weak types), so every
    task of a physics group hands `forward` the same types: it compiles once.
    """
    fresh = mjx.make_data(self.mjx_model)
    data, info = self.spec.initialize(key, self.mjx_model, fresh)
    data = jax.tree.map(lambda x, ref: jnp.asarray(x, ref.dtype), data, fresh)
    return data, {k: jnp.asarray(v, jnp.result_type(v)) for k, v in info.items()}

  @full_precision
  def forward(self, data: mjx.Data) -> mjx.Data:
    """`mj_forward`: every stage, as dm_control runs after `initialize_episode`."""
    return mjx.forward(self.mjx_model, data)

  def first_state(self, data: mjx.Data, info: Info) -> State:
    """The `State` right after reset, from forwarded data and task variables."""
    obs, _ = self.observe(data, info)
    return State(data=data, obs=obs, reward=jnp.zeros((), jnp.float32),
                 done=jnp.zeros((), bool), step_count=jnp.zeros((), jnp.int32),
                 info=info)

  @full_precision
  def advance(self, data: mjx.Data, action: jax.Array) -> mjx.Data:
    """The physics of one control step: clip the action, step, then `sync`."""
    m = self.mjx_model
    action = jnp.nan_to_num(jnp.asarray(action, jnp.float32), nan=0.0)
    action = jnp.clip(action, self.action_low, self.action_high)
    data = physics_steps(m, data.replace(ctrl=action), self.n_sub_steps)
    return sync(m, data)

  @full_precision
  def observe(self, data: mjx.Data, info: Info) -> tuple[jax.Array, jax.Array]:
    """The flat float32 observation and the float32 reward of synced `data`."""
    m = self.mjx_model
    obs = flatten_observation(self.spec.observation(m, data, info))
    return obs, jnp.asarray(self.spec.reward(m, data, info), jnp.float32)

  def next_state(self, state: State, data: mjx.Data) -> State:
    """The `State` after `state` once the physics has advanced to `data`."""
    obs, reward = self.observe(data, state.info)
    count = state.step_count + 1
    return state.replace(data=data, obs=obs, reward=reward,
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
def _cached_task(spec: TaskSpec, solver_iterations: int | None,
                 ls_iterations: int | None) -> Task:
  return Task(spec, solver_iterations, ls_iterations)


def build_task(spec: TaskSpec, solver_iterations: int | None = None,
               ls_iterations: int | None = None) -> Task:
  """Builds (once per spec and solver budget, cached) the `Task` for a `TaskSpec`."""
  return _cached_task(spec, solver_iterations, ls_iterations)
