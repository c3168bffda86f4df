"""The DMCR paper's zero-shot protocol (Sec. 4.2–4.3) for any policy, as one batched program.

A policy is a pure JAX function ``policy(params, obs, key) -> actions``: `obs` a
uint8 batch (B, H, W, 3·frame_stack) of frame stacks (channels last, oldest frame
first), `key` a `jax.random` key, the result float (B, A) in [−1, 1] (mapped
linearly onto the task's action bounds). `params` is any pytree; with
``agents=K`` every leaf carries a leading axis of K agents, evaluated in one pass.

The protocol (`prepare` plans it, its `Protocol` runs it, `evaluate` does both):
- "train": `train_episodes` episodes (paper: 100) at the training look;
- each visual condition: `visual_seeds` held-out looks (paper: 100, drawn from
  `dmcr_jax.TEST_SEEDS` with a NumPy generator seeded by `seed`) × `dynamics_seeds`
  initial states (paper: 3): "none" (nothing varied), one factor at a time (light,
  camera, body, floor, then background, target and reflectance where they apply to
  the domain) and "all" (`conditions_for`);
- E_G = (train − test) / train per condition (paper Sec. 3).
Episode i of every condition starts from the same initial state (per-env reset
seed `reset_seeds(n, seed)[i]`) and its policy draws the same keys, so conditions
differ only in their looks, and agents only in their params. When the training
look is dm_control's (seed 0, or the range levels:1), which "none" also shows,
the train episodes are the first `train_episodes` of "none".

Renderers: "jax" (the default) runs every episode of every condition and agent
as one env batch on the device (split into blocks of at most `max_envs` envs, all
of one shape, so one compilation serves every block): per block one jitted call
makes the looks from the per-env seeds and factor masks, resets the physics from
the per-env seeds and `lax.scan`s the episode with the policy inside, with no host
round trip per step (each scan step draws the frames, asks the policy and steps
the physics; the program holds one render and one physics step, and no env resets
inside a block). "pool" renders MuJoCo's own pixels in the CPU render pool
(`dmcr_jax.make`), every condition's envs in one block (`PixelVectorEnv.set_looks`),
the same jitted policy called from the host loop; a block steps as two pipelined
groups of envs (`pool_groups`), a group's physics and policy running while the
workers draw the other's frames. Returns are those of `dmcr_jax.make`'s env stepped by
the same policy (`tests/test_protocol.py`). The policy is vmapped over envs (and
the K agents run one after another, each on its own envs): an env's action
depends on its own observation and key alone, so the returns do not depend on
`max_envs` or on the number of agents (up to the float rounding of a
batched matrix product, which on some backends varies with the batch size).
The plan (conditions, looks, seeds, every agent's episodes) is
`dmcr_jax.protocol_plan`'s; the reports are `dmcr_jax.protocol_report`'s.

Actions outside [−1, 1] or NaN are not clipped: the pass raises a ValueError
naming the agent. An interrupted pass goes on where it stopped when called again
with the same `progress_file` (finished blocks are kept there).

    import dmcr_jax.protocol as P
    result = P.evaluate("cartpole-balance", policy, params, visual_seeds=4, dynamics_seeds=1,
                        train_episodes=4, image_size=16, action_repeat=100)
    print(result.markdown()); result.write("eval_out")
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import math
import os
import sys
import time
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax._progress import progress_bar
from dmcr_jax.checks import positive_int
from dmcr_jax.protocol_plan import (FACTOR_CONDITIONS, PROGRESS_FILE, Plan, Segment,
                                    check_disjoint, conditions_for, held_out_seeds,
                                    is_default_look, load_progress, look_label, make_plan,
                                    reset_seeds, save_progress, train_look_seeds)
from dmcr_jax.protocol_report import generalization_error
from dmcr_jax.visuals.levels import SeedRange

__all__ = ["FACTOR_CONDITIONS", "PROGRESS_FILE", "Plan", "Policy", "Protocol", "Results",
           "Segment", "check_actions", "check_disjoint", "check_policy", "conditions_for",
           "evaluate", "generalization_error", "held_out_seeds", "is_default_look",
           "load_progress", "look_label", "make_plan", "policy_actions", "prepare",
           "reset_seeds", "save_progress", "train_look_seeds"]

Policy = Callable[[Any, jax.Array, jax.Array], jax.Array]
"""``policy(params, obs, key) -> actions``: uint8 (B, H, W, 3·stack) → float (B, A)."""

_POOL_OPTIONS = ("quality", "workers", "egl_devices", "gl")
_JAX_OPTIONS = ("shadows", "reflection", "render_chunk", "render_kernel")


def params_digest(params) -> str:
  """SHA-1 of a pytree's structure and leaf bytes (what a progress file is keyed by)."""
  h = hashlib.sha1(str(jax.tree.structure(params)).encode())
  for leaf in jax.tree.leaves(jax.device_get(params)):
    a = np.asarray(leaf)
    h.update(str((a.shape, a.dtype)).encode())
    h.update(np.ascontiguousarray(a).tobytes())
  return h.hexdigest()


# --------------------------------------------------------------------------- #
# The policy inside the program.
# --------------------------------------------------------------------------- #


