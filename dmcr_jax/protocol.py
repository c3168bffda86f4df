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
  the domain) and "all" (`conditions_for`); and moving conditions
  ``moving-<factor>@<intensity>`` (`conditions=` names, or `moving_intensities=`
  for every moving factor and "all" at each intensity): dm_control's look with
  that factor moving within each episode, the held-out seed picking its motion, as
  `dmcr_jax.make(vary="none", moving=factor, intensity=intensity)` draws it
  (`protocol_plan.parse_condition`; intensity 0 is "none");
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
inside a block; with moving conditions each step's looks are made in the scan, every
env moving its own factors). "pool" renders MuJoCo's own pixels in the CPU render
pool (`dmcr_jax.make`), every condition's envs in one block (`PixelVectorEnv.set_looks`),
the same jitted policy called from the host loop; a block steps as two pipelined
groups of envs (`pool_groups`), or one group per motion when it holds moving
conditions (`protocol_pool.block_groups`), a group's physics and policy running
while the workers draw another's frames, the physics on the host CPU
(`protocol_pool.pass_workers`). Returns are those of `dmcr_jax.make`'s env stepped by
the same policy (`tests/test_protocol.py`). The policy is vmapped over envs (and
the K agents run one after another, each on its own envs): an env's action
depends on its own observation and key alone, so the returns do not depend on
`max_envs` or on the number of agents (up to the float rounding of a
batched matrix product, which on some backends varies with the batch size).
This module is the public door (`prepare`, `Protocol`, `evaluate`, `Results` and
the helpers re-exported below); the parts live beside it, one concern each: the plan
(conditions, looks, seeds, every agent's episodes) in `dmcr_jax.protocol_plan`, the
policy contract and its checks in `dmcr_jax.protocol_policy`, the ray caster's block
program in `dmcr_jax.protocol_ray`, the pool pass in `dmcr_jax.protocol_pool`, the
`Results` in `dmcr_jax.protocol_results` and the reports in `dmcr_jax.protocol_report`.

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
import math
import os
import sys
import time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax._progress import progress_bar
from dmcr_jax.checks import positive_int
from dmcr_jax.protocol_plan import (FACTOR_CONDITIONS, MOVING_PREFIX, PROGRESS_FILE, Plan,
                                    Segment, check_conditions, check_disjoint,
                                    conditions_for, held_out_seeds, is_default_look,
                                    load_progress, look_label, make_plan, moving_condition,
                                    moving_conditions_for, moving_of, parse_condition,
                                    reset_seeds, save_progress, train_look_seeds)
from dmcr_jax.protocol_policy import (POLICY_STREAM, Policy, agent_count, check_actions,
                                      check_policy, env_actions, params_digest,
                                      policy_actions, worst_action)
from dmcr_jax.protocol_pool import (POOL_GROUPS, _pool_act, block_runner,  # noqa: F401
                                    pool_envs, pool_groups, run_pipelined)
from dmcr_jax.protocol_ray import (_pixel_env, _ray_block, _ray_block_jit,  # noqa: F401
                                   block_looks, episode_step, render_chunk, render_padding)
from dmcr_jax.protocol_report import generalization_error
from dmcr_jax.protocol_results import Results
from dmcr_jax.visuals.levels import SeedRange

__all__ = ["FACTOR_CONDITIONS", "MOVING_PREFIX", "POLICY_STREAM", "POOL_GROUPS",
           "PROGRESS_FILE", "Plan", "Policy", "Protocol", "Results", "Segment",
           "block_looks", "check_actions", "check_conditions", "check_disjoint",
           "check_policy", "conditions_for", "env_actions", "episode_step", "evaluate",
           "generalization_error", "held_out_seeds", "is_default_look", "load_progress",
           "look_label", "make_plan", "moving_condition", "moving_conditions_for",
           "moving_of", "params_digest", "parse_condition", "policy_actions",
           "pool_groups", "prepare", "render_chunk", "render_padding", "reset_seeds",
           "run_pipelined", "save_progress", "train_look_seeds", "worst_action"]

_POOL_OPTIONS = ("quality", "workers", "physics_workers", "egl_devices", "gl")
_JAX_OPTIONS = ("shadows", "reflection", "render_chunk", "render_kernel")



@dataclasses.dataclass(frozen=True)
class Protocol:
  """A planned protocol (build with `prepare`): call it with params to run a pass.

  The jitted block program is built once per (policy, sizes); calling again with
  other params of the same shapes compiles nothing (a training loop can evaluate
  its agents as it goes). With the pool, each pass starts its render and physics
  workers and stops them at its end; inside ``with proto:`` they start on the
  first pass and serve every pass until the block ends (`close`), so that passes
  after the first pay only for their episodes:

      with protocol.prepare(task, policy, renderer="pool") as proto:
        results = [proto(p) for p in checkpoints]

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
  _held: dict = dataclasses.field(default_factory=dict, init=False, repr=False,
                                  compare=False)
  """Inside ``with``: "open" (True), and once a pool pass has opened its envs
  "pool", (the `contextlib.ExitStack` that closes them, their
  `protocol_pool.PoolEnvs`)."""

  def __enter__(self) -> "Protocol":
    if "open" in self._held:
      raise RuntimeError("this Protocol is already open (`with proto:` nested)")
    self._held["open"] = True
    return self

  def __exit__(self, *exc) -> None:
    self.close()

  def close(self) -> None:
    """Stops the workers the passes inside ``with`` kept (nothing else to do)."""
    self._held.pop("open", None)
    self._drop_pool()

  def _drop_pool(self) -> None:
    """Closes the kept pool envs, if any, and forgets them."""
    held = self._held.pop("pool", None)
    if held is not None:
      held[0].close()

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
    on, intensity = p.motion_arrays(idx)
    return dict(seeds=flat(p.visual_seed[:, idx]), masks=flat(p.mask[:, idx]),
                vary_index=flat(p.vary_index[:, idx]),
                resets=np.tile(p.reset_seed[idx], k), index=np.tile(p.index[idx], k),
                motion_index=np.tile(p.motion_index[idx], k), motion=np.tile(on, (k, 1)),
                intensity=np.tile(intensity, k))

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
    k = agent_count(params, self.agents)
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
    moving = self.plan.moving

    def run_block(inputs):
      motion = (jnp.asarray(inputs["motion"]), jnp.asarray(inputs["intensity"])) \
          if moving else None
      returns, worst = fn(penv, params, jnp.asarray(inputs["seeds"]),
                          jnp.asarray(inputs["masks"]), jnp.asarray(inputs["resets"]),
                          jnp.asarray(inputs["index"]), key, motion, policy=self.policy,
                          agents=self.agents, steps=self.episode_length, moving=moving)
      check_actions(np.asarray(worst))
      return np.asarray(returns, np.float64)
    yield run_block

  @contextlib.contextmanager
  def _pool_runner(self, params, key):
    """A context giving `run_block(inputs) -> returns (K·B,)` with the render pool
    (`protocol_pool.block_runner`): on the pool envs kept inside ``with`` (opened
    on the first pass; closed and dropped where a pass fails, so that the next
    opens new ones), else on envs opened for this pass alone."""
    if "open" not in self._held:
      with pool_envs(self) as penvs:
        yield block_runner(self, penvs, params, key)
      return
    if "pool" not in self._held:
      stack = contextlib.ExitStack()
      self._held["pool"] = (stack, stack.enter_context(pool_envs(self)))
    try:
      yield block_runner(self, self._held["pool"][1], params, key)
    except BaseException:
      self._drop_pool()
      raise


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
            conditions: Sequence[str] | None = None,
            moving_intensities: Sequence[float] = (), train_look=0, train_vary="all",
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
    conditions: the conditions to run (default: every static one that applies,
      `conditions_for`); static names ("none", "floor", "all", …) or moving ones,
      ``moving-<factor>@<intensity>`` (`protocol_plan.parse_condition`: dm_control's
      look with that factor moving within each episode; factor "all" moves all).
    moving_intensities: also every moving condition (each moving factor of the
      domain, then "all") at each of these intensities (e.g. (0.1, 0.2, 0.3)).
    train_look: the training look: a visual seed (0: dm_control's), a `SeedRange`
      (few-shot), or one per agent.
    train_vary: the factors the training looks vary ("all").
    seed: seeds the held-out looks' draw, the initial states and the policy keys.
    image_size, frame_stack: the observations' size (H = W, or (H, W)) and stack.
    action_repeat: control steps per agent step (default: the paper's for the task).
    max_envs: at most this many envs per block (default: every episode in one block).
    **render_options: "jax": shadows, reflection, render_chunk, render_kernel;
      "pool": quality, workers, egl_devices, gl (`dmcr_jax.make`), physics_workers
      (CPU processes stepping each pool env's physics; 0: this process; default
      `protocol_pool.pass_workers`).

  Returns:
    The `Protocol`; call it with params.

  Raises:
    ValueError: any bad option (the message names the valid ones).
  """
  from dmcr_jax import models
  from dmcr_jax.env_checks import check_physics_workers, check_renderer_name, default_frame_skip
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
  conditions = check_conditions(task, conditions, moving_intensities)
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
  if renderer == "pool" and render_options.get("physics_workers") is not None:
    check_physics_workers(render_options["physics_workers"], "cpu")
  test = held_out_seeds(visual_seeds, seed)
  for look in set(looks):
    check_disjoint(test, look)
  plan = make_plan(task, conditions, test, dynamics_seeds, train_episodes, looks,
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
                   if name not in ("workers", "physics_workers", "egl_devices")})  # same returns
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
