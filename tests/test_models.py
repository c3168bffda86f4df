"""Every DMCR task against dm_control: observations, rewards, trajectories, protocol.

For each of the 22 tasks:
- state parity: 200 states from dm_control random rollouts are loaded into MJX;
  after the position/velocity stages are recomputed (`base.sync`), our
  observation and reward equal dm_control's `get_observation`/`get_reward` to
  1e-4. Acceleration-stage sensors (touch) describe the previous physics substep
  in dm_control (legacy stepping), so they cannot be recomputed from the state
  alone: they are carried over from dm_control here and checked by the
  trajectory test, which steps the physics.
- trajectory parity: from dm_control's initial states and the same 20 random
  actions, MJX (float32) stays within `TRAJECTORY_ATOL` of dm_control (float64).
- protocol: random steps keep the state finite and its shapes and dtypes (so a
  jitted step is traced once), with `done` exactly at the time limit (a full
  1,000-step episode per physics); `reset` repeats for a key and differs
  across keys.

Compile time dominates on CPU, so the tests run `reset` and `step` as their two
parts (`Task.reset = first_state ∘ forward ∘ initialize`,
`Task.step = next_state ∘ advance`): the physics parts are compiled once per
physics (`Task.physics_key`, shared by the tasks of a domain) and only the cheap
task parts once per task. `initialize` reads nothing but the key, the physics'
model and `TaskSpec.initialize`, so tasks of one physics that share the latter
(humanoid's rejection sampler, walker's, hopper's) share its compilation too.
`test_composed_matches_task` checks on one domain
that the jitted `Task.reset`/`Task.step` give the same states as the parts.
Each domain's tests run in one xdist group, so they share those compilations.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from dmcr_jax import models
from dmcr_jax.models import base
from tests import dmc_reference

# Largest |MJX − dm_control| allowed over 20 control steps (qpos, qvel, obs and
# reward). Float32 against float64 through contacts and constraint solvers;
# looser entries say why.
TRAJECTORY_ATOL = {
    "default": 1e-3,
    # Capsule–capsule contact with elliptic cones (fingertip hits the spinner):
    # MJX's contact forces differ from MuJoCo C's; f64 MJX drifts the same
    # (1.2e-3 at contact onset, 2.8e-2 rad/s in the hinge velocity after a
    # second hit); more solver iterations do not change it. f32: 2.7e-2.
    "finger": 5e-2,
    # f32: 6.7e-3 qvel spike at a contact onset (1.03e-2 compiled as the suite
    # compiles, without LLVM's optimisations: conftest); f64 MJX: 4.3e-4.
    "humanoid": 2e-2,
    "walker": 2e-2,  # f32 contact drift 2e-5 -> 4.7e-3 over 20 steps; f64 MJX: 1e-12
}

STATE_ATOL = 1e-4

# Every jitted call uses this batch size, so each function compiles once.
B = 4
STEPS_FROM_RESET = 100
"""Steps a random episode runs from its reset before it jumps to its end (`test_random_episode`)."""
STEPS_AT_END = 10
"""Steps a random episode runs up to its time limit (after the jump), and the steps
of a task whose physics another task's episode ran (`test_random_episode`)."""


@functools.cache
def physics(key: tuple) -> "Physics":
  return Physics(key)


class Physics:
  """The jitted, vmapped physics parts, compiled once per `Task.physics_key`."""

  def __init__(self, key: tuple):
    domain = key[0]
    task = next(t for t in (models.load(f"{domain}-{n}")
                            for n in models.DOMAIN_TASKS[domain])
                if t.physics_key == key)
    m = task.mjx_model
    self.traces = 0

    def counted_advance(data, action):
      self.traces += 1
      return task.advance(data, action)

    def counted_forward(data):
      self.traces += 1
      return task.forward(data)

    self.forward = jax.jit(jax.vmap(counted_forward))
    self.advance = jax.jit(jax.vmap(counted_advance))
    self.sync = jax.jit(jax.vmap(lambda d: base.sync(m, d)))
    # Built under `jit`, so its arrays are uncommitted like those `reset` returns:
    # a committed input would make `advance` compile a second time (for another
    # input sharding) without tracing again, unseen by the trace counts.
    self.blank = jax.jit(jax.vmap(lambda _: mjx.make_data(m)))(jnp.zeros(B))
    self.initializers = {}  # TaskSpec.initialize -> its jitted, vmapped Task.initialize

  def initialize(self, task):
    """`task.initialize`, compiled once per `TaskSpec.initialize` of this physics."""
    draw = task.spec.initialize
    if draw not in self.initializers:
      self.initializers[draw] = jax.jit(jax.vmap(task.initialize))
    return self.initializers[draw]