POLICY_STREAM = 0x9E3779B9
"""`fold_in` constant of the policy keys' stream (apart from the dynamics keys)."""


def policy_actions(policy: Policy, params, obs: jax.Array, index: jax.Array,
                   t: jax.Array, key: jax.Array, agents: int | None) -> jax.Array:
  """Every env's action: the policy vmapped over envs, one agent after another.

  Env e's action is ``policy(params_k, obs[e:e+1], fold_in(fold_in(key, index[e]),
  t))[0]``, so it depends on its own observation and key alone. The vmap over
  envs batches the policy's layers over them (a batch-1 convolution becomes one
  of the agent's B envs); the K agents run in turn (`lax.map`), so each agent's
  layers keep their own unbatched weights (a vmap over agents would make grouped
  convolutions of K groups).

  Args:
    policy: the `Policy`.
    params: its params (leading axis K when `agents` is K).
    obs: uint8 (K·B, H, W, C) observations, agent k's in rows [k·B, (k+1)·B).
    index: int32 (K·B,) each env's episode index within its segment.
    t: int32 scalar, the agent step.
    key: the pass's policy key.
    agents: K, or None (params without an agent axis).

  Returns:
    float (K·B, A) actions.
  """
  keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.fold_in(key, i), t))(index)
  one = lambda p, o, k: policy(p, o[None], k)[0]
  per_env = jax.vmap(one, in_axes=(None, 0, 0))
  if agents is None:
    return per_env(params, obs, keys)
  blocks = lambda x: x.reshape((agents, x.shape[0] // agents) + x.shape[1:])
  actions = jax.lax.map(lambda a: per_env(*a), (params, blocks(obs), blocks(keys)))
  return actions.reshape((obs.shape[0],) + actions.shape[2:])


def worst_action(actions: jax.Array, agents: int) -> jax.Array:
  """float32 (K,) max |action| of each agent's envs; NaN where any action is NaN."""
  a = jnp.abs(actions.astype(jnp.float32)).reshape(agents, -1)
  return jnp.where(jnp.isnan(a).any(axis=1), jnp.nan, jnp.max(a, axis=1))


def env_actions(actions: jax.Array, low: np.ndarray, high: np.ndarray) -> jax.Array:
  """Policy actions in [−1, 1] → the task's bounds (float32), as `dmcr_jax.train.step`'s
  `to_env_action`."""
  low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
  return (low + (actions.astype(jnp.float32) + 1.0) * 0.5 * (high - low)).astype(jnp.float32)


def block_looks(maker, masks: jax.Array, seeds: jax.Array):
  """Each env's `DeviceLook`: its visual seed under its own factor mask.

  Args:
    maker: the domain's `jax_render_scene.LookMaker` (its own mask is replaced).
    masks: bool (N, 7) factor masks (`params.factor_mask`).
    seeds: int32 (N,) visual seeds.

  Returns:
    The `DeviceLook` of the N envs (leading axis N).
  """
  looks = jax.vmap(lambda m, s: maker.replace(mask=m)(s[None]))(masks, seeds)
  return jax.tree.map(lambda x: x[:, 0], looks)


def episode_step(task, frame_skip: int, physics, actions: jax.Array):
  """One agent step of N envs inside an episode: `physics_env.step` where no env
  resets (no env's previous step ended its episode), without its reset branch.

  Args:
    task: the `Task`.
    frame_skip: control steps per agent step.
    physics: the `physics_env.EnvState`, no env with `needs_reset` set.
    actions: float (N, A) in the task's bounds.

  Returns:
    The next `EnvState` (its `needs_reset` marks the envs whose episode ended).
  """
  from dmcr_jax import physics_env
  stepped, reward = jax.vmap(lambda s, a: physics_env.skip_step(task, s, a, frame_skip))(
      physics.task, actions)
  return physics.replace(task=stepped, episode_step=physics.episode_step + 1,
                         episode_return=physics.episode_return + reward,
                         needs_reset=stepped.done)


def render_chunk(num_envs: int) -> int | None:
  """Envs per render chunk for a block of `num_envs` envs: the fewest chunks of
  at most `jax_env.RENDER_CHUNK` envs, all of one size (None: one chunk)."""
  from dmcr_jax import jax_env
  if num_envs <= jax_env.RENDER_CHUNK:
    return None
  return -(-num_envs // -(-num_envs // jax_env.RENDER_CHUNK))


def render_padding(penv) -> int:
  """Envs the block's frames are padded with (copies of env 0) to a whole number
  of `penv.render_chunk`-env chunks, so the render is one vmapped chunk program
  (`lax.map` renders a remainder with a second one); 0 for the fused kernel."""
  chunk = penv.render_chunk
  if penv.render_kernel or not chunk or chunk >= penv.num_envs:
    return 0
  return -penv.num_envs % chunk


def _pad(tree, extra: int):
  """Every leaf with `extra` copies of its row 0 appended."""
  if not extra:
    return tree
  return jax.tree.map(lambda x: jnp.concatenate(
      [x, jnp.broadcast_to(x[:1], (extra,) + x.shape[1:])]), tree)


def _ray_block(penv, params, seeds, masks, resets, index, key, *, policy, agents, steps):
  """One block of the ray caster's pass: looks, reset, `steps` agent steps.

  Each scan step renders the envs' frames, stacks them, asks the policy and
  steps the physics (`episode_step`: `steps` is the episode length, so no env
  resets inside the block); a frame is rendered once, at one place in the
  program. The stacks and returns are those of `jax_env.PixelEnv` stepped from
  `start` (the first stack is the first frame repeated).

  Args: the block's envs' int32 visual seeds (N,), bool factor masks (N, 7),
  uint32 reset seeds (N,), int32 episode indices (N,); `penv` a `PixelEnv` of N
  envs without looks, its frames padded by `render_padding`; `key` the policy key.

  Returns:
    (episode returns float32 (N,), `worst_action` float32 (K,) over the episode).
  """
  from dmcr_jax import physics_env
  n, k = penv.num_envs, agents or 1
  extra = render_padding(penv)
  looks = _pad(block_looks(penv.maker, masks, seeds), extra)
  physics = physics_env.init(penv.task, seeds, jax.vmap(jax.random.key)(resets), n)
  low, high = penv.task.action_low, penv.task.action_high

  def body(carry, t):
    physics, obs, worst = carry
    frame = penv.draw(_pad(penv.render_inputs(physics), extra), looks)[:n]
    obs = jnp.where(t == 0, jnp.tile(frame, (1, 1, 1, penv.frame_stack)),
                    jnp.concatenate([obs[..., 3:], frame], axis=-1))
    actions = policy_actions(policy, params, obs, index, t, key, agents)
    worst = jnp.maximum(worst, worst_action(actions, k))  # NaN stays NaN
    physics = episode_step(penv.task, penv.frame_skip, physics,
                           env_actions(actions, low, high))
    return (physics, obs, worst), None

  obs = jnp.zeros((n, penv.height, penv.width, 3 * penv.frame_stack), jnp.uint8)
  init = (physics, obs, jnp.zeros((k,), jnp.float32))
  (physics, _, worst), _ = jax.lax.scan(body, init, jnp.arange(steps, dtype=jnp.int32))
  return physics.episode_return, worst


@functools.cache
def _ray_block_jit():
  from dmcr_jax.models.base import physics_jit
  return physics_jit(_ray_block, static_argnames=("policy", "agents", "steps"))


@functools.partial(jax.jit, static_argnames=("policy", "agents"))
def _pool_act(params, obs, index, t, key, low, high, *, policy, agents):
  """The pool's policy call: (env actions float32 (N, A), `worst_action` (K,))."""
  actions = policy_actions(policy, params, obs, index, t, key, agents)
  return env_actions(actions, low, high), worst_action(actions, agents or 1)


# --------------------------------------------------------------------------- #
# Results.
# --------------------------------------------------------------------------- #


@dataclasses.dataclass(frozen=True)
class Results:
  """A pass's returns, per agent (K = 1 without an agent axis).

  Attributes:
    task: the task.
    conditions: the conditions, in order.
    train: float64 (K, T) returns at the training look.
    returns: {condition: float64 (K, V·D) returns}, episode i of look i // D.
    test_visual_seeds: int64 (V,) held-out seeds.
    train_looks: per agent its training look's label (`look_label`).
    config: the protocol's options (JSON-safe).
    labels: per agent its name in tables.
    device: the device kind the pass ran on.
    wall_s: seconds of the pass (of every attempt, when resumed).
    compile_s: seconds of its first block (compilation included); None if resumed.
    agent_steps: agent steps run (every env's, every block's, padding included).
  """
  task: str
  conditions: tuple[str, ...]
  train: np.ndarray
  returns: dict
  test_visual_seeds: np.ndarray
  train_looks: tuple[str, ...]
  config: dict
  labels: tuple[str, ...]
  device: str
  wall_s: float
  compile_s: float | None
  agent_steps: int

  @property
  def train_mean(self) -> np.ndarray:
    """(K,) mean train return per agent."""
    return self.train.mean(axis=1)

  def mean(self, condition: str) -> np.ndarray:
    """(K,) mean return per agent under `condition`."""
    return self.returns[condition].mean(axis=1)

  def e_g(self, condition: str) -> np.ndarray:
    """(K,) E_G = (train − test) / train per agent (NaN where train is 0)."""
    return np.array([generalization_error(float(tr), float(te))
                     for tr, te in zip(self.train_mean, self.mean(condition))])

  def summary(self) -> dict:
    """The results as `dmcr_jax.protocol_report`'s summary (E_G NaN where undefined):
    per agent ("agents") its train return and each condition's mean, std,
    episodes and E_G; "mean" over agents; the protocol's config and seeds."""
    from dmcr_jax import protocol_report
    agents = []
    for k, label in enumerate(self.labels):
      train = self.train[k]
      row = dict(agent=k, label=label, train_look=self.train_looks[k],
                 train=dict(mean=float(train.mean()), std=float(train.std()),
                            episodes=train.tolist()), conditions={})
      for c in self.conditions:
        r = self.returns[c][k]
        row["conditions"][c] = dict(mean=float(r.mean()), std=float(r.std()),
                                    episodes=r.tolist(),
                                    e_g=generalization_error(row["train"]["mean"],
                                                             float(r.mean())))
      agents.append(row)
    out = dict(task=self.task, conditions=list(self.conditions), config=dict(self.config),
               test_visual_seeds=self.test_visual_seeds.tolist(),
               train_look=", ".join(dict.fromkeys(self.train_looks)), device=self.device,
               wall_s=self.wall_s, compile_s=self.compile_s, agent_steps=self.agent_steps,
               agents=agents)
    out["mean"] = protocol_report.mean_row(agents, self.conditions)
    out["augs"] = protocol_report.aug_groups(out)
    return out

  def to_json(self) -> str:
    """`summary()` as JSON text (an undefined E_G is null)."""
    from dmcr_jax import protocol_report
    return json.dumps(protocol_report.json_safe(self.summary()), indent=1, allow_nan=False)

  def markdown(self) -> str:
    """The table of returns per condition and E_G (`protocol_report.markdown`)."""
    from dmcr_jax import protocol_report
    return protocol_report.markdown(self.summary())

  def plot(self, path: str) -> None:
    """The bar chart of returns and E_G per condition (`protocol_report.plot`), a PNG."""
    from dmcr_jax import protocol_report
    protocol_report.plot(self.summary(), path)

  def write(self, out_dir: str) -> dict:
    """Writes eval.json, eval.md and eval.png into `out_dir` (made); returns the summary."""
    from dmcr_jax import protocol_report
    summary = self.summary()
    protocol_report.write(summary, out_dir)
    return summary


# --------------------------------------------------------------------------- #
# The protocol.
# --------------------------------------------------------------------------- #


def _agent_count(params, agents) -> int | None:
  """`agents` checked against the params' leading axes (None: no agent axis)."""
  if agents is None:
    return None
  k = positive_int("agents", agents)
  leaves = jax.tree.leaves(params)
  if not leaves:
    raise ValueError("params has no arrays: with agents=K every leaf carries a leading "
                     "axis of K agents")
  bad = sorted({tuple(np.shape(x)) for x in leaves if np.ndim(x) == 0 or np.shape(x)[0] != k})
  if bad:
    raise ValueError(f"agents={k}: every params leaf must have a leading axis of {k} "
                     f"agents; got leaves of shape {', '.join(map(str, bad[:3]))}")
  return k


_TRACER_ERRORS = tuple(getattr(jax.errors, name) for name in (
    "ConcretizationTypeError", "TracerArrayConversionError", "TracerBoolConversionError",
    "TracerIntegerConversionError", "UnexpectedTracerError") if hasattr(jax.errors, name))


def check_policy(policy: Policy, params, obs_shape: tuple[int, ...], action_size: int,
                 agents: int | None) -> None:
  """Traces `policy` abstractly (`jax.eval_shape`, nothing compiled or run) on one
  agent's params, a uint8 batch of 2 observations and a key; ValueError unless it
  is a pure JAX function returning float (2, action_size).

  Args:
    policy: the `Policy`.
    params: its params (leading axis K when `agents` is K).
    obs_shape: (H, W, 3·frame_stack).
    action_size: A.
    agents: K or None.
  """
  if not callable(policy):
    raise ValueError(f"policy must be a function policy(params, obs, key) -> actions, got "
                     f"{type(policy).__name__}")
  spec = lambda x: jax.ShapeDtypeStruct(np.shape(x)[1 if agents else 0:], jnp.result_type(x))
  one = jax.tree.map(spec, params)
  obs = jax.ShapeDtypeStruct((2,) + tuple(obs_shape), jnp.uint8)
  key = jax.eval_shape(lambda: jax.random.key(0))
  try:
    out = jax.eval_shape(policy, one, obs, key)
  except _TRACER_ERRORS as e:
    first = str(e).strip().splitlines()[0]
    raise ValueError("policy must be a pure JAX function of (params, obs, key): tracing "
                     f"it on abstract arrays failed ({type(e).__name__}: {first})") from e
  except Exception as e:  # noqa: BLE001 - any failure of the user's code, named
    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
    raise ValueError(f"policy(params, obs, key) failed when traced on obs uint8 "
                     f"{obs.shape} and one agent's params ({type(e).__name__}: {first})"
                     ) from e
  want = (2, action_size)
  if not isinstance(out, jax.ShapeDtypeStruct) or tuple(out.shape) != want:
    got = out.shape if isinstance(out, jax.ShapeDtypeStruct) else type(out).__name__
    raise ValueError(f"policy must return actions of shape (batch, action_size) = {want} "
                     f"for a batch of 2 observations {tuple(obs.shape)}, got {got}")
  if not jnp.issubdtype(out.dtype, jnp.floating):
    raise ValueError(f"policy must return float actions in [-1, 1], got dtype {out.dtype}")


@dataclasses.dataclass(frozen=True)
class Protocol:
  """A planned protocol (build with `prepare`): call it with params to run a pass.

  The jitted block program is built once per (policy, sizes); calling again with
  other params of the same shapes compiles nothing (a training loop can evaluate
  its agents as it goes).

  Attributes:
    task: the task name.
    policy: the `Policy`.
    agents: K, or None (params without an agent axis).
    conditions: the conditions, in order.
    test_seeds: int64 (V,) held-out visual seeds.
    plan: every agent's episodes (`Plan`).
    train_looks: per agent its training look.
    renderer: "jax" or "pool".
    block: envs per agent in a block (the pass runs ceil(E / block) blocks).
    episode_length: agent steps per episode.
    config: the options (JSON-safe).
    env_kwargs: `dmcr_jax.make`'s keywords (sizes, frame skip, render options).
  """
  task: str
  policy: Policy
  agents: int | None
  conditions: tuple[str, ...]
  test_seeds: np.ndarray
  plan: Plan
  train_looks: tuple
  renderer: str
  block: int
  episode_length: int
  config: dict
  env_kwargs: dict

  @property
  def num_blocks(self) -> int:
    """Blocks in a pass."""
    return math.ceil(self.plan.episodes / self.block)

  @property
  def block_envs(self) -> int:
    """Envs of one block: K · block."""
    return (self.agents or 1) * self.block

  def block_slices(self) -> list[np.ndarray]:
    """Per block, the episode indices of its envs (the last block padded with
    episode 0, whose results are dropped)."""
    e = self.plan.episodes
    out = []
    for b in range(self.num_blocks):
      idx = np.arange(b * self.block, (b + 1) * self.block)
      out.append(np.where(idx < e, idx, 0))
    return out

  def _block_inputs(self, idx: np.ndarray) -> dict:
    """Host arrays of a block's K · B envs (agent-major)."""
    p, k = self.plan, self.agents or 1
    flat = lambda x: x.reshape((k * x.shape[1],) + x.shape[2:])
    return dict(seeds=flat(p.visual_seed[:, idx]), masks=flat(p.mask[:, idx]),
                vary_index=flat(p.vary_index[:, idx]),
                resets=np.tile(p.reset_seed[idx], k), index=np.tile(p.index[idx], k))

  def __call__(self, params, *, labels: Sequence[str] | None = None,
               progress: bool | None = None, progress_file: str | None = None,
               progress_key: dict | None = None) -> Results:
    """Runs the pass for `params`.

    Args:
      params: the policy's params (leading axis K when `agents` is K).
      labels: per agent its name in tables (default "agent k").
      progress: True: a progress bar on a terminal (a line per block when stderr
        is not one); False: a line per block on stderr; None: silent.
      progress_file: keep finished blocks there (npz) and resume from it: a pass
        interrupted and called again with the same protocol, params and
        `progress_key` runs only the blocks still missing (the file is removed
        once the pass ends).
      progress_key: more of what the file must match (e.g. a run folder).

    Returns:
      The `Results`.

    Raises:
      ValueError: params without the agent axis, a policy that cannot be traced or
        returns the wrong shape (before anything compiles), or actions outside
        [−1, 1] or NaN (after the block that produced them).
    """
    k = _agent_count(params, self.agents)
    h, w = self.env_kwargs["image_size"]
    check_policy(self.policy, params, (h, w, 3 * self.env_kwargs["frame_stack"]),
                 self._action_size(), k)
    kk = k or 1
    labels = tuple(labels) if labels is not None else tuple(f"agent {i}" for i in range(kk))
    if len(labels) != kk:
      raise ValueError(f"labels must name the {kk} agents, got {len(labels)}")
    key = jax.random.fold_in(jax.random.key(self.config["seed"]), POLICY_STREAM)
    pkey, done, earlier = None, {}, 0.0
    if progress_file:
      pkey = dict(progress_key or {}, protocol=self.config, block=self.block,
                  params=params_digest(params))
      done, earlier = load_progress(progress_file, pkey)
    if done and progress is not None:
      print(f"evaluate: resuming from {progress_file}: {len(done)} of {self.num_blocks} "
            "blocks already done", file=sys.stderr, flush=True)
    bar = progress_bar(progress, total=self.num_blocks, initial=len(done), desc="evaluate",
                       unit="block")
    t_start = time.perf_counter()
    compile_s = None
    runner = self._ray_runner if self.renderer == "jax" else self._pool_runner
    try:
      with runner(params, key) as run_block:
        for b, idx in enumerate(self.block_slices()):
          name = f"block{b}"
          if name in done:
            continue
          t0 = time.perf_counter()
          returns = run_block(self._block_inputs(idx)).reshape(kk, self.block)
          wall = time.perf_counter() - t0
          if compile_s is None and not done:
            compile_s = wall
          done[name] = (returns.astype(np.float64), wall)
          if progress_file:
            save_progress(progress_file, pkey, done,
                          earlier + time.perf_counter() - t_start)
          if bar is not None:
            bar.update(1)
          elif progress is not None:
            print(f"evaluate: block {b + 1}/{self.num_blocks} done, {wall:.0f} s",
                  file=sys.stderr, flush=True)
    finally:
      if bar is not None:
        bar.close()
    wall_s = earlier + time.perf_counter() - t_start
    all_returns = np.concatenate([done[f"block{b}"][0] for b in range(self.num_blocks)],
                                 axis=1)[:, :self.plan.episodes]
    seg = {s.name: all_returns[:, s.start:s.start + s.size] for s in self.plan.segments}
    t = self.config["train_episodes"]
    train = np.stack([seg["none"][a, :t] if self.plan.shares[a] else seg["train"][a]
                      for a in range(kk)])
    if progress_file and os.path.exists(progress_file):
      os.remove(progress_file)
    return Results(task=self.task, conditions=self.conditions, train=train,
                   returns={c: seg[c] for c in self.conditions},
                   test_visual_seeds=self.test_seeds.copy(),
                   train_looks=tuple(look_label(x) for x in self.train_looks),
                   config=dict(self.config), labels=labels,
                   device=jax.devices()[0].device_kind, wall_s=wall_s, compile_s=compile_s,
                   agent_steps=self.num_blocks * self.block_envs * self.episode_length)

  def _action_size(self) -> int:
    from dmcr_jax import models
    return models.load(self.task).action_size

  # Renderers ------------------------------------------------------------------

  def pixel_env(self):
    """The ray caster's `jax_env.PixelEnv` of one block's envs (looks made per block)."""
    return _pixel_env(self.task, self.block_envs, self.env_kwargs["frame_skip"],
                      self.env_kwargs["frame_stack"], *self.env_kwargs["image_size"],
                      tuple(sorted(self.env_kwargs["render"].items())))

  @contextlib.contextmanager
  def _ray_runner(self, params, key):
    """A context giving `run_block(inputs) -> returns (K·B,)` on the device."""
    penv, fn = self.pixel_env(), _ray_block_jit()

    def run_block(inputs):
      returns, worst = fn(penv, params, jnp.asarray(inputs["seeds"]),
                          jnp.asarray(inputs["masks"]), jnp.asarray(inputs["resets"]),
                          jnp.asarray(inputs["index"]), key, policy=self.policy,
                          agents=self.agents, steps=self.episode_length)
      check_actions(np.asarray(worst))
      return np.asarray(returns, np.float64)
    yield run_block

  @contextlib.contextmanager
  def _pool_runner(self, params, key):
    """A context giving `run_block(inputs) -> returns (K·B,)` with the render pool:
    the block's envs as `pool_groups` pipelined groups, one pool env each, all
    drawn by one `RenderPool`'s workers (which stop when the context ends)."""
    from dmcr_jax import models
    from dmcr_jax.env import check_camera, make
    from dmcr_jax.visuals.render_pool import RenderPool, default_workers
    kw, k = self.env_kwargs, self.agents or 1
    groups = pool_groups(k, self.block)
    size = len(groups[0][0])
    opts = dict(kw["render"])
    check_camera(models.load(self.task).mj_model, opts.get("camera", 0), self.task)
    workers = min(size, opts.pop("workers", None) or default_workers())
    (h, w), frame_stack = kw["image_size"], kw["frame_stack"]
    with contextlib.ExitStack() as stack:
      pool = stack.enter_context(RenderPool(self.task, max_batch=size * len(groups),
                                            height=h, width=w, workers=workers,
                                            frame_stack=frame_stack, **opts))
      envs = [stack.enter_context(make(
          self.task, renderer="pool", num_envs=size, frame_skip=kw["frame_skip"],
          frame_stack=frame_stack, image_size=(h, w), camera=opts.get("camera", 0),
          seed=self.config["seed"], copy_obs=False,
          render_pool=pool.rows(g * size, (g + 1) * size)))
          for g in range(len(groups))]
      low = np.asarray(envs[0].single_action_space.low, np.float32)
      high = np.asarray(envs[0].single_action_space.high, np.float32)

      def act(env, obs, index, t):
        actions, worst = _pool_act(params, obs, index, np.int32(t), key, low, high,
                                   policy=self.policy, agents=self.agents)
        check_actions(np.asarray(worst))
        env.step_async(np.asarray(actions))

      def run_block(inputs):
        varies = [self.plan.varies[i] for i in inputs["vary_index"]]
        index, obs = [], []
        for env, (rows, _) in zip(envs, groups):
          env.set_looks(inputs["seeds"][rows], [varies[i] for i in rows])
          obs.append(env.reset(seed=inputs["resets"][rows])[0])
          index.append(jnp.asarray(inputs["index"][rows]))
        last = run_pipelined(envs, obs, index, act, self.episode_length)
        out = np.empty(len(inputs["index"]), np.float64)
        for (truncated, info), (rows, real) in zip(last, groups):
          if not truncated.all():
            raise RuntimeError("episodes did not all end together; the env's episode "
                               "length is off")
          out[rows[real]] = np.asarray(info["episode_return"], np.float64)[real]
        return out
      yield run_block


def check_actions(worst: np.ndarray) -> None:
  """ValueError naming the agents whose actions were NaN or outside [−1, 1]
  (`worst`: each agent's `worst_action`)."""
  nan = np.flatnonzero(np.isnan(worst))
  out = np.flatnonzero(worst > 1.0)
  if len(nan) or len(out):
    parts = []
    if len(nan):
      parts.append(f"NaN actions (agents {nan.tolist()})")
    if len(out):
      parts.append(f"actions outside [-1, 1] (agents {out.tolist()}, largest |action| "
                   f"{float(np.nanmax(worst[out])):.4g})")
    raise ValueError(f"policy returned {' and '.join(parts)}: a policy must return "
                     "finite actions in [-1, 1] (they are not clipped); squash them, "
                     "e.g. with jnp.tanh")


@functools.lru_cache(maxsize=8)
def _pixel_env(task: str, num_envs: int, frame_skip: int, frame_stack: int, height: int,
               width: int, render: tuple):
  """A `jax_env.PixelEnv` of `num_envs` envs without looks (the block program makes
  them), built once per sizes."""
  from dmcr_jax import jax_env, models
  from dmcr_jax.visuals import jax_render as JR
  from dmcr_jax.visuals import jax_render_scene as JS
  opts = dict(render)
  t = models.load(task)
  rm, scene = jax_env.scene_of(t.spec.domain, opts.get("camera", 0))
  chunk = opts.get("render_chunk")
  if chunk is None:
    chunk = render_chunk(num_envs)
  return jax_env.PixelEnv(
      scene=scene, maker=JS.look_maker(scene, rm, "all"), looks=None, fixed_seeds=None,
      seed_bounds=None, task=t, num_envs=int(num_envs), frame_skip=int(frame_skip),
      frame_stack=int(frame_stack), height=int(height), width=int(width),
      shadows=bool(opts.get("shadows", True)), reflection=bool(opts.get("reflection", True)),
      render_chunk=chunk, render_kernel=JR.use_kernel(opts.get("render_kernel", False)))


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
  """Steps pool envs `steps` agent steps each, round robin, so that while the
  workers draw one env's frames another env's policy and physics run: env h's
  frames are collected (`step_wait`), env h+1's submitted (`step_submit`), then
  h's policy and physics dispatched (`act`). Each env's episode is what
  `env.step` in a loop gives.

  Args:
    envs: `dmcr_jax.env.PixelVectorEnv`s, just reset.
    obs: their first observations.
    index: their envs' episode indices (int32 arrays).
    act: `act(env, obs, index, t)` steps `env.step_async` with the policy's actions.
    steps: agent steps.

  Returns:
    Per env its last step's (truncated, info).
  """
  g, last = len(envs), [None] * len(envs)
  for h in range(g):
    act(envs[h], obs[h], index[h], 0)
  envs[0].step_submit()
  for t in range(steps):
    final = t + 1 == steps
    for h in range(g):
      o, _, _, truncated, info = envs[h].step_wait()
      nxt = (h + 1) % g
      if nxt != h and not (final and nxt == 0):
        envs[nxt].step_submit()
      if final:
        last[h] = (truncated, info)
        continue
      act(envs[h], o, index[h], t + 1)
      if nxt == h:
        envs[h].step_submit()
  return last


def _check_train_look(look, k: int) -> tuple:
  """Per agent its training look: one int seed or `SeedRange` for all, or K of them."""
  looks = list(look) if isinstance(look, (list, tuple)) else [look] * k
  if len(looks) != k:
    raise ValueError(f"train_look must be one look or one per agent ({k}), got {len(looks)}")
  for x in looks:
    if not isinstance(x, SeedRange) and (isinstance(x, bool)
                                         or not isinstance(x, (int, np.integer)) or x < 0):
      raise ValueError(f"train_look must be a visual seed (int ≥ 0) or a SeedRange, got {x!r}")
  return tuple(x if isinstance(x, SeedRange) else int(x) for x in looks)


def prepare(task: str, policy: Policy, *, agents: int | None = None, renderer: str = "jax",
            visual_seeds: int = 100, dynamics_seeds: int = 3, train_episodes: int = 100,
            conditions: Sequence[str] | None = None, train_look=0, train_vary="all",
            seed: int = 0, image_size: int | tuple[int, int] = 84, frame_stack: int = 3,
            action_repeat: int | None = None, max_envs: int | None = None,
            **render_options) -> Protocol:
  """Plans the protocol (host work only: seeds and episode lists; nothing compiles).

  Args:
    task: one of `dmcr_jax.ALL_TASKS`.
    policy: ``policy(params, obs, key) -> actions`` (module docstring).
    agents: K when params carry a leading axis of K agents; None: one agent.
    renderer: "jax" (the ray caster, one device program) or "pool" (MuJoCo's pixels).
    visual_seeds: held-out looks per condition (paper: 100).
    dynamics_seeds: initial states per look (paper: 3).
    train_episodes: episodes at the training look (paper: 100), at most
      visual_seeds · dynamics_seeds.
    conditions: the conditions to run (default: every one that applies, `conditions_for`).
    train_look: the training look: a visual seed (0: dm_control's), a `SeedRange`
      (few-shot), or one per agent.
    train_vary: the factors the training looks vary ("all").
    seed: seeds the held-out looks' draw, the initial states and the policy keys.
    image_size, frame_stack: the observations' size (H = W, or (H, W)) and stack.
    action_repeat: control steps per agent step (default: the paper's for the task).
    max_envs: at most this many envs per block (default: every episode in one block).
    **render_options: "jax": shadows, reflection, render_chunk, render_kernel;
      "pool": quality, workers, egl_devices, gl (`dmcr_jax.make`).

  Returns:
    The `Protocol`; call it with params.

  Raises:
    ValueError: any bad option (the message names the valid ones).
  """
  from dmcr_jax import models
  from dmcr_jax.env import check_renderer_name, default_frame_skip
  check_renderer_name(renderer)
  if task not in models.ALL_TASKS:
    raise ValueError(f"Unknown task {task!r}; valid: {', '.join(models.ALL_TASKS)}")
  if not callable(policy):
    raise ValueError(f"policy must be a function policy(params, obs, key) -> actions, got "
                     f"{type(policy).__name__}")
  for name, v in (("visual_seeds", visual_seeds), ("dynamics_seeds", dynamics_seeds),
                  ("train_episodes", train_episodes), ("frame_stack", frame_stack)):
    positive_int(name, v)
  if train_episodes > visual_seeds * dynamics_seeds:
    raise ValueError(f"train_episodes ({train_episodes}) must be at most "
                     f"visual_seeds · dynamics_seeds = {visual_seeds * dynamics_seeds}")
  if agents is not None:
    positive_int("agents", agents)
  other = _JAX_OPTIONS if renderer == "pool" else _POOL_OPTIONS
  mine = _POOL_OPTIONS if renderer == "pool" else _JAX_OPTIONS
  wrong = sorted(set(render_options) & set(other))
  if wrong:
    raise ValueError(f"{', '.join(wrong)} apply only to renderer="
                     f"{'jax' if renderer == 'pool' else 'pool'!r}, not renderer={renderer!r}")
  unknown = sorted(set(render_options) - set(mine) - {"camera"})
  if unknown:
    raise ValueError(f"unknown option {', '.join(unknown)}; renderer={renderer!r} takes "
                     f"{', '.join(mine + ('camera',))}")
  valid = conditions_for(task)
  conditions = valid if conditions is None else tuple(conditions)
  bad = [c for c in conditions if c not in valid]
  if bad or not conditions:
    raise ValueError(f"conditions {bad or conditions!r} are not valid for {task}; valid: "
                     f"{', '.join(valid)}")
  if len(set(conditions)) != len(conditions):
    raise ValueError(f"conditions {conditions!r} name a condition twice")
  from dmcr_jax.visuals.factors import check_vary
  domain = task.split("-", 1)[0]
  check_vary(domain, train_vary)
  k = agents or 1
  looks = _check_train_look(train_look, k)
  frame_skip = positive_int("action_repeat", default_frame_skip(task)
                            if action_repeat is None else action_repeat)
  h, w = (image_size, image_size) if np.ndim(image_size) == 0 else tuple(image_size)
  positive_int("image height", h)
  positive_int("image width", w)
  if renderer == "pool" and render_options.get("workers") is not None:
    positive_int("workers", render_options["workers"])
  test = held_out_seeds(visual_seeds, seed)
  for look in set(looks):
    check_disjoint(test, look)
  plan = make_plan(domain, conditions, test, dynamics_seeds, train_episodes, looks,
                   train_vary, seed)
  e = plan.episodes
  block = e if max_envs is None else max(1, min(e, positive_int("max_envs", max_envs) // k))
  t = models.load(task)
  config = dict(visual_seeds=int(visual_seeds), dynamics_seeds=int(dynamics_seeds),
                train_episodes=int(train_episodes), seed=int(seed), renderer=renderer,
                conditions=list(conditions), image_size=[int(h), int(w)],
                frame_stack=int(frame_stack), action_repeat=frame_skip,
                train_vary=train_vary if isinstance(train_vary, str) else ",".join(train_vary),
                train_look=[look_label(x) for x in looks],
                **{name: v for name, v in render_options.items()
                   if name not in ("workers", "egl_devices")})  # same pixels either way
  if renderer == "pool":
    config.setdefault("quality", "exact")
  return Protocol(task=task, policy=policy, agents=agents, conditions=tuple(conditions),
                  test_seeds=test, plan=plan, train_looks=looks, renderer=renderer,
                  block=block, episode_length=-(-t.time_limit // frame_skip), config=config,
                  env_kwargs=dict(frame_skip=frame_skip, frame_stack=int(frame_stack),
                                  image_size=(int(h), int(w)), render=dict(render_options)))


def evaluate(task: str, policy: Policy, params, *, agents: int | None = None,
             labels: Sequence[str] | None = None, progress: bool | None = None,
             progress_file: str | None = None, **options) -> Results:
  """The protocol for `policy` with `params`: `prepare(task, policy, agents=agents,
  **options)(params, labels=labels, progress=progress, progress_file=progress_file)`.

  Args:
    task, policy, agents, **options: as for `prepare` (renderer, visual_seeds,
      dynamics_seeds, train_episodes, conditions, train_look, train_vary, seed,
      image_size, frame_stack, action_repeat, max_envs, render options).
    params: the policy's params (leading axis K with agents=K).
    labels, progress, progress_file: as for `Protocol.__call__`.

  Returns:
    The `Results` (`.markdown()`, `.to_json()`, `.plot(path)`, `.write(out_dir)`).
  """
  return prepare(task, policy, agents=agents, **options)(
      params, labels=labels, progress=progress, progress_file=progress_file)
