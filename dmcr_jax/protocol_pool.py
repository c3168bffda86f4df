"""The render pool's protocol pass: a block's envs as pipelined pool envs on the host.

A pool block's K·B envs (agent-major) step as groups (`block_groups`: the
pipelined halves of `pool_groups`, or one group per motion where the block holds
moving conditions), each a `dmcr_jax.make` pool env (made with the group's
`moving` and `intensity`) drawn by one shared `RenderPool`'s workers; `run_pipelined`
steps them round robin, so that one group's physics and policy (`_pool_act`, the
jitted policy call) run while the workers draw another's frames, each group's
frames queued behind the others' so that the workers need not wait for the host
between groups. `pool_envs` opens a pass's envs and workers (once per pass, or once
for every pass inside a `with` block of the `Protocol`), `block_runner` runs its
blocks on them (`Protocol._pool_runner`).
Returns are those of `dmcr_jax.make`'s env stepped by the same policy.

Where the work runs (`pass_workers`): the physics of every group on the host CPU
(`physics_device="cpu"`), never on an accelerator that EGL draws on, where CUDA
kernels and the GL workers' draws take turns and neither overlaps the other; and,
where an accelerator draws the frames, only `POOL_RENDER_WORKERS` render workers
(more draw no more frames there), the cores they leave stepping the groups'
physics in worker processes and launching the policy
(`benchmarks/results/pool_pipeline_h200.md` measures each choice).
"""

from __future__ import annotations

import contextlib
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.protocol_policy import check_actions, env_actions, policy_actions, worst_action


@functools.partial(jax.jit, static_argnames=("policy", "agents"))
def _pool_act(params, obs, index, t, key, low, high, *, policy, agents):
  """The pool's policy call: (env actions float32 (N, A), `worst_action` (K,))."""
  actions = policy_actions(policy, params, obs, index, t, key, agents)
  return env_actions(actions, low, high), worst_action(actions, agents or 1)


POOL_RENDER_WORKERS = 4
"""Render workers of the pool pass where an accelerator draws the frames (EGL on a
GPU): as many frames/s as one worker per core, with the other cores left free."""
POOL_PHYSICS_WORKERS = 4
"""The most physics worker processes (`dmcr_jax.physics_pool`) of one pool env of the
pass."""