class Harness:
  """One task's jitted parts, composed with its domain's shared physics."""

  def __init__(self, name: str):
    self.task = task = models.load(name)
    self.physics = physics(task.physics_key)
    self.traces = 0

    def counted_next_state(state, data):
      self.traces += 1
      return task.next_state(state, data)

    self.initialize = self.physics.initialize(task)
    self.first_state = jax.jit(jax.vmap(task.first_state))
    self.next_state = jax.jit(jax.vmap(counted_next_state))
    self.observe = jax.jit(jax.vmap(task.observe))

  def reset(self, keys: jax.Array) -> base.State:
    data, info = self.initialize(keys)
    return self.first_state(self.physics.forward(data), info)

  def step(self, state: base.State, action) -> base.State:
    return self.next_state(state, self.physics.advance(state.data, action))

  def states(self, rec: dmc_reference.Records) -> base.State:
    """dm_control's recorded states as synced `State`s with their obs/reward."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    data = self.physics.blank.replace(qpos=f32(rec.qpos), qvel=f32(rec.qvel), act=f32(rec.act),
                        ctrl=f32(rec.ctrl), sensordata=f32(rec.sensordata),
                        qacc_warmstart=f32(rec.qacc_warmstart))
    data = self.physics.sync(data)
    info = {k: f32(v) for k, v in rec.info.items()}
    obs, reward = self.observe(data, info)
    n = len(rec.reward)
    return base.State(data=data, obs=obs, reward=reward,
                      done=jnp.zeros((n,), bool), step_count=jnp.zeros((n,), jnp.int32),
                      info=info)


@functools.cache
def harness(name: str) -> Harness:
  return Harness(name)


SLOW_DOMAINS = ("cheetah", "finger", "hopper", "humanoid", "walker")
"""Domains whose tests here take over ~12 s each on a 2-core CPU: marked slow, so
`pytest -m "not slow"` keeps the other domains' dm_control checks."""
PARAMS = [pytest.param(n, marks=[pytest.mark.xdist_group(models.split_name(n)[0])]
                       + ([pytest.mark.slow] if models.split_name(n)[0] in SLOW_DOMAINS
                          else []))
          for n in models.ALL_TASKS]


@pytest.mark.parametrize("name", PARAMS)
def test_state_parity(name):
  h = harness(name)
  rec = dmc_reference.random_rollout_states(name, n_states=200)
  assert len(rec.reward) == 200
  chunks = [h.states(rec.take(slice(i, i + B))) for i in range(0, 200, B)]
  # Joined on the host: an eager concatenation of every field of the states would
  # compile one program per field shape.
  obs = np.concatenate([np.asarray(c.obs, np.float64) for c in chunks])
  reward = np.concatenate([np.asarray(c.reward, np.float64) for c in chunks])
  assert obs.shape == rec.obs.shape, (obs.shape, rec.obs.shape)
  obs_err = np.abs(obs - rec.obs)
  rew_err = np.abs(reward - rec.reward)
  worst = np.unravel_index(np.argmax(obs_err), obs_err.shape)
  assert obs_err.max() <= STATE_ATOL, (
      f"obs max err {obs_err.max():.2e} at state {worst[0]}, index {worst[1]} "
      f"({h.task.observation_shapes})")
  assert rew_err.max() <= STATE_ATOL, f"reward max err {rew_err.max():.2e}"


@pytest.mark.parametrize("name", PARAMS)
def test_trajectory_parity(name):
  h = harness(name)
  task = h.task
  rng = np.random.RandomState(1)
  T = 20
  actions = rng.uniform(task.action_low, task.action_high, (T, B, task.action_size))
  init, steps = dmc_reference.trajectories(name, actions, seeds=range(B))
  s = h.states(init)
  errs = []
  for t in range(T):
    s = h.step(s, jnp.asarray(actions[t], jnp.float32))
    ref = steps[t]
    errs.append(max(
        np.abs(np.asarray(s.data.qpos) - ref.qpos).max(),
        np.abs(np.asarray(s.data.qvel) - ref.qvel).max(),
        np.abs(np.asarray(s.obs) - ref.obs).max(),
        np.abs(np.asarray(s.reward) - ref.reward).max()))
  atol = TRAJECTORY_ATOL.get(name, TRAJECTORY_ATOL.get(task.spec.domain,
                                                       TRAJECTORY_ATOL["default"]))
  assert max(errs) <= atol, f"drift per step: {np.array2string(np.array(errs), precision=2)}"


