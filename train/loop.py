"""The training run (SAC+AUG, CURL, SAC+AE): K agents, each acting in its own N pixel envs.

`train` resolves a `TrainConfig` into a plan (`dmcr_jax.train.config.resolve`:
every check, the driver, where physics and frames run), takes the run folder
(`dmcr_jax.train.checkpoint`: one run per folder), builds one `dmcr_jax.make` env
of K·N envs for all agents (agent k acts in envs k·N … k·N + N − 1) and drives a
stepper around `dmcr_jax.train.step`'s training step, reporting each step (or
chunk) to the run's log (`dmcr_jax.train.runlog.RunLog`), saving checkpoints
and stopping on SIGINT/SIGTERM. The two steppers yield the same reports:

- the host driver (`host_steps`, here): per vector step, `act` (jitted), the
  env's `step_async` (physics dispatched), `learn` (the updates owed, launched
  from a second thread: the accelerator runs them while the env steps), the
  env's `step_wait` (rendering), `store` (jitted, buffers donated);
- the device driver (`dmcr_jax.train.device_loop.device_steps`, the ray caster
  with the physics on the learner's device): chunks of the same step scanned
  as single XLA calls.

Steps: `steps` counts training steps per agent as the paper defines them (its
Sec. 4: an action taken and its transition stored; one such step is
`action_repeat` control steps), so with N envs an agent takes ⌈steps/N⌉ vector
steps of N transitions each; the first `warmup_steps` transitions come from
uniform random actions (Table 6: 1,000), and `utd` updates are owed per
transition. On accelerators the update pairs owed at a step run as one jitted
loop; on CPU, where XLA runs a loop body several times slower than the same ops
outside one, that loop is unrolled.

Checkpoints (`<out>/checkpoints`): the agents (parameters, optimizer states, α,
update count), the step counter and the RNG key, every `checkpoint_every` steps,
at the end and when SIGINT/SIGTERM arrives. `resume` restores exactly those; the
replay buffers are NOT saved (100,000 frames are 2.1 GB per agent): a resumed
run starts new episodes and refills its buffers with the restored policy,
`warmup_steps` transitions per agent in which no update is owed
(`updates_from`), then updates at `utd` per transition again.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.train import checkpoint, config, eval_curve, replay, runlog
from dmcr_jax.train import step as train_step
# Names other modules and earlier code reach through this module.
from dmcr_jax.train.checkpoint import init_agents, load_run  # noqa: F401
from dmcr_jax.train.checkpoint import manager as _checkpointer, save as _save  # noqa: F401
from dmcr_jax.train.config import (AGENT_LOOPS, PHYSICS_WORKERS_MAX, RENDERERS,  # noqa: F401
                                   Plan, TrainConfig, check_config, check_renderer,
                                   default_physics_workers, egl_devices_arg, load_config,
                                   look_label, num_looks, parse_visual_seeds, resolve,
                                   save_config)
from dmcr_jax.train.devices import (agent_mesh, mesh_devices, put_agents,  # noqa: F401
                                    valid_device_counts)
from dmcr_jax.train.runlog import crossed, json_safe, plot_learning_curve  # noqa: F401


def open_run(cfg: TrainConfig, resume: bool) -> checkpoint.RunLock:
  """Checks the run folder, takes its lock and writes config.json; the held lock.

  With `resume`, `cfg` must match the run's config.json but for `RESUMABLE`
  fields (`config.check_resume`; changed ones are written back). Every check that
  needs no lock runs before anything is created; the folder's checkpoints are
  looked at again under the lock.

  Raises:
    ValueError: a resumed config that differs from the run's; a folder that is a
      file or cannot be written (`checkpoint.RunFolderError`), or that a running
      process holds (`checkpoint.RunLockedError`, naming it).
    FileExistsError: `out_dir` already holds checkpoints and `resume` is False.
    FileNotFoundError: `resume` and no run (config.json and a checkpoint) in `out_dir`.
  """
  out = cfg.out_dir
  checkpoint.check_out_dir(out)

  def check_folder():
    if resume:
      if not os.path.exists(os.path.join(out, "config.json")):
        raise FileNotFoundError(f"--resume: no run in {out!r} (no config.json); check "
                                "the folder (--out)")
      config.check_resume(load_config(out), cfg)
      if not checkpoint.steps(out):
        raise FileNotFoundError(f"--resume: no checkpoint in {checkpoint.folder(out)}")
    elif checkpoint.steps(out):
      raise FileExistsError(f"{checkpoint.folder(out)} already holds a run (step "
                            f"{checkpoint.steps(out)[-1]}): pass resume=True (--resume) "
                            "to continue it, or choose another out_dir (--out)")

  check_folder()
  lock = checkpoint.RunLock(out).acquire()
  try:
    check_folder()
    save_config(cfg, out)
  except BaseException:
    lock.release()
    raise
  return lock


def finished_summary(cfg: TrainConfig) -> dict | None:
  """For a resumed run whose newest intact checkpoint is at `steps` or past it:
  says so on stderr and returns its summary (summary.json's, else the step);
  None when there is training left to do."""
  done = [s for s in checkpoint.steps(cfg.out_dir)
          if s >= cfg.steps and checkpoint.damage(cfg.out_dir, s) is None]
  if not done:
    return None
  print(f"train: the run in {cfg.out_dir} is finished: its checkpoint is at step "
        f"{done[-1]:,} (steps {cfg.steps:,}); pass a larger --steps to extend it",
        file=sys.stderr, flush=True)
  path = os.path.join(cfg.out_dir, "summary.json")
  summary = runlog.read_json(path) if os.path.exists(path) else dict(steps=done[-1])
  return dict(summary, interrupted=False)


def initial_state(cfg: TrainConfig, plan: Plan, resume: bool, obs_shape, action_size: int):
  """Fresh agents (or the newest intact checkpoint's), empty buffers, the key and step.

  Returns:
    (agents, buffers with leading agent axis K, key, start step).
  """
  k = len(plan.agents)
  agents = init_agents(cfg, obs_shape, action_size)
  one = replay.init(cfg.buffer_capacity, cfg.num_envs, obs_shape[:2] + (3,), action_size,
                    cfg.frame_stack)
  buffers = jax.tree.map(lambda x: jnp.broadcast_to(x, (k,) + x.shape), one)
  key = jax.random.key(int(cfg.seeds[0]) + 7919)
  start = 0
  if resume:
    agents, key, start = checkpoint.restore(cfg.out_dir, agents, key, fallback=True)
  return agents, buffers, key, start


def updates_from(cfg: TrainConfig, start: int) -> int:
  """Transitions per agent before which no update is owed, for a run starting at
  transition `start` (0, or a resumed run's step): `warmup_steps` past it, in
  which a fresh run acts at random and a resumed one refills its buffers (not
  checkpointed) with its restored policy."""
  return int(start) + int(cfg.warmup_steps)


def step_spec(plan: Plan, env) -> train_step.StepSpec:
  """The `dmcr_jax.train.step.StepSpec` of a run on `env` (its action bounds)."""
  cfg = plan.cfg
  return train_step.StepSpec(
      agents=len(plan.agents), num_envs=cfg.num_envs, warmup_steps=int(cfg.warmup_steps),
      utd=float(cfg.utd), sac=cfg.sac, agent_loop=plan.agent_loop,
      low=tuple(float(x) for x in env.single_action_space.low),
      high=tuple(float(x) for x in env.single_action_space.high))


def make_env(cfg: TrainConfig, num_envs: int | None = None, **options):
  """The run's `dmcr_jax.make` env: `num_envs` envs per agent (None: N), K·that
  in all (`options` go to `make`); with several training-look ranges, agent k's
  envs draw from its own range."""
  import dmcr_jax
  k = len(cfg.agents())
  if cfg.renderer == "pool":
    options = dict(quality=cfg.quality, workers=cfg.workers, egl_devices=cfg.egl_devices,
                   **options)
  n = num_envs or cfg.num_envs
  looks = (cfg.looks[0] if len(cfg.looks) == 1
           else [look for look in cfg.agent_looks() for _ in range(n)])
  return dmcr_jax.make(cfg.task, num_envs=k * n, visual_seeds=looks, vary=cfg.vary,
                       moving=cfg.moving, intensity=cfg.intensity, frame_skip=cfg.action_repeat, frame_stack=cfg.frame_stack,
                       image_size=cfg.image_size, seed=int(cfg.seeds[0]),
                       renderer=cfg.renderer, **options)


def physics_before_updates(physics_device: str | None) -> bool:
  """Whether the host driver dispatches a step's physics before its updates.

  True when they share a device (`physics_device` None, or a CPU backend): the
  physics then leaves that device's queue first. Otherwise the updates are
  launched first, before the actions are waited for, so that the device runs
  them right after `act` while the host steps the physics. Either order computes
  the same values.
  """
  return physics_device is None or jax.default_backend() == "cpu"


class HostTimes:
  """The host driver's breakdown of its loop (summary.json's "host_seconds": act,
  learn, env_step_async, env_step_wait, store; "env_seconds": the env's own
  parts; "steady": both from the first episode end past the warm-up, when the
  act and update steps have compiled, to the end)."""

  def __init__(self):
    self.host_s: dict[str, float] = {}
    self.env_s: dict[str, float] = {}
    self.t0 = time.perf_counter()
    self._steady_from = None  # (step, time, host_s, env_s) where `steady` starts

  @contextlib.contextmanager
  def timed(self, part: str):
    """Adds the seconds the block takes to `host_s[part]`."""
    t = time.perf_counter()
    try:
      yield
    finally:
      self.host_s[part] = self.host_s.get(part, 0.0) + time.perf_counter() - t

  def mark_steady(self, step: int, env_s: dict[str, float]) -> None:
    """Starts the steady window at `step` (once; later calls do nothing)."""
    if self._steady_from is None:
      self._steady_from = (step, time.perf_counter(), dict(self.host_s), dict(env_s))

  def summary(self, step: int) -> dict:
    """summary.json's "host_seconds", "env_seconds" and "steady" (transitions per
    agent, wall seconds and each part's seconds; None if never marked)."""
    steady = None
    if self._steady_from is not None:
      s0, t0, host0, env0 = self._steady_from
      diff = lambda now, then: {k: v - then.get(k, 0.0) for k, v in now.items()}
      steady = dict(steps=step - s0, wall_s=time.perf_counter() - t0,
                    host_seconds=diff(self.host_s, host0), env_seconds=diff(self.env_s, env0))
    return dict(host_seconds=self.host_s, env_seconds=self.env_s, steady=steady)


def host_steps(plan: Plan, env, learner: train_step.Learner, spec: train_step.StepSpec,
               start: int, first_update: int, mesh=None, times: HostTimes | None = None):
  """The host driver: yields (step before, step after, finished episodes, learner)
  after every vector step until `steps` (episodes: (step, agent, return, update
  metrics) each; the learner settled, its updates done)."""
  cfg = plan.cfg
  n = cfg.num_envs
  times = times or HostTimes()
  on_cpu = jax.default_backend() == "cpu"
  put = lambda x: put_agents(jnp.asarray(x), mesh)
  physics_first = physics_before_updates(plan.physics_device)

  def learn(learner, owed, ready, step):
    """`dmcr_jax.train.step.learn` with the pairs planned at `step` (host counters)."""
    owed, ready, pairs = train_step.plan_updates(
        owed, ready, step, lambda: train_step.can_sample_jit(learner.buffers), spec,
        updates_from=first_update)
    learner = train_step.learn_jit(learner, pairs=int(pairs), spec=spec, mesh=mesh,
                                   unroll=on_cpu)
    return learner, owed, ready

  owed, ready, step = np.float32(0), False, start
  obs, info = env.reset(seed=int(cfg.seeds[0]) + start)
  first = info["episode_step"] == 0
  with ThreadPoolExecutor(1, "updates") as updates:
    while step < cfg.steps:
      with times.timed("act"):
        o, f = put(obs), put(first)
        learner, action, env_action = train_step.act_jit(learner, o, spec=spec, mesh=mesh)
      # The updates owed are launched from another thread (launching their kernels
      # holds a thread for a large part of their run) while this one steps the env.
      # Physics on the updates' device is dispatched first (it then leaves the
      # queue first, and the host renders while the updates run); else the updates
      # are launched before the actions are waited for, so that they queue right
      # behind `act` on the device.
      if not physics_first:
        learning = updates.submit(learn, learner, owed, ready, step)
      with times.timed("act"):  # waits for what the device runs before `act`
        env_action = np.asarray(env_action)
      with times.timed("env_step_async"):
        env.step_async(env_action)
      if physics_first:
        learning = updates.submit(learn, learner, owed, ready, step)
      with times.timed("env_step_wait"):
        obs, reward, _, truncated, info = env.step_wait()
      with times.timed("learn"):  # `store` writes the buffers the updates read
        learner, owed, ready = learning.result()
      with times.timed("store"):
        learner = train_step.store_jit(learner, o, f, action, put(reward), spec=spec,
                                       mesh=mesh)
      before, step = step, step + n
      first = info["episode_step"] == 0
      times.env_s = {part: env.timings[part] for part in env.timing_parts}
      metrics = jax.device_get(learner.metrics) if truncated.any() else {}
      if truncated.any() and step > cfg.warmup_steps:
        times.mark_steady(step, times.env_s)
      yield before, step, [(step, int(i // n), float(info["episode_return"][i]), metrics)
                           for i in np.flatnonzero(truncated)], learner


def train(cfg: TrainConfig | Plan, resume: bool = False, progress: bool = True,
          devices: int | None = None) -> dict:
  """Trains the plan's agents (a config is resolved first); returns a summary (also
  written as JSON).

  The agent axis is sharded over the plan's local devices (`devices` None: all of
  them when K is a multiple of their count, else one; the device driver runs on
  one). Writes `<out_dir>/config.json`, `<out_dir>/log.csv` (one row per finished
  episode: step, agent, seed, augmentation, return, length, wall time,
  transitions/s, gradient updates/s and the latest update metrics), `<out_dir>/learning_curve.png`, segments.json and
  summary.json (with the host driver also `HostTimes.summary`) and the
  checkpoints; with `eval_every`, eval_curve.csv and eval_curve.png
  (`dmcr_jax.train.eval_curve`; summary.json's "eval_seconds"). A resumed run whose checkpoint is at `steps` already returns its
  summary at once.

  Args:
    cfg: the run's config, or its plan (`dmcr_jax.train.config.resolve`; then
      `devices` is the plan's).
    resume: continue the run in `cfg.out_dir` from its newest intact checkpoint.
    progress: a progress bar on a terminal (progress lines otherwise, and always
      without one).
    devices: local devices to shard the agents over (None: `resolve`'s choice).

  Raises:
    ValueError: a bad config, device count or run folder (before anything is built).
    FileExistsError: `out_dir` already holds checkpoints and `resume` is False.
    FileNotFoundError: `resume` and no checkpoint.
  """
  plan = cfg if isinstance(cfg, Plan) else resolve(cfg, devices)
  cfg = plan.cfg
  with contextlib.ExitStack() as stack:
    stack.callback(open_run(cfg, resume).release)
    done = finished_summary(cfg) if resume else None
    if done is not None:
      return done
    for line in (plan.describe(),) + plan.notes:
      print(f"{cfg.task}: {line}", file=sys.stderr, flush=True)
    extra = dict(obs_on_device=True) if cfg.renderer == "jax" else {}
    env = stack.enter_context(make_env(cfg, physics_device=plan.physics_device,
                                       physics_workers=plan.physics_workers, **extra))
    spec = step_spec(plan, env)
    agents, buffers, key, start = initial_state(cfg, plan, resume,
                                                env.single_observation_space.shape,
                                                env.task.action_size)
    mesh = None if plan.device_driver else agent_mesh(len(plan.agents), plan.devices)
    learner = train_step.init_learner(put_agents(agents, mesh), put_agents(buffers, mesh),
                                      key, start, spec)
    times = None if plan.device_driver else HostTimes()
    if plan.device_driver:
      from dmcr_jax.train import device_loop
      steps = device_loop.device_steps(plan, env, learner, spec, start,
                                       updates_from(cfg, start))
    else:
      steps = host_steps(plan, env, learner, spec, start, updates_from(cfg, start), mesh,
                         times)
    stack.callback(steps.close)
    manager = checkpoint.manager(cfg.out_dir)
    log = stack.enter_context(runlog.RunLog(cfg, plan.agents, plan.look_labels, start,
                                            resume, progress,
                                            episode_length=env.episode_length))
    curve = stack.enter_context(eval_curve.EvalCurve(plan, start, resume))
    step, updates_before = start, train_step.update_count(learner)
    for before, step, episodes, learner in steps:   # the stepper ends at `steps`
      # The updates this segment has run and the latest update metrics, read where
      # episodes end or the log is due (the drivers then wait for the learner anyway).
      due = log.due(before, step)
      updates = (train_step.update_count(learner) - updates_before
                 if episodes or due else None)
      log.report(before, step, episodes, updates,
                 jax.device_get(learner.metrics) if due else None)
      if crossed(cfg.checkpoint_every, before, step) or step >= cfg.steps or log.stopped:
        checkpoint.save(manager, step, learner.agents, learner.key)
        log.checkpointed(step)
      if log.stopped:
        break
      if curve.due(before, step):
        log.evaluated(curve.evaluate(step, learner.agents))
    if log.stopped:
      print(f"interrupted: saved checkpoint at step {step} in "
            f"{os.path.join(checkpoint.folder(cfg.out_dir), str(step))}; resume with "
            f"dmcr-train --resume --out {cfg.out_dir}", file=sys.stderr, flush=True)
    curve.close()  # eval_curve.png
    return runlog.finish(cfg, step, log,
                         dict(times.summary(step) if times else {}, **curve.summary()))