def pass_workers(envs: int, cores: int, software_gl: bool,
                 workers: int | None = None, physics_workers: int | None = None
                 ) -> tuple[int, int]:
  """(render workers, physics workers per pool env) of a pool pass.

  Where the frames are drawn in software (no accelerator, or OSMesa) every core
  renders (`render_pool.default_workers`) and the physics steps in this process.
  Where an accelerator draws them, `POOL_RENDER_WORKERS` render and the cores left
  (one kept for this process) step the physics: an equal share per pool env, at
  most `POOL_PHYSICS_WORKERS`; in this process (on its CPU) where the share is none.

  Args:
    envs: the pass's pool envs (each with its own physics workers).
    cores: the host's CPU cores.
    software_gl: whether the frames are drawn on the CPU.
    workers, physics_workers: the caller's choice (None: as above); kept.

  Returns:
    (render workers ≥ 1, physics workers per env ≥ 0).
  """
  from dmcr_jax.visuals.render_pool import default_workers
  if software_gl:
    render = workers or default_workers()
    return render, 0 if physics_workers is None else physics_workers
  render = workers or min(POOL_RENDER_WORKERS, cores)
  if physics_workers is None:
    physics_workers = max(0, min(POOL_PHYSICS_WORKERS, (cores - render - 1) // max(envs, 1)))
  return render, physics_workers


POOL_GROUPS = 2
"""A pool block's envs step as this many groups, pipelined (`run_pipelined`): a
group's physics and policy run while the render workers draw another's frames."""


def pool_groups(agents: int, block: int, groups: int = POOL_GROUPS
                ) -> list[tuple[np.ndarray, np.ndarray]]:
  """How a pool block's K·B envs (agent-major) split into pipelined groups.

  Each of `min(groups, B)` groups holds g = ceil(B / groups) consecutive episodes
  of every agent, agent-major (so `policy_actions` sees K blocks of g); the last
  group is padded, per agent, with copies of its own first episode.

  Args:
    agents: K.
    block: B, envs per agent in the block.
    groups: the most groups.

  Returns:
    Per group (rows int (K·g,) into the block's envs, real bool (K·g,) False on
    padding).
  """
  n = min(groups, block)
  g = -(-block // n)
  out = []
  for h in range(n):
    j = np.arange(h * g, (h + 1) * g)
    real = j < block
    j = np.where(real, j, j[0])
    rows = (np.arange(agents)[:, None] * block + j[None]).reshape(-1)
    out.append((rows, np.tile(real, agents)))
  return out


def run_pipelined(envs, obs, index, act, steps: int) -> list[tuple[np.ndarray, dict]]:
  """Steps pool envs `steps` agent steps each, round robin, so that the workers
  draw one env's frames while another env's policy and physics run: env h's
  frames are collected (`step_wait`), its policy and physics dispatched (`act`),
  and its next frames handed to the workers (`step_submit`, once its physics is
  done) behind the other envs' frames in flight, so the workers go from one env's
  frames straight to the next one's. Each env's episode is what `env.step` in a
  loop gives.

  Args:
    envs: `dmcr_jax.env.PixelVectorEnv`s, just reset, whose render pools are row
      views of one pool (or pools of their own).
    obs: their first observations.
    index: their envs' episode indices (int32 arrays).
    act: `act(env, obs, index, t)` steps `env.step_async` with the policy's actions.
    steps: agent steps.

  Returns:
    Per env its last step's (truncated, info).
  """
  last = [None] * len(envs)
  for h, env in enumerate(envs):
    act(env, obs[h], index[h], 0)
    env.step_submit()
  for t in range(1, steps + 1):
    for h, env in enumerate(envs):
      o, _, _, truncated, info = env.step_wait()
      if t == steps:
        last[h] = (truncated, info)
        continue
      act(env, o, index[h], t)
      env.step_submit()
  return last


def block_groups(agents: int, motion_index: np.ndarray, groups: int = POOL_GROUPS
                 ) -> list[tuple[int, np.ndarray, np.ndarray]]:
  """How a pool block's K·B envs split into groups, one pool env each.

  A pool env draws one motion (`Plan.motions`: static looks, or one moving
  condition's factors and intensity, as `dmcr_jax.make(moving=..., intensity=...)`),
  so a block whose episodes all share a motion steps as `pool_groups`' pipelined
  groups, and a block of several motions as one group per motion (its episodes of
  every agent, agent-major; these groups pipeline with each other).

  Args:
    agents: K.
    motion_index: int (B,) each episode's motion (`Plan.motion_index` of the block).
    groups: the most groups of a one-motion block.

  Returns:
    Per group (motion index, rows int (K·g,) into the block's envs, real bool (K·g,)
    False on padding).
  """
  motion_index = np.asarray(motion_index)
  block = len(motion_index)
  motions = list(dict.fromkeys(motion_index.tolist()))
  if len(motions) == 1:
    return [(motions[0], rows, real) for rows, real in pool_groups(agents, block, groups)]
  out = []
  for m in motions:
    j = np.flatnonzero(motion_index == m)
    rows = (np.arange(agents)[:, None] * block + j[None]).reshape(-1)
    out.append((m, rows, np.ones(rows.size, bool)))
  return out


def _env_keys(layout) -> list[tuple[int, int, int]]:
  """Per group of a block's `block_groups` its pool env: (motion, size, n-th of those)."""
  seen: dict = {}
  keys = []
  for m, rows, _ in layout:
    n = seen[(m, len(rows))] = seen.get((m, len(rows)), -1) + 1
    keys.append((m, len(rows), n))
  return keys


def _pass_env_keys(proto) -> list[tuple[int, int, int]]:
  """The pass's pool envs over all its blocks: (motion, size, n-th of those)."""
  k = proto.agents or 1
  return list(dict.fromkeys(
      e for idx in proto.block_slices()
      for e in _env_keys(block_groups(k, proto.plan.motion_index[idx][:proto.block]))))


def host_workers(envs: int, gl: str | None = None, workers: int | None = None,
                 physics_workers: int | None = None) -> tuple[int, int]:
  """`pass_workers` for `envs` pool envs on this host: its cores, and software GL
  where JAX has no accelerator or `gl` (None: `render_pool.default_gl()`) is OSMesa."""
  import os
  from dmcr_jax.visuals.render_pool import default_gl
  software = jax.default_backend() == "cpu" or (gl or default_gl()) == "osmesa"
  return pass_workers(envs, os.cpu_count() or 1, software, workers, physics_workers)


def workers_for(proto) -> tuple[int, int]:
  """(render workers, physics workers per pool env) of `proto`'s pool pass:
  `host_workers` for its pool envs, with the render options' `gl`, `workers` and
  `physics_workers` where given; no more render workers than the largest group
  has envs."""
  opts = proto.env_kwargs["render"]
  keys = _pass_env_keys(proto)
  render, physics = host_workers(len(keys), opts.get("gl"), opts.get("workers"),
                                 opts.get("physics_workers"))
  return min(render, max(size for _, size, _ in keys)), physics


class PoolEnvs(NamedTuple):
  """A pool pass's open envs (`pool_envs`): per `_pass_env_keys` entry its pool env,
  and the task's action bounds (float32 (A,))."""
  envs: dict
  low: np.ndarray
  high: np.ndarray


@contextlib.contextmanager
def pool_envs(proto):
  """A context giving the `PoolEnvs` of `proto`'s pool pass: one pool env per motion
  and size over the pass's blocks (`_pass_env_keys`), all drawn by one `RenderPool`'s
  workers, which stop, with the envs' physics workers, when the context ends. The
  render workers start while the envs' physics workers start and compile (the
  first frames wait for them).

  Args:
    proto: the `protocol.Protocol` (its task, plan, sizes and render options).
  """
  from dmcr_jax import models
  from dmcr_jax.env import make
  from dmcr_jax.env_checks import check_camera
  from dmcr_jax.visuals.render_pool import RenderPool
  kw, plan = proto.env_kwargs, proto.plan
  keys = _pass_env_keys(proto)
  starts = np.cumsum([0] + [size for _, size, _ in keys])
  opts = dict(kw["render"])
  check_camera(models.load(proto.task).mj_model, opts.get("camera", 0), proto.task)
  workers, physics_workers = workers_for(proto)
  opts.pop("workers", None)
  opts.pop("physics_workers", None)
  (h, w), frame_stack = kw["image_size"], kw["frame_stack"]
  with contextlib.ExitStack() as stack:
    pool = stack.enter_context(RenderPool(proto.task, max_batch=int(starts[-1]),
                                          height=h, width=w, workers=workers,
                                          frame_stack=frame_stack, wait_start=False,
                                          **opts))
    envs = {}
    for j, (m, size, n) in enumerate(keys):
      moving, intensity = plan.motions[m]
      envs[(m, size, n)] = stack.enter_context(make(
          proto.task, renderer="pool", num_envs=size, frame_skip=kw["frame_skip"],
          frame_stack=frame_stack, image_size=(h, w), camera=opts.get("camera", 0),
          seed=proto.config["seed"], copy_obs=False, moving=moving or None,
          intensity=intensity, physics_device="cpu", physics_workers=physics_workers,
          render_pool=pool.rows(int(starts[j]), int(starts[j + 1]))))
    first = next(iter(envs.values()))
    yield PoolEnvs(envs, np.asarray(first.single_action_space.low, np.float32),
                   np.asarray(first.single_action_space.high, np.float32))


def reset_block(proto, penvs: PoolEnvs, inputs: dict):
  """A pool block's start on the open `penvs`: its envs as `block_groups` groups, each
  group's looks set (a moving condition's with `set_visuals`) and its envs reset.

  Args:
    proto: the `protocol.Protocol` whose `pool_envs` `penvs` are.
    penvs: its open `PoolEnvs`.
    inputs: the block's inputs (`Protocol._block_inputs`).

  Returns:
    (envs, groups, obs, index): per group its pool env, its `block_groups` entry,
    its first observations and its episodes' indices (int32 arrays).
  """
  plan = proto.plan
  varies = [plan.varies[i] for i in inputs["vary_index"]]
  groups = block_groups(proto.agents or 1, inputs["motion_index"][:proto.block])
  envs = [penvs.envs[e] for e in _env_keys(groups)]
  index, obs = [], []
  for env, (m, rows, _) in zip(envs, groups):
    if plan.motions[m][0]:    # a moving condition's looks: all of one vary
      env.set_visuals(inputs["seeds"][rows], vary=varies[rows[0]])
    else:
      env.set_looks(inputs["seeds"][rows], [varies[i] for i in rows])
    obs.append(env.reset(seed=inputs["resets"][rows])[0])
    index.append(jnp.asarray(inputs["index"][rows]))
  return envs, groups, obs, index


def block_runner(proto, penvs: PoolEnvs, params, key):
  """`run_block(inputs) -> returns (K·B,)` on the open `penvs`: the block's groups
  started by `reset_block`, then stepped by `run_pipelined` for one episode.

  Args:
    proto: the `protocol.Protocol` whose `pool_envs` `penvs` are.
    penvs: its open `PoolEnvs`.
    params: the policy's params (leading axis K when `proto.agents` is K).
    key: the pass's policy key.
  """
  low, high = penvs.low, penvs.high

  def act(env, obs, index, t):
    actions, worst = _pool_act(params, obs, index, np.int32(t), key, low, high,
                               policy=proto.policy, agents=proto.agents)
    check_actions(np.asarray(worst))
    env.step_async(np.asarray(actions))

  def run_block(inputs):
    block_envs, groups, obs, index = reset_block(proto, penvs, inputs)
    last = run_pipelined(block_envs, obs, index, act, proto.episode_length)
    out = np.empty(len(inputs["index"]), np.float64)
    for (truncated, info), (_, rows, real) in zip(last, groups):
      if not truncated.all():
        raise RuntimeError("episodes did not all end together; the env's episode "
                           "length is off")
      out[rows[real]] = np.asarray(info["episode_return"], np.float64)[real]
    return out
  return run_block