def _types(tree) -> list[tuple]:
  return [(x.shape, x.dtype, jax.typeof(x).weak_type) for x in jax.tree.leaves(tree)]


def _first_of_its_physics(task) -> bool:
  domain = task.spec.domain
  return next(n for n in models.DOMAIN_TASKS[domain]
              if models.load(f"{domain}-{n}").physics_key == task.physics_key
              ) == task.spec.task


@pytest.mark.parametrize("name", PARAMS)
def test_random_episode(name):
  """Random actions keep the state finite and its types fixed; done at the limit.

  The step's jitted parts (`advance` shared by the physics, `next_state` per
  task) trace at most at the episode's first step, never after it. (Whether an
  earlier test's trace is reused depends on what else ran in the process: JAX's
  tracing caches are bounded, and MJX traces fill them.)

  The first task of each physics group runs its first `STEPS_FROM_RESET` steps,
  then its step counter jumps to the last `STEPS_AT_END` steps of the episode
  (1,000 steps: a whole one takes up to 0.1 s a step on two CPU cores); the
  others, whose physics is the same, run `STEPS_AT_END` steps from their own reset.
  """
  h = harness(name)
  task = h.task
  s = h.reset(jax.random.split(jax.random.key(3), B))
  structure, types = jax.tree.structure(s), _types(s)
  steps = task.time_limit if _first_of_its_physics(task) else STEPS_AT_END
  jump = STEPS_FROM_RESET if steps > STEPS_FROM_RESET + STEPS_AT_END else None
  rng = np.random.RandomState(4)
  actions = rng.uniform(task.action_low, task.action_high,
                        (steps, B, task.action_size)).astype(np.float32)
  t, traces = 0, None
  while t < steps:
    if t == 1:
      traces = (h.traces, h.physics.traces)
    if t == jump:
      t = task.time_limit - STEPS_AT_END
      s = s.replace(step_count=jnp.full_like(s.step_count, t))
    s = h.step(s, actions[t])
    obs, reward, done = jax.device_get((s.obs, s.reward, s.done))
    assert np.isfinite(obs).all() and np.isfinite(reward).all(), f"step {t}"
    assert done.all() == (t == task.time_limit - 1) and done.all() == done.any(), t
    t += 1
  # Same structure, shapes, dtypes and weak types: a jitted step traces once.
  assert jax.tree.structure(s) == structure
  assert _types(s) == types
  # No step after the first traced `next_state` or the physics again.
  assert (h.traces, h.physics.traces) == traces
  assert 1 <= h.traces and 1 <= h.physics.traces
  assert task.time_limit == 1000


@pytest.mark.parametrize("name", PARAMS)
def test_reset_repeats_for_a_key_and_differs_across_keys(name):
  h = harness(name)
  keys = jax.random.split(jax.random.key(7), B)
  s1, s2 = h.reset(keys), h.reset(keys)
  np.testing.assert_array_equal(np.asarray(s1.obs), np.asarray(s2.obs))
  np.testing.assert_array_equal(np.asarray(s1.data.qpos), np.asarray(s2.data.qpos))
  q = np.asarray(s1.data.qpos)
  assert all(not np.array_equal(q[0], q[i]) for i in range(1, len(q)))


@pytest.mark.slow
@pytest.mark.xdist_group("cartpole")
def test_composed_matches_task():
  """The jitted `Task.reset`/`Task.step` equal the tests' composed parts."""
  h = harness("cartpole-swingup")
  task = h.task
  traces = []

  def counted_step(state, action):
    traces.append(1)
    return task.step(state, action)

  step = jax.jit(jax.vmap(counted_step))
  keys = jax.random.split(jax.random.key(5), B)
  s, r = jax.jit(jax.vmap(task.reset))(keys), h.reset(keys)
  for t in range(3):
    for a, b in zip(jax.tree.leaves(s), jax.tree.leaves(r)):  # two programs: last bits
      np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
    # float32, not weak-typed: the parts then reuse `advance`'s compilation.
    action = jnp.full((B, task.action_size), 0.3 * t - 0.4, jnp.float32)
    s, r = step(s, action), h.step(r, action)
  assert len(traces) == 1


