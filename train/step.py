"""One training step of K agents, as pure functions that both training drivers call.

A vector step of the K·N envs (agent k acts in envs k·N … k·N + N − 1) is, in
this order:

1. `act`: actions for the current observations — uniform in [−1, 1] while the
   agents' step count is below the warm-up (Table 6: 1,000 transitions), else
   samples of each agent's policy (`sac.act`);
2. `learn`: the gradient updates owed for the N transitions this step collects
   (`owed_updates`: `utd` per transition, none during the warm-up or a resumed
   run's refill, run in pairs:
   a critic-only update, then a full one), sampling the buffers as they are
   before this step's transitions (the DrQ, CURL and SAC-AE order: update, then
   env step); they wait, and accumulate, until every buffer can be sampled;
3. the env step (not here: the driver's);
4. `store`: the transition (the newest frame of the observation acted on, its
   episode-start flag, the action, the reward) into every agent's buffer.

The state between steps is one `Learner` (a frozen pytree). Its key is split by
`act` and by `learn`, every step, whether or not updates run, so one seed gives
one RNG stream whichever driver runs the step.

The drivers: `dmcr_jax.train.loop` (host driver) jits `act`, `learn` and `store` around a
gymnasium vector env (the render pool, or the JAX renderer with the physics on
the host CPU) and launches `learn` from a second thread while its own steps the
env (`step_async`, `step_wait`), so the accelerator runs the updates while the
env steps;
`dmcr_jax.train.device_loop` (device driver) scans them around `jax_env.PixelEnv.step` in
one XLA call per chunk of steps.

Agent batching (`StepSpec.agent_loop`, `over_agents`): "vmap" runs the K agents'
updates and policies as one batched computation (their convolutions become grouped
convolutions); "map" runs them one after the other in the same call
(`jax.lax.map`), faster on GPUs for several agents (`benchmarks/learner.py`). With a `mesh`, the agent axis is split
over its devices with `shard_map` (each device runs the vmapped function on its
own agents).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from dmcr_jax.train import replay, sac


@struct.dataclass
class Learner:
  """K agents and what they learn from (every array but `key` and `step` has a
  leading agent axis K).

  Attributes:
    agents: the `sac.AgentState`s.
    buffers: their `replay.ReplayBuffer`s.
    key: the run's PRNG key.
    step: int32 transitions per agent acted on so far (`act` counts them).
    metrics: name → float32 (K,) means of the latest updates (NaN before any).
  """
  agents: sac.AgentState
  buffers: replay.ReplayBuffer
  key: jax.Array
  step: jax.Array
  metrics: dict


@dataclasses.dataclass(frozen=True)
class StepSpec:
  """What a training step needs besides the `Learner` (static, hashable).

  Attributes:
    agents: K.
    num_envs: N, envs per agent.
    warmup_steps: random-action transitions per agent before learning.
    utd: gradient updates per transition.
    sac: the learner's hyperparameters.
    agent_loop: "vmap" or "map" (module doc).
    low, high: the env's action bounds (policy actions in [−1, 1] map onto them).
  """
  agents: int
  num_envs: int
  warmup_steps: int
  utd: float
  sac: sac.SACConfig
  agent_loop: str
  low: tuple
  high: tuple


def _agent_parallel(fn, mesh):
  """`fn` (every argument and output with the leading agent axis) per device of
  `mesh` (None: as it is)."""
  if mesh is None:
    return fn
  spec = jax.sharding.PartitionSpec("agents")
  return jax.shard_map(fn, mesh=mesh, in_specs=spec, out_specs=spec)


def to_env_action(action, low, high):
  """Policy actions in [−1, 1] → the env's bounds [low, high] (float32; NumPy for
  NumPy input, a `jax.Array` for a `jax.Array`)."""
  xp = jnp if isinstance(action, jax.Array) else np
  low, high = np.asarray(low, np.float32), np.asarray(high, np.float32)
  return (low + (xp.asarray(action) + 1.0) * 0.5 * (high - low)).astype(xp.float32)


def policy_actions(agents: sac.AgentState, obs: jax.Array, keys: jax.Array,
                   random: jax.Array, agent_loop: str = "vmap"):
  """Actions in [−1, 1] (K, N, A) for observations (K, N, H, W, C): the policies'
  samples (agent k's `sac.act` on its envs, the agents batched by `over_agents`
  with `agent_loop`, as the updates are), or uniform where `random` (a traced
  bool: the warm-up)."""
  size = agents.networks.actor.action_size
  uniform = lambda: jax.vmap(lambda o, k: jax.random.uniform(
      k, (o.shape[0], size), minval=-1, maxval=1))(obs, keys)
  policy = lambda: over_agents(sac.act, agent_loop, obs.shape[0])(agents, obs, keys)
  return jax.lax.cond(random, uniform, policy)


def act(learner: Learner, obs: jax.Array, spec: StepSpec, mesh=None):
  """Step 1 (module doc): the agents' actions for the current observations.

  Args:
    learner: the `Learner`.
    obs: uint8 (K·N, H, W, C) observations of the envs.
    spec: the `StepSpec`.
    mesh: a device mesh over the agent axis, or None.

  Returns:
    (learner with its key and step count advanced, actions in [−1, 1] (K, N, A)
    for the buffer, the same in the env's bounds (K·N, A) for the env).
  """
  k, n = spec.agents, spec.num_envs
  key, k_act = jax.random.split(learner.key)
  obs = obs.reshape((k, n) + obs.shape[1:])
  # The warm-up flag travels with the agent axis, so `shard_map` splits it too.
  random = jnp.broadcast_to(learner.step < spec.warmup_steps, (k,))
  fn = lambda agents, obs, keys, random: policy_actions(agents, obs, keys, random[0],
                                                      spec.agent_loop)
  action = _agent_parallel(fn, mesh)(learner.agents, obs, jax.random.split(k_act, k),
                                     random)
  env_action = to_env_action(action.reshape(k * n, -1), spec.low, spec.high)
  return learner.replace(key=key, step=learner.step + n), action, env_action


def _first_update(spec: StepSpec, updates_from):
  """`updates_from`, or the warm-up when None (`owed_updates`)."""
  return spec.warmup_steps if updates_from is None else updates_from


def owed_updates(owed, step, spec: StepSpec, xp=np, updates_from=None):
  """Updates owed once the N transitions of the step at `step` are collected.

  Args:
    owed: updates owed and not yet run (float32).
    step: transitions per agent acted on before this step.
    spec: the `StepSpec` (N, warm-up, utd).
    xp: `numpy` (a host driver's counters) or `jax.numpy` (traced).
    updates_from: transitions per agent before which no update is owed (None:
      `spec.warmup_steps`). A resumed run passes its first step plus the
      warm-up: its buffers, which checkpoints do not hold, refill first.

  Returns:
    (owed including this step's, update pairs that can run now: ⌊owed / 2⌋).
  """
  start = _first_update(spec, updates_from)
  after = step + spec.num_envs
  new = spec.utd * (after - xp.maximum(step, start))
  owed = xp.where(after > start, owed + xp.float32(new), owed)
  return xp.float32(owed), xp.floor(owed / 2).astype(xp.int32)


def plan_updates(owed, ready, step, can_sample_now, spec: StepSpec, xp=np,
                 updates_from=None):
  """Which updates run at the step at `step` (both drivers' bookkeeping).

  Args:
    owed: updates owed and not yet run (float32).
    ready: whether every buffer could be sampled at an earlier step (bool).
    step: transitions per agent acted on before this step.
    can_sample_now: () → whether every buffer can be sampled now (`can_sample`);
      asked only while learning and not yet ready.
    spec: the `StepSpec`.
    xp: `numpy` (host counters: `can_sample_now` returns a Python bool) or
      `jax.numpy` (traced: it returns a traced bool, asked under `lax.cond`).
    updates_from: as for `owed_updates` (a Python int or a traced int32).

  Returns:
    (owed after this step's updates, ready, update pairs to run now: 0 until
    learning starts and the buffers can be sampled; owed updates wait till then).
  """
  owed, pairs = owed_updates(owed, step, spec, xp, updates_from)
  start = _first_update(spec, updates_from)
  learning = step + spec.num_envs > start
  if xp is np:
    ready = ready or (learning and bool(can_sample_now()))
  else:
    ready = jax.lax.cond(ready | ~learning, lambda: ready, can_sample_now)
  run = learning & ready & (pairs > 0)
  return xp.where(run, owed - 2 * pairs, owed), ready, xp.where(run, pairs, 0)


def can_sample(buffers: replay.ReplayBuffer) -> jax.Array:
  """Whether every agent's buffer holds a transition to sample (bool)."""
  return jnp.all(jax.vmap(replay.num_valid)(buffers) > 0)


def update_pair(agent: sac.AgentState, buffer: replay.ReplayBuffer, key: jax.Array,
                config: sac.SACConfig):
  """One agent's `sac.update_pair` on two batches sampled from its buffer.

  Returns:
    (agent, metrics of the pair).
  """
  k_sample, k_update = jax.random.split(key)
  batches = jax.vmap(lambda kk: replay.sample(buffer, kk, config.batch_size))(
      jax.random.split(k_sample, 2))
  return sac.update_pair(agent, batches, k_update, config)


def over_agents(one_agent, agent_loop: str, num_agents: int):
  """`one_agent(agent, buffer, key)` batched over the agent axis: "vmap" batches
  the agents, "map" runs them one after the other (module doc)."""
  if agent_loop == "map" and num_agents > 1:
    return lambda *args: jax.lax.map(lambda a: one_agent(*a), args)
  return jax.vmap(one_agent)


def update_agents(agents, buffers, key, pairs, spec: StepSpec, names: tuple[str, ...],
                  mesh=None, unroll: bool = False):
  """`pairs` × `update_pair` for every agent; (agents, mean metrics (K,)).

  Args:
    agents, buffers: with the leading agent axis K.
    key: a PRNG key (pair i of agent k uses `fold_in(split(key, K)[k], i)`).
    pairs: update pairs per agent: a Python int (a scan of fixed length) or a
      traced int32 (a loop of that many iterations; 0 runs none).
    spec: the `StepSpec`.
    names: the metrics to average (`metric_names`).
    mesh: a device mesh over the agent axis, or None.
    unroll: unroll a fixed-length scan (XLA:CPU runs loop bodies slowly).

  Returns:
    (agents, {name: float32 (K,)} the metrics' means over the pairs; NaN for
    none).
  """
  def one_agent(agent, buffer, k):
    def body(i, carry):
      agent, sums = carry
      agent, m = update_pair(agent, buffer, jax.random.fold_in(k, i), spec.sac)
      return agent, {name: sums[name] + jnp.mean(m[name]).astype(jnp.float32)
                     for name in names}
    # Zeros derived from the agent, so under `shard_map` they vary along the agent
    # axis as the sums do.
    zero = (agent.step * 0).astype(jnp.float32)
    zeros = {name: zero for name in names}
    static = isinstance(pairs, int)
    agent, sums = jax.lax.fori_loop(0, pairs, body, (agent, zeros),
                                    unroll=bool(unroll) if static and pairs else None)
    return agent, {name: v / pairs for name, v in sums.items()}

  fn = over_agents(one_agent, spec.agent_loop, spec.agents)
  return _agent_parallel(fn, mesh)(agents, buffers, jax.random.split(key, spec.agents))


def metric_names(agents: sac.AgentState, buffers: replay.ReplayBuffer,
                 config: sac.SACConfig) -> tuple[str, ...]:
  """The names of `update_pair`'s metrics for these (K-stacked) agents (traced
  abstractly: nothing is computed)."""
  # One agent's shapes, not its slices: slicing agents sharded over several
  # devices would run a gather across them.
  one = lambda tree: jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), tree)
  shapes = jax.eval_shape(lambda a, b, kk: update_pair(a, b, kk, config)[1],
                          one(agents), one(buffers), jax.random.key(0))
  return tuple(sorted(shapes))


def learn(learner: Learner, pairs, spec: StepSpec, mesh=None, unroll: bool = False
          ) -> Learner:
  """Step 2 (module doc): `pairs` update pairs per agent (0: none; the key still
  advances); metrics keep their last values when none run.

  Args:
    learner: the `Learner` (its buffers not yet holding this step's transitions).
    pairs: a Python int or a traced int32 (`update_agents`).
    spec, mesh, unroll: as for `update_agents`.
  """
  key, k_upd = jax.random.split(learner.key)
  agents, means = update_agents(learner.agents, learner.buffers, k_upd, pairs, spec,
                                tuple(sorted(learner.metrics)), mesh, unroll)
  ran = jnp.asarray(pairs) > 0
  metrics = {name: jnp.where(ran, means[name], learner.metrics[name])
             for name in learner.metrics}
  return learner.replace(agents=agents, key=key, metrics=metrics)


def store(learner: Learner, obs: jax.Array, first: jax.Array, action: jax.Array,
          reward: jax.Array, spec: StepSpec, mesh=None) -> Learner:
  """Step 4 (module doc): one transition per env into its agent's buffer.

  Args:
    learner: the `Learner`.
    obs: uint8 (K·N, H, W, 3·stack), the observations acted on (their newest
      frame is stored), agent k's envs first.
    first: bool (K·N,), that observation began an episode.
    action: (K, N, A) the actions taken (in [−1, 1], as `act` returned them).
    reward: float32 (K·N,) the rewards that followed.
    spec, mesh: as for `act`.

  Returns:
    The learner with its buffers holding the transitions.
  """
  k, n = spec.agents, spec.num_envs
  per_agent = lambda x: x.reshape((k, n) + x.shape[1:])
  add = _agent_parallel(jax.vmap(replay.add), mesh)
  buffers = add(learner.buffers, per_agent(obs[..., -3:]), per_agent(first), action,
                per_agent(reward))
  return learner.replace(buffers=buffers)


def update_count(learner: Learner) -> int:
  """The gradient updates all K agents have run (the sum of their update counts,
  `sac.AgentState.step`; an update pair is two); waits for the updates launched."""
  return int(np.sum(jax.device_get(learner.agents.step)))


def init_learner(agents: sac.AgentState, buffers: replay.ReplayBuffer, key: jax.Array,
                 step: int, spec: StepSpec) -> Learner:
  """A `Learner` at training step `step` (metrics NaN: no update yet)."""
  return Learner(agents=agents, buffers=buffers, key=key,
                 step=jnp.asarray(step, jnp.int32),
                 metrics={name: jnp.full((spec.agents,), jnp.nan, jnp.float32)
                          for name in metric_names(agents, buffers, spec.sac)})


# The host driver's jitted steps (the device driver traces the functions above
# inside its scan). `mesh` and `unroll` are static; the learner is donated on
# accelerators (XLA:CPU cannot reuse donated buffers and warns).

_STATIC = ("spec", "mesh")
act_jit = jax.jit(act, static_argnames=_STATIC)
learn_jit = jax.jit(learn, static_argnames=_STATIC + ("pairs", "unroll"),
                    donate_argnums=(0,))
store_jit = jax.jit(store, static_argnames=_STATIC, donate_argnums=(0,))
can_sample_jit = jax.jit(can_sample)