@pytest.mark.parametrize("name", PARAMS)
def test_matches_dm_control_specs(name):
  h = harness(name)
  env = dmc_reference.load_env(name, 0)
  assert h.task.n_sub_steps == env._n_sub_steps
  assert h.task.time_limit == env._step_limit
  spec = env.action_spec()
  np.testing.assert_allclose(h.task.action_low, spec.minimum)
  np.testing.assert_allclose(h.task.action_high, spec.maximum)
  obs_spec = env.observation_spec()
  assert list(h.task.observation_shapes) == list(obs_spec)
  for k, v in obs_spec.items():
    assert int(np.prod(h.task.observation_shapes[k])) == int(np.prod(v.shape)), k
  # The physics layout is dm_control's.
  assert h.task.mj_model.nq == env.physics.model.nq
  assert h.task.mj_model.nv == env.physics.model.nv


def _dot_precisions(lowered_text: str) -> list[str]:
  """The `precision = [...]` of every dot_general in lowered StableHLO text."""
  lines = [line for line in lowered_text.splitlines() if "stablehlo.dot_general" in line]
  return [line.split("precision = ")[1].split("]")[0] + "]" if "precision = " in line
          else "none" for line in lines]


@pytest.mark.slow
@pytest.mark.xdist_group("cheetah")
def test_physics_products_traced_in_float32():
  """Every matrix product of reset and step is traced at HIGHEST precision.

  A GPU's default lets float32 products run in TensorFloat-32, which on an H100
  made MJX drift from dm_control by orders of magnitude (base module docstring);
  a CPU computes float32 either way, so the traced precision is what is checked.
  Cheetah's reset runs `mjx.forward` and physics steps in its `initialize`.
  `Task.reset` and `Task.step` are compositions of the jitted parts that the
  cheetah tests call (`test_composed_matches_task`): each part is lowered at the
  arguments those tests gave it, so its trace is theirs (in the cheetah group).
  """
  h = harness("cheetah-run")
  task = h.task
  keys = jax.random.split(jax.random.key(3), B)
  data, info = h.initialize(keys)
  forwarded = h.physics.forward(data)
  state = h.first_state(forwarded, info)
  action = jnp.zeros((B, task.action_size), jnp.float32)
  advanced = h.physics.advance(state.data, action)
  parts = (h.initialize.lower(keys), h.physics.forward.lower(data),
           h.first_state.lower(forwarded, info), h.physics.advance.lower(state.data, action),
           h.next_state.lower(state, advanced))
  products = []
  for lowered in parts:
    products += _dot_precisions(lowered.as_text())
  assert products, "no matrix products found: the check would pass vacuously"
  assert set(products) == {"[HIGHEST, HIGHEST]"}, sorted(set(products))
  # Both halves have products of their own: reset's (initialize, forward) and step's.
  assert _dot_precisions(parts[0].as_text()) and _dot_precisions(parts[3].as_text())
  keys = jax.random.split(jax.random.key(0), 2)
  # The check itself, on pendulum (the cheapest physics to trace): a bare MJX step
  # outside the tasks' wrappers is not HIGHEST; the diagnostic switch of the
  # benchmarks reaches the physics, and only inside its block.
  small = models.load("pendulum-swingup")
  state = jax.jit(jax.vmap(small.reset)).trace(keys).out_info
  action = jax.ShapeDtypeStruct((2, small.action_size), jnp.float32)
  bare = jax.jit(jax.vmap(lambda d: mjx.step(small.mjx_model, d))).lower(state.data).as_text()
  assert _dot_precisions(bare) and "[HIGHEST, HIGHEST]" not in set(_dot_precisions(bare))
  with base.physics_matmul_precision("default"):
    lowered = jax.jit(jax.vmap(small.step)).lower(state, action).as_text()
  assert set(_dot_precisions(lowered)) == {"[DEFAULT, DEFAULT]"}
  assert base.PHYSICS_MATMUL_PRECISION == "highest"
  with pytest.raises(ValueError, match="highest"):
    with base.physics_matmul_precision("fp8"):
      pass
