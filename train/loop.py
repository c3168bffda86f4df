"""The training run (SAC+AUG, CURL, SAC+AE): K agents, each acting in its own N pixel envs.

`train` builds one `dmcr_jax.make` env of K·N envs for all agents (agent k acts
in envs k·N … k·N + N − 1) and drives `dmcr_jax.train.step`'s training step around it
(the host driver): per vector step, `act` (jitted), the env's `step_async`
(physics dispatched), `learn` (the updates owed, dispatched: the accelerator
runs them while the env steps), the env's `step_wait` (rendering), `store`
(jitted, buffers donated). With the JAX renderer and the physics on the same
device, `dmcr_jax.train.device_loop` (the device driver) scans chunks of the same step as
single XLA calls instead. Both drivers share this module's config, log,
checkpoints, resume and summary.

Physics device (`TrainConfig.physics`): "auto" steps the physics of small
batches (K·N ≤ `CPU_PHYSICS_MAX_ENVS`) on the host CPU when the learner runs on
an accelerator: a few dozen envs step there faster than an accelerator's launch
latency allows, and off the accelerator's queue, so the updates and the physics
run at the same time; larger batches step on the accelerator. On the host CPU the
physics steps in `TrainConfig.physics_workers` processes (`dmcr_jax.physics_pool`),
each a slice of the envs, so that a many-core host steps the batch in parallel
(default None: `default_physics_workers`, half the host's cores and at most
`PHYSICS_WORKERS_MAX` beside an accelerator; 0 is the training process itself).

Env groups (`TrainConfig.env_groups` = G, host driver): each agent's N envs are
G envs of N/G (G `dmcr_jax.make` envs, each with its own render workers), stepped
one group per training step in turn: group g acts, its physics is dispatched and
the updates owed for its N/G transitions are dispatched, then the group stepped
longest ago finishes (`step_wait`: its pixels) and its transitions are stored.
With G = 2 one group's physics and pixels are computed on the host while the
accelerator runs the updates and acts for the other (double-buffered sampling),
so the host's env work stays off the training step's critical path as long as it
takes less than G steps' updates. Every transition is acted on by the freshest
policy the accelerator has; updates sample the transitions stored so far (those
of the groups still stepping are not yet in the buffers). G = 1 is the plain
vector step.

Agents: one per (training looks, augmentation, seed): the look groups of
`visual_seeds` × `sac.aug_names` × `seeds` (e.g. ``aug="drq,cj+drq"`` with 3
seeds trains 6 agents; ``visual_seeds="levels:1,10,100"`` makes that 18, each
agent's envs drawing their looks from its own range). An agent's network init
depends only on its seed, so augmentations and ranges are compared from the
same start.

Devices (host driver): the agent axis is sharded over the local devices with
`shard_map` (each device updates and acts for K / D of the agents, their
buffers on it), all D of them when K is a multiple of D, else one device
(`mesh_devices`; `train(..., devices=D)` picks D). One process drives them all
and renders every env in one render pool on the host. The device driver runs on
one device.

Steps: `steps` counts training steps per agent as the paper defines them (its
Sec. 4: an action taken and its transition stored; one such step is
`action_repeat` control steps), so with N envs an agent takes ⌈steps/N⌉ vector
steps of N transitions each; the first `warmup_steps` transitions come from
uniform random actions (Table 6: 1,000), and `utd` updates are owed per
transition.

Agent batching (`agent_loop`): "vmap" batches the K agents' updates, "map" runs
them one after the other in the same call; None picks "map" on accelerators and
"vmap" on CPU (`dmcr_jax.train.step`).

Update chunks: on accelerators the update pairs owed at a step run as one
jitted loop; on CPU, where XLA runs a loop body several times slower than the
same ops outside one, that loop is unrolled.

Checkpoints (orbax, `<out>/checkpoints`): the agents (parameters, optimizer
states, α, update count), the step counter and the RNG key, every
`checkpoint_every` steps and when SIGINT/SIGTERM arrives. `resume` restores
exactly those; the replay buffers are NOT saved (100,000 frames are 2.1 GB per
agent): a resumed run starts new episodes and refills its buffers with the
restored policy, `warmup_steps` transitions per agent in which no update is
owed (`updates_from`), then updates at `utd` per transition again.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import json
import os
import signal
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.checks import positive_int
from dmcr_jax.env import (RENDERERS, check_physics_workers,  # noqa: F401 (RENDERERS: CLIs)
                          check_renderer_name)
from dmcr_jax.visuals.levels import TEST_SEEDS, TRAIN_SEEDS, SeedRange
from dmcr_jax.train import replay, sac
from dmcr_jax.train import step as train_step


AGENT_LOOPS = ("vmap", "map")
"""What `TrainConfig.agent_loop` accepts."""
PHYSICS = ("auto", "cpu", "device")
"""What `TrainConfig.physics` accepts: "auto" (module doc), the host CPU, or the
learner's device."""
CPU_PHYSICS_MAX_ENVS = 64
"""The largest K·N whose physics "auto" steps on the host CPU."""
PHYSICS_WORKERS_MAX = 8
"""The most physics worker processes `default_physics_workers` gives a run."""
RESUMABLE = ("steps", "checkpoint_every", "log_every", "workers", "physics_workers",
             "egl_devices")
"""`TrainConfig` fields a resumed run may change (a larger `steps` extends it; the
others change neither the agents nor the data); `out_dir` may name the folder
differently. Every other field must equal the run's config.json."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """What a training run does (every field has the paper's default where it has one).

  Attributes:
    task: a DMCR task, e.g. "cartpole-balance".
    steps: training steps (transitions) per agent (the paper's Sec. 4 and Table 4).
    seeds: one agent per seed and per augmentation in `sac.aug`. An agent's seed
      fixes its network initialisation; exploration, updates and the envs'
      initial states draw from one run key made from the first seed and split
      over the run's agents, so an agent trained beside others is another sample
      than the one its seed gives trained alone.
    num_envs: envs per agent; each vector step stores N transitions per agent, and
      the updates owed for them (N·utd) run before the next. 32 by default: the
      step's fixed cost (act, frames, store, the host's turnaround) is spread
      over more transitions. (The paper trained one env; learning curves at equal
      transition counts against fewer envs: benchmarks/results/num_envs_curves_h200.)
    action_repeat: None = the paper's Table 4 value for the task.
    visual_seeds: an int (fixed look; 0 = dm_control's) or "levels:<n>[,<n>…]"
      (few-shot: every episode draws a look from seeds [0, n); several counts
      train one agent per range, `parse_visual_seeds`).
    vary: factors the visual seeds change.
    warmup_steps: random-action training steps (transitions) per agent before
      learning (Table 6: 1,000).
    utd: gradient updates per training step (Table 6: 1).
    buffer_capacity: transitions per agent (Table 6: 100,000).
    image_size, frame_stack: observation size (Table 6: 84, 3). None = 84, or for
      CURL `sac.curl_crop` + 16 (100: CURL renders larger and crops to 84).
    quality: render preset (`dmcr_jax.visuals.tiled.QUALITY`).
    workers: render workers (None: one per core).
    egl_devices: EGL device indices the render workers are spread over (None:
      MuJoCo's default; `dmcr_jax.visuals.render_pool`), e.g. GPUs other than the
      learner's.
    log_every: steps between progress-bar and CSV metric updates.
    checkpoint_every: steps between checkpoints (0: only at the end / on a signal);
      checkpoints fall on the first vector step at or past each multiple.
    agent_loop: "vmap" or "map", how the K agents' updates are batched; None picks
      by backend (module doc).
    renderer: "pool" (the CPU render pool; this module's host loop) or "jax" (the
      JAX ray caster; `dmcr_jax.train.device_loop` runs chunks of training as single XLA
      calls).
    chunk_steps: with the device driver (renderer "jax", physics on the device),
      vector steps (of all envs) per XLA call; logs, checkpoints and the stop
      flag are handled between chunks.
    physics: where the physics steps: "auto", "cpu" or "device" (module doc).
    env_groups: G, the groups each agent's N envs step in with the host driver
      (module doc); G divides N; 1 with the device driver.
    physics_workers: with the physics on the host CPU, processes that step each
      env group's physics (`dmcr_jax.physics_pool`; 0: the training process; None:
      `default_physics_workers`).
    out_dir: where the CSV, the PNG and the checkpoints go.
    sac: the learner's hyperparameters.
  """
  task: str = "cartpole-balance"
  steps: int = 50_000
  seeds: tuple[int, ...] = (0,)
  num_envs: int = 32
  action_repeat: int | None = None
  visual_seeds: int | str = 0
  vary: str = "all"
  warmup_steps: int = 1000
  utd: float = 1.0
  buffer_capacity: int = 100_000
  image_size: int | None = None
  frame_stack: int = 3
  quality: str = "exact"
  workers: int | None = None
  egl_devices: tuple[int, ...] | None = None
  log_every: int = 1000
  checkpoint_every: int = 10_000
  out_dir: str = "runs/default"
  agent_loop: str | None = None
  renderer: str = "pool"
  chunk_steps: int = 50
  physics: str = "auto"
  env_groups: int = 1
  physics_workers: int | None = None
  sac: sac.SACConfig = sac.SACConfig()

  def __post_init__(self):
    if self.image_size is None:
      size = self.sac.curl_crop + 16 if self.sac.algo == "curl" else 84
      object.__setattr__(self, "image_size", size)

  def physics_device(self) -> str | None:
    """`dmcr_jax.make`'s `physics_device` for this run (None: JAX's default)."""
    if self.physics == "cpu" or (
        self.physics == "auto" and jax.default_backend() != "cpu"
        and len(self.agents()) * self.num_envs <= CPU_PHYSICS_MAX_ENVS):
      return "cpu"
    return None

  def physics_pool_workers(self) -> int:
    """`dmcr_jax.make`'s `physics_workers` for each env group of this run (0 unless
    the physics steps on the host CPU; `default_physics_workers` when None)."""
    if self.physics_device() != "cpu":
      return 0
    if self.physics_workers is None:
      return default_physics_workers(os.cpu_count() or 1, jax.default_backend(),
                                     self.env_groups)
    return self.physics_workers

  def device_driver(self) -> bool:
    """Whether `train` runs this config with the device driver
    (`dmcr_jax.train.device_loop`: the JAX renderer with the physics on the learner's
    device; one device, no env groups) rather than the host loop."""
    return self.renderer == "jax" and self.physics_device() is None

  def agents(self) -> list[tuple[int, str]]:
    """(seed, augmentation) of each agent, in the order of the agent axis (look
    groups outermost, then augmentations, then seeds; `agent_looks`)."""
    groups = len(parse_visual_seeds(self.visual_seeds))
    return [(seed, aug) for _ in range(groups) for aug in self.sac.aug_names
            for seed in self.seeds]

  def agent_looks(self) -> list[int | SeedRange]:
    """The training looks of each agent (a fixed seed or a `SeedRange`), in the
    order of the agent axis."""
    per_group = len(self.sac.aug_names) * len(self.seeds)
    return [look for look in parse_visual_seeds(self.visual_seeds) for _ in range(per_group)]


ALL_LEVELS = "all"
"""The count `levels:` takes for the whole training range (`TRAIN_SEEDS`)."""
VISUAL_SEEDS_FORM = (
    "an int in [0, 2**31 - 1] (one fixed look; 0 = dm_control's) or "
    f"'levels:<n>[,<n>...]': distinct ints 1 <= n <= {len(TRAIN_SEEDS)} (2**30) or "
    f"'{ALL_LEVELS}', one agent per range of the first n seeds (levels:1 = seed 0 only, "
    "dm_control's look), e.g. levels:1,10,100,1000,10000,all")
"""The valid forms of `TrainConfig.visual_seeds` (named by its errors)."""


def default_physics_workers(cores: int, backend: str, groups: int = 1) -> int:
  """Physics worker processes per env group when `TrainConfig.physics_workers` is
  None and the physics steps on the host CPU.

  Args:
    cores: the host's CPU cores.
    backend: JAX's default backend, where the learner runs ("cpu", "gpu", "tpu").
    groups: env groups (`TrainConfig.env_groups`), each with its own workers.

  Returns:
    Half the cores, at most `PHYSICS_WORKERS_MAX`, shared by the groups, when the
    learner runs on an accelerator (the other half render and launch the updates);
    0, the physics in the training process, when that leaves fewer than two per
    group or when the learner itself runs on the CPU's cores.
  """
  if backend == "cpu":
    return 0
  workers = min(PHYSICS_WORKERS_MAX, int(cores) // 2) // int(groups)
  return workers if workers >= 2 else 0


def parse_visual_seeds(value) -> tuple[int | SeedRange, ...]:
  """`TrainConfig.visual_seeds` → the training looks of each look group, each what
  `dmcr_jax.make` takes: (seed,) for a fixed look, or one `levels(n)` per count of
  "levels:<n>[,<n>…]" ("all" = the whole `TRAIN_SEEDS`).

  Raises:
    ValueError: naming `VISUAL_SEEDS_FORM`, for a seed out of range, a count < 1
      or past the training range (which would reach `TEST_SEEDS`), a duplicate
      count, a non-integer, or a fixed seed mixed with levels.
  """
  from dmcr_jax.visuals.levels import levels
  from dmcr_jax.visuals.params import check_seeds

  def bad(why: str):
    return ValueError(f"visual_seeds {value!r}: {why}; valid: {VISUAL_SEEDS_FORM}")

  if isinstance(value, str) and "levels" in value:
    if not value.startswith("levels:"):
      raise bad("a fixed seed cannot be mixed with levels (one form or the other)")
    if value.count("levels") > 1:
      raise bad("give levels: once, with comma-separated counts")
    counts = []
    for item in value[len("levels:"):].split(","):
      item = item.strip()
      if item == ALL_LEVELS:
        counts.append(len(TRAIN_SEEDS))
        continue
      if not item.lstrip("+-").isdigit():
        raise bad(f"{item!r} is not an integer count of looks")
      n = int(item)
      if n < 1:
        raise bad(f"levels:{n} holds no seed (the zero-shot setting is levels:1, seed 0)")
      if n > len(TRAIN_SEEDS):
        raise bad(f"levels:{n} reaches past the training range {TRAIN_SEEDS} into the "
                  f"held-out test range {TEST_SEEDS}")
      counts.append(n)
    if len(set(counts)) != len(counts):
      raise bad("a count appears twice (one agent per range)")
    return tuple(levels(n) for n in counts)
  try:
    if isinstance(value, (bool, float)):
      raise ValueError
    seed = int(value)
    check_seeds(seed)
  except (TypeError, ValueError):
    raise bad("not a seed in [0, 2**31 - 1]") from None
  return (seed,)


def look_label(look: int | SeedRange) -> str:
  """How logs, tables and plots name a training look: "seed 0" or "levels:10"."""
  if isinstance(look, SeedRange):
    return f"levels:{ALL_LEVELS}" if look == TRAIN_SEEDS else f"levels:{len(look)}"
  return f"seed {look}"


def num_looks(look: int | SeedRange) -> int:
  """How many looks a training look holds (1 for a fixed seed)."""
  return len(look) if isinstance(look, SeedRange) else 1


def check_renderer(renderer: str, quality: str, workers: int | None,
                   egl_devices: tuple[int, ...] | None = None) -> None:
  """A ValueError for a renderer not in `RENDERERS`, for the pool's options
  (`quality` other than the default "exact", `workers`, `egl_devices`) given to
  the JAX one, or for EGL devices that are not device indices."""
  from dmcr_jax.visuals.render_pool import check_egl_devices, default_gl
  check_renderer_name(renderer)
  if renderer == "jax" and (quality != "exact" or workers is not None
                            or egl_devices is not None):
    raise ValueError("quality, workers and egl_devices apply only to renderer 'pool' "
                     "(the JAX ray caster has no render workers and no quality presets)")
  check_egl_devices(egl_devices, default_gl())


def egl_devices_arg(text: str) -> tuple[int, ...]:
  """A command line's `--egl-devices` ("1", "0,1") as a tuple of device indices
  (an argparse type: a bad value is reported as the flag's error)."""
  import argparse
  parts = text.split(",")
  if not all(p.strip().isdigit() for p in parts):
    raise argparse.ArgumentTypeError(
        f"want EGL device indices (ints >= 0) separated by commas, got {text!r}")
  return tuple(int(p) for p in parts)


def check_config(cfg: TrainConfig) -> None:
  """Raises ValueError naming the problem (before anything is compiled)."""
  from dmcr_jax import models
  from dmcr_jax.visuals.factors import check_vary
  from dmcr_jax.visuals.tiled import check_quality
  domain, _ = models.split_name(cfg.task)
  check_vary(domain, cfg.vary)
  check_quality(cfg.quality)
  parse_visual_seeds(cfg.visual_seeds)
  for name in ("steps", "num_envs", "buffer_capacity", "image_size", "frame_stack",
               "log_every"):
    positive_int(name, getattr(cfg, name))
  if (not cfg.seeds or len(set(cfg.seeds)) != len(cfg.seeds)
      or any(isinstance(s, bool) or not isinstance(s, (int, np.integer))
             or not 0 <= s < 2**31 for s in cfg.seeds)):
    raise ValueError(f"seeds must be distinct ints in [0, 2**31), got {cfg.seeds!r}")
  if cfg.workers is not None:
    positive_int("workers", cfg.workers)
  # The env's own check; "cpu" because the workers only apply there
  # (`physics_pool_workers`).
  check_physics_workers(cfg.physics_workers, "cpu")
  if cfg.warmup_steps < 0 or cfg.checkpoint_every < 0:
    raise ValueError("warmup_steps and checkpoint_every must be >= 0")
  if not cfg.utd > 0:
    raise ValueError(f"utd must be > 0, got {cfg.utd}")
  if cfg.action_repeat is not None and cfg.action_repeat < 1:
    raise ValueError(f"action_repeat must be a positive int, got {cfg.action_repeat}")
  if cfg.buffer_capacity < cfg.num_envs * (cfg.frame_stack + 1):
    raise ValueError(f"buffer_capacity must be at least num_envs·(frame_stack + 1) = "
                     f"{cfg.num_envs * (cfg.frame_stack + 1)}")
  check_renderer(cfg.renderer, cfg.quality, cfg.workers, cfg.egl_devices)
  if cfg.renderer == "jax":
    positive_int("chunk_steps", cfg.chunk_steps)
  if cfg.physics not in PHYSICS:
    raise ValueError(f"physics must be one of {', '.join(PHYSICS)}, got {cfg.physics!r}")
  groups = positive_int("env_groups", cfg.env_groups)
  if cfg.num_envs % groups:
    raise ValueError(f"env_groups ({groups}) must divide num_envs ({cfg.num_envs}): each "
                     "group steps num_envs / env_groups envs per agent")
  if groups > 1 and cfg.device_driver():
    raise ValueError("env_groups > 1 needs the host driver: the pool renderer, or "
                     "--renderer jax with the physics on the host CPU (physics 'cpu')")
  if cfg.agent_loop is not None and cfg.agent_loop not in AGENT_LOOPS:
    raise ValueError(f"agent_loop must be one of {', '.join(AGENT_LOOPS)}, got "
                     f"{cfg.agent_loop!r}")
  if cfg.image_size < 16:
    raise ValueError(f"image_size must be >= 16 for the encoder, got {cfg.image_size}")
  if cfg.sac.algo == "curl" and cfg.image_size <= cfg.sac.curl_crop:
    raise ValueError(f"CURL crops {cfg.sac.curl_crop}-pixel windows: image_size must be "
                     f"> curl_crop ({cfg.sac.curl_crop}; CURL renders "
                     f"{cfg.sac.curl_crop + 16}), got {cfg.image_size}")


def check_resume(saved: TrainConfig, cfg: TrainConfig) -> None:
  """ValueError naming the fields in which `cfg` differs from the run's `saved`
  config, other than those in `RESUMABLE` (and `out_dir`)."""
  old, new = dataclasses.asdict(saved), dataclasses.asdict(cfg)
  differ = [k for k in old if k not in RESUMABLE + ("out_dir",) and old[k] != new[k]]
  if differ:
    raise ValueError(
        f"resume: the config differs from the run's config.json in {cfg.out_dir} in "
        + ", ".join(f"{k} ({new[k]!r}, the run has {old[k]!r})" for k in differ)
        + f"; a resumed run keeps its settings (only {', '.join(RESUMABLE)} may change): "
        "use `dmcr_jax.train.loop.load_config(out_dir)`, or start a new run in another out_dir")


# Devices ----------------------------------------------------------------------------


def valid_device_counts(k: int, available: int) -> list[int]:
  """The local device counts K agents can be sharded over: 1, and every count up
  to `available` that divides K (`shard_map` gives each device K / count agents)."""
  return [n for n in range(1, available + 1) if n == 1 or k % n == 0]


def check_devices(devices: int, k: int, available: int) -> None:
  """Raises ValueError, naming the valid counts, unless K agents can be sharded
  over `devices` of the `available` local devices (`valid_device_counts`)."""
  valid = valid_device_counts(k, available)
  if isinstance(devices, bool) or not isinstance(devices, (int, np.integer)) or devices < 1:
    why = "not a positive device count"
  elif devices in valid:
    return
  elif devices > available:
    why = "more than the local devices"
  else:
    why = f"{k} agent{'s are' if k != 1 else ' is'} not a multiple of it"
  raise ValueError(f"devices {devices!r}: {why} ({available} local device"
                   f"{'s' if available != 1 else ''}); valid counts for {k} agent"
                   f"{'s' if k != 1 else ''}: {', '.join(map(str, valid))}")


def mesh_devices(k: int, devices: int | None = None, available: int | None = None) -> int:
  """How many local devices `train` shards K agents over.

  Args:
    k: the number of agents.
    devices: a count (checked with `check_devices`), or None: all `available`
      devices when K is a multiple of their count, else one.
    available: the local device count (None: `jax.local_device_count()`).
  """
  available = jax.local_device_count() if available is None else available
  if devices is not None:
    check_devices(devices, k, available)
    return int(devices)
  return available if k % available == 0 else 1


def agent_mesh(k: int, devices: int | None = None):
  """A mesh over the agent axis of the first `mesh_devices(k, devices)` local
  devices, or None for one device (the arrays stay on the default device)."""
  n = mesh_devices(k, devices)
  if n < 2:
    return None
  return jax.sharding.Mesh(np.array(jax.local_devices()[:n]), ("agents",))


def put_agents(tree, mesh):
  """`tree`'s arrays split along their leading (agent) axis over `mesh` (None: as
  they are)."""
  if mesh is None:
    return tree
  return jax.device_put(tree, jax.sharding.NamedSharding(
      mesh, jax.sharding.PartitionSpec("agents")))


# Checkpoints ------------------------------------------------------------------------


def _checkpointer(out_dir: str):
  import orbax.checkpoint as ocp
  return ocp.CheckpointManager(
      os.path.abspath(os.path.join(out_dir, "checkpoints")),
      options=ocp.CheckpointManagerOptions(max_to_keep=2))


def _save(manager, step: int, agents, key) -> None:
  import orbax.checkpoint as ocp
  state = {"agents": agents, "key": jax.random.key_data(key),
           "step": np.asarray(step, np.int64)}
  manager.save(step, args=ocp.args.StandardSave(state), force=True)
  manager.wait_until_finished()


def _uncommitted(tree):
  """`tree`'s arrays as fresh ones are: on the default device and uncommitted.

  Orbax restores arrays committed to a device; a jitted function given committed
  arguments lowers to another program (each input carries its sharding) than the
  one fresh agents compiled, so a resumed run would miss the compilation cache and
  compile its learner again."""
  return jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), tree)


def _restore(manager, agents, key):
  import orbax.checkpoint as ocp
  step = manager.latest_step()
  if step is None:
    return None
  like = {"agents": agents, "key": jax.random.key_data(key),
          "step": np.asarray(0, np.int64)}
  state = _uncommitted(manager.restore(step, args=ocp.args.StandardRestore(like)))
  return state["agents"], jax.random.wrap_key_data(state["key"]), int(state["step"])


def save_config(cfg: TrainConfig, out_dir: str) -> None:
  """Writes `cfg` as `<out_dir>/config.json` (read back by `load_config`)."""
  with open(os.path.join(out_dir, "config.json"), "w") as f:
    json.dump(dataclasses.asdict(cfg), f, indent=1)


def load_config(out_dir: str) -> TrainConfig:
  """The `TrainConfig` a run in `out_dir` was started with."""
  path = os.path.join(out_dir, "config.json")
  if not os.path.exists(path):
    raise FileNotFoundError(f"{path} does not exist: is {out_dir!r} a `train` output folder?")
  with open(path) as f:
    raw = json.load(f)
  raw["seeds"] = tuple(raw["seeds"])
  if raw.get("egl_devices") is not None:
    raw["egl_devices"] = tuple(raw["egl_devices"])
  raw["sac"] = sac.SACConfig.from_dict(raw["sac"])
  return TrainConfig(**raw)


def init_agents(cfg: TrainConfig, obs_shape, action_size: int) -> sac.AgentState:
  """Fresh agents for `cfg.agents()`, stacked along a leading agent axis.

  Each agent is initialised by its own call of one jitted function (its seed and
  augmentation index are arguments, so one compilation serves them all): the
  K agents' initialisations vmapped into one XLA:CPU program never finished on a
  2-core machine (every thread waiting), while one agent's always does.
  """
  aug_index = {name: i for i, name in enumerate(cfg.sac.aug_names)}
  agents = [_init_agent(jnp.asarray(seed), jnp.asarray(aug_index[aug]), tuple(obs_shape),
                        int(action_size), cfg.sac)
            for seed, aug in cfg.agents()]
  return jax.tree.map(lambda *x: jnp.stack(x), *agents)


@functools.partial(jax.jit, static_argnums=(2, 3, 4))
def _init_agent(seed, aug_index, obs_shape, action_size, config):
  # Jitted: one compilation instead of op-by-op dispatch (the same values).
  return sac.init_agent(jax.random.key(seed), obs_shape, action_size, config, aug_index)


def load_run(out_dir: str, step: int | None = None):
  """The agents of a `train` run from its checkpoints.

  Args:
    out_dir: the run's output folder (with config.json and checkpoints/).
    step: which checkpoint; None = the latest.

  Returns:
    (cfg, agents with a leading agent axis in `cfg.agents()` order, step).

  Raises:
    FileNotFoundError: no config.json or no checkpoint.
  """
  import dmcr_jax
  import orbax.checkpoint as ocp
  cfg = load_config(out_dir)
  task = dmcr_jax.models.load(cfg.task)
  obs_shape = (cfg.image_size, cfg.image_size, 3 * cfg.frame_stack)
  like = {"agents": init_agents(cfg, obs_shape, task.action_size),
          "key": jax.random.key_data(jax.random.key(0)), "step": np.asarray(0, np.int64)}
  manager = _checkpointer(out_dir)
  step = manager.latest_step() if step is None else step
  if step is None:
    raise FileNotFoundError(f"no checkpoint in {out_dir}/checkpoints")
  state = _uncommitted(manager.restore(step, args=ocp.args.StandardRestore(like)))
  return cfg, state["agents"], int(state["step"])


# The loop ---------------------------------------------------------------------------


def open_run(cfg: TrainConfig, resume: bool):
  """Checks `cfg`, creates `out_dir` and writes config.json; the checkpoint manager.

  With `resume`, `cfg` must match the run's config.json but for `RESUMABLE`
  fields (`check_resume`; changed ones are written back). Nothing is created or
  written before every check has passed.

  Raises:
    ValueError: a bad config, or a resumed one that differs from the run's.
    FileExistsError: `out_dir` already holds checkpoints and `resume` is False.
    FileNotFoundError: `resume` and no run (config.json and a checkpoint) in `out_dir`.
  """
  check_config(cfg)
  if resume:
    if not os.path.exists(os.path.join(cfg.out_dir, "config.json")):
      raise FileNotFoundError(f"--resume: no run in {cfg.out_dir!r} (no config.json); "
                              "check the folder (--out)")
    check_resume(load_config(cfg.out_dir), cfg)
    if (not os.path.isdir(os.path.join(cfg.out_dir, "checkpoints"))
        or _checkpointer(cfg.out_dir).latest_step() is None):
      raise FileNotFoundError(f"--resume: no checkpoint in {cfg.out_dir}/checkpoints")
    manager = _checkpointer(cfg.out_dir)
  else:
    ckpt = os.path.join(cfg.out_dir, "checkpoints")
    if os.path.isdir(ckpt) and _checkpointer(cfg.out_dir).latest_step() is not None:
      raise FileExistsError(f"{ckpt} already holds a run (step "
                            f"{_checkpointer(cfg.out_dir).latest_step()}): pass resume=True "
                            "(--resume) to continue it, or choose another out_dir (--out)")
    os.makedirs(cfg.out_dir, exist_ok=True)
    manager = _checkpointer(cfg.out_dir)
  save_config(cfg, cfg.out_dir)
  return manager


def initial_state(cfg: TrainConfig, manager, resume: bool, obs_shape, action_size: int):
  """Fresh agents (or the checkpoint's), empty buffers, the run's key and step.

  Returns:
    (agents, buffers with leading agent axis K, key, start step).

  Raises:
    FileNotFoundError: `resume` and no checkpoint.
  """
  k, n = len(cfg.agents()), cfg.num_envs
  agents = init_agents(cfg, obs_shape, action_size)
  one = replay.init(cfg.buffer_capacity, n, obs_shape[:2] + (3,), action_size,
                    cfg.frame_stack)
  buffers = jax.tree.map(lambda x: jnp.broadcast_to(x, (k,) + x.shape), one)
  key = jax.random.key(int(cfg.seeds[0]) + 7919)
  start = 0
  if resume:
    restored = _restore(manager, agents, key)
    if restored is None:
      raise FileNotFoundError(f"--resume: no checkpoint in {cfg.out_dir}/checkpoints")
    agents, key, start = restored
  return agents, buffers, key, start


PROGRESS_FRACTION = 0.02
"""`RunLog.due` reports progress at least every this fraction of a run's steps,
whatever `log_every` says, so a run shorter than `log_every` still shows
progress."""


def progress_every(cfg: TrainConfig) -> int:
  """Steps between progress reports: `log_every`, at most `PROGRESS_FRACTION` of
  the run (at least 1)."""
  return max(1, min(cfg.log_every, int(cfg.steps * PROGRESS_FRACTION)))


class RunLog:
  """A run's host side between steps (or chunks): the episode log (log.csv), the
  progress bar (or, without one, progress lines on stderr), and the stop flag that
  SIGINT/SIGTERM set (the handlers are restored by `close`).

  A finished episode's row is flushed at once and moves the bar; `due` says when
  the loop should call `progress` (every `every` steps). Creating a RunLog
  announces the compilation that the loop's first steps trigger."""

  def __init__(self, cfg: TrainConfig, start: int, resume: bool, progress: bool):
    self.cfg, self.specs, self.start = cfg, cfg.agents(), start
    self.every = progress_every(cfg)
    self._last_line = None
    self.stop = {"signal": None}
    self._previous = {s: signal.signal(s, lambda sig, _: self.stop.update(signal=sig))
                      for s in (signal.SIGINT, signal.SIGTERM)}
    self.path = os.path.join(cfg.out_dir, "log.csv")
    self.fields = ["step", "agent", "seed", "aug", "episode_return", "wall_s",
                   "agent_steps_per_s", "critic_loss", "actor_loss", "alpha", "q"]
    if cfg.sac.algo != "sac_aug":
      self.fields.append("aux_loss")
    # Several training-look ranges: the agent's range after its augmentation.
    self.looks = ([look_label(x) for x in cfg.agent_looks()]
                  if len(parse_visual_seeds(cfg.visual_seeds)) > 1 else None)
    if self.looks is not None:
      self.fields.insert(4, "looks")
    new_log = not (resume and os.path.exists(self.path))
    self._file = open(self.path, "w" if new_log else "a", newline="")
    self._writer = csv.DictWriter(self._file, fieldnames=self.fields)
    if new_log:
      self._writer.writeheader()
    self._bar = None
    print(f"{cfg.task}: compiling the agents' act and update steps on the first steps "
          f"({jax.default_backend()}); this can take a minute or more on a CPU",
          file=sys.stderr, flush=True)
    if progress:
      from tqdm.auto import tqdm
      self._bar = tqdm(total=cfg.steps, initial=start, desc=cfg.task, unit="step")
    self.t0 = time.perf_counter()
    self.recent: list[float] = []
    self.host_s: dict[str, float] = {}
    self.env_s: dict[str, float] = {}
    self._steady_from = None  # (step, wall, host_s, env_s) where `steady` starts

  def mark_steady(self, step: int, env_s: dict[str, float]) -> None:
    """Starts the steady window of the host breakdown at `step` (once; later calls
    do nothing): the first episode end past the warm-up, when the act and update
    steps have compiled."""
    if self._steady_from is None:
      self._steady_from = (step, self.wall(), dict(self.host_s), dict(env_s))

  def steady(self, step: int) -> dict | None:
    """The loop's breakdown from `mark_steady` to `step` (summary.json's
    "steady"): transitions per agent, wall seconds, and the seconds of each host
    part and env part; None if never marked."""
    if self._steady_from is None:
      return None
    s0, w0, host0, env0 = self._steady_from
    diff = lambda now, then: {k: v - then.get(k, 0.0) for k, v in now.items()}
    return dict(steps=step - s0, wall_s=self.wall() - w0,
                host_seconds=diff(self.host_s, host0), env_seconds=diff(self.env_s, env0))

  @contextlib.contextmanager
  def timed(self, part: str):
    """Adds the seconds the block takes to `host_s[part]`: the host driver's
    breakdown of its loop (summary.json's "host_seconds")."""
    t = time.perf_counter()
    try:
      yield
    finally:
      self.host_s[part] = self.host_s.get(part, 0.0) + time.perf_counter() - t

  @property
  def stopped(self) -> bool:
    return self.stop["signal"] is not None

  def wall(self) -> float:
    return time.perf_counter() - self.t0

  def episode(self, step: int, agent: int, episode_return: float, wall: float,
              metrics: dict) -> None:
    """One finished episode of `agent` (metrics: name → (K,) latest update means;
    NaN entries, no update yet, are left out)."""
    self.recent.append(episode_return)
    row = dict(step=step, agent=agent, seed=self.specs[agent][0], aug=self.specs[agent][1],
               episode_return=episode_return, wall_s=round(wall, 2),
               agent_steps_per_s=round((step - self.start) * len(self.specs)
                                       / max(wall, 1e-9), 1))
    if self.looks is not None:
      row["looks"] = self.looks[agent]
    for f in self.fields[7 + (self.looks is not None):]:
      if f in metrics and np.isfinite(np.mean(metrics[f][agent])):
        row[f] = float(np.mean(metrics[f][agent]))
    self._writer.writerow(row)
    self._file.flush()
    if self._bar is not None and step > self._bar.n:
      self._bar.update(min(step, self.cfg.steps) - self._bar.n)

  def due(self, before: int, step: int) -> bool:
    """Whether the loop should call `progress` after moving from `before` to `step`:
    every `every` steps (`log_every`, at most 2 % of the run) and at the end."""
    return crossed(self.every, before, step) or step >= self.cfg.steps

  def progress(self, step: int) -> None:
    """Flushes the log and moves the progress bar to `step` (without a bar: prints
    a progress line to stderr)."""
    self._file.flush()
    sps = (step - self.start) * len(self.specs) / max(self.wall(), 1e-9)
    ret = f"{np.mean(self.recent[-10 * len(self.specs):]):.1f}" if self.recent else None
    if self._bar is not None:
      self._bar.update(min(step, self.cfg.steps) - self._bar.n)
      self._bar.set_postfix(**({"ret": ret} if ret else {}), sps=f"{sps:.1f}")
    elif step != self._last_line:
      print(f"{self.cfg.task}: step {min(step, self.cfg.steps):,}/{self.cfg.steps:,} "
            f"({100 * min(step, self.cfg.steps) / self.cfg.steps:.0f} %), "
            f"{sps:.1f} transitions/s, {self.wall():.0f} s"
            + (f", recent return {ret}" if ret else ""), file=sys.stderr, flush=True)
    self._last_line = step

  def close(self) -> None:
    for s, handler in self._previous.items():
      signal.signal(s, handler)
    self._file.close()
    if self._bar is not None:
      self._bar.close()


def json_safe(tree):
  """`tree` (dicts, lists, numbers) with NaN and ±inf replaced by None, so that
  `json.dump(..., allow_nan=False)` writes valid JSON (null)."""
  if isinstance(tree, dict):
    return {k: json_safe(v) for k, v in tree.items()}
  if isinstance(tree, (list, tuple)):
    return [json_safe(v) for v in tree]
  if isinstance(tree, float) and not np.isfinite(tree):
    return None
  return tree


def run_segments(out_dir: str, start: int, step: int, wall_s: float) -> list[dict]:
  """The processes that trained a run, oldest first: those of an earlier
  summary.json in `out_dir` that ended at or before `start` (a resumed run's),
  then this one ({"start", "steps", "wall_s", "device"}: its first and last
  training step, its loop's wall time, the learner's device kind)."""
  earlier = []
  path = os.path.join(out_dir, "summary.json")
  if start > 0 and os.path.exists(path):
    with open(path) as f:
      old = json.load(f)
    earlier = [s for s in old.get("segments", [dict(start=None, steps=old.get("steps"),
                                                     wall_s=old.get("wall_s"), device=None)])
               if s.get("steps") is not None and s["steps"] <= start]
  return earlier + [dict(start=start, steps=step, wall_s=wall_s,
                         device=jax.devices()[0].device_kind)]


def finish(cfg: TrainConfig, step: int, log: RunLog) -> dict:
  """The run's summary (also summary.json) and learning_curve.png.

  summary.json's `wall_s` is this process's loop time; `segments` lists every
  process of a resumed run (`run_segments`), `train_wall_s` their total."""
  specs = cfg.agents()
  segments = run_segments(cfg.out_dir, log.start, step, log.wall())
  summary = dict(task=cfg.task, seeds=list(cfg.seeds), augs=list(cfg.sac.aug_names),
                 steps=step, num_envs=cfg.num_envs, interrupted=log.stopped,
                 wall_s=log.wall(), segments=segments,
                 train_wall_s=sum(s["wall_s"] or 0.0 for s in segments),
                 **({"host_seconds": log.host_s, "env_seconds": log.env_s,
                     "steady": log.steady(step)} if log.host_s else {}),
                 final_return=plot_learning_curve(log.path, os.path.join(
                     cfg.out_dir, "learning_curve.png"), specs, log.looks))
  if log.looks is not None:
    summary["looks"] = log.looks
  with open(os.path.join(cfg.out_dir, "summary.json"), "w") as f:
    json.dump(json_safe(summary), f, indent=1, allow_nan=False)
  return summary


def crossed(every: int, before: int, step: int) -> bool:
  """Whether `step` passed a multiple of `every` since `before` (0: never)."""
  return bool(every) and step // every != before // every


def updates_from(cfg: TrainConfig, start: int) -> int:
  """Transitions per agent before which no update is owed, for a run starting at
  transition `start` (0, or a resumed run's step): `warmup_steps` past it, in
  which a fresh run acts at random and a resumed one refills its buffers (not
  checkpointed) with its restored policy."""
  return int(start) + int(cfg.warmup_steps)


def step_spec(cfg: TrainConfig, env) -> train_step.StepSpec:
  """The `dmcr_jax.train.step.StepSpec` of a run on `env` (its action bounds)."""
  on_cpu = jax.default_backend() == "cpu"
  return train_step.StepSpec(
      agents=len(cfg.agents()), num_envs=cfg.num_envs, warmup_steps=int(cfg.warmup_steps),
      utd=float(cfg.utd), sac=cfg.sac,
      agent_loop=cfg.agent_loop or ("vmap" if on_cpu else "map"),
      low=tuple(float(x) for x in env.single_action_space.low),
      high=tuple(float(x) for x in env.single_action_space.high),
      env_groups=cfg.env_groups)


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
  groups = parse_visual_seeds(cfg.visual_seeds)
  looks = (groups[0] if len(groups) == 1
           else [look for look in cfg.agent_looks() for _ in range(n)])
  return dmcr_jax.make(cfg.task, num_envs=k * n,
                       visual_seeds=looks, vary=cfg.vary,
                       frame_skip=cfg.action_repeat, frame_stack=cfg.frame_stack,
                       image_size=cfg.image_size, seed=int(cfg.seeds[0]),
                       renderer=cfg.renderer, **options)


def group_seed(seed: int, group: int) -> int:
  """The `reset` seed of env group `group` in a run reset with `seed` (group 0:
  `seed` itself, so one group resets as an ungrouped run does)."""
  if group == 0:
    return seed
  return int(np.random.SeedSequence([seed, group]).generate_state(1)[0])


def check_train_devices(cfg: TrainConfig, devices: int | None) -> None:
  """Raises ValueError, naming the valid counts, for a `devices` count `train`
  cannot shard `cfg`'s agents over (`check_devices`), or for more than one device
  with the device driver (renderer "jax", physics on the device: one device);
  None passes."""
  if devices is None:
    return
  k = len(cfg.agents())
  check_devices(devices, k, jax.local_device_count())
  if devices > 1 and cfg.device_driver():
    raise ValueError(f"devices {devices}: the device driver (renderer 'jax' with the "
                     "physics on the device) runs on one device; valid counts: 1 (or "
                     "physics 'cpu', or the pool renderer, to shard the agents)")


def one_device_note(k: int, available: int, devices: int | None, device_driver: bool
                    ) -> str | None:
  """Why a run on a host with several local devices uses only one (None when it
  uses them all, was asked for its count, or there is one device)."""
  if available < 2 or devices is not None:
    return None
  if device_driver:
    return (f"training on one of the {available} local devices: the device driver "
            "(renderer 'jax', physics on the device) runs on one")
  if k % available:
    return (f"training on one of the {available} local devices: the {k} agents are not "
            f"a multiple of {available} (shard them with a multiple of {available} agents, "
            "or limit the visible devices, e.g. CUDA_VISIBLE_DEVICES)")
  return None


def shared_frames_note(renderer: str, egl_devices, platform: str, available: int,
                       used: int) -> str | None:
  """How to keep the pool's frames off the learner's GPU, when some GPU is idle.

  None unless the pool draws its frames on MuJoCo's default EGL device
  (`egl_devices` None: neither `--egl-devices` nor `MUJOCO_EGL_DEVICE_ID` given)
  on a GPU host (`platform` "gpu") whose learner uses `used` of its `available`
  local devices and leaves at least one idle. That EGL device is usually the
  learner's first GPU, where the frames slow the updates.
  """
  if renderer != "pool" or egl_devices is not None or platform != "gpu" or used >= available:
    return None
  return (f"the pool draws its frames on the first EGL device, usually the learner's "
          f"GPU, where they slow the updates; {available - used} of the {available} GPUs "
          f"stay idle: --egl-devices {used} draws the frames on the next one (EGL's "
          "device order, usually the GPUs')")


def physics_before_updates(physics_device: str | None) -> bool:
  """Whether the host driver dispatches a step's physics before its updates.

  True when they share a device (`physics_device` None, or a CPU backend): the
  physics then leaves that device's queue first. Otherwise the updates are
  launched first, before the actions are waited for, so that the device runs
  them right after `act` while the host steps the physics. Either order computes
  the same values.
  """
  return physics_device is None or jax.default_backend() == "cpu"


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True,
          devices: int | None = None) -> dict:
  """Trains `len(cfg.agents())` agents; returns a summary (also written as JSON).

  The agent axis is sharded over `mesh_devices(K, devices)` local devices
  (`devices` None: all of them when K is a multiple of their count, else one;
  the device driver below always runs on one).

  Writes `<out_dir>/config.json`, `<out_dir>/log.csv` (one row per finished
  episode: step, agent, seed, augmentation, return, wall time, transitions/s and
  the latest update metrics), `<out_dir>/learning_curve.png`,
  `<out_dir>/summary.json` (with the host driver also the seconds its loop spent
  in each part, "host_seconds", and in the env's parts, "env_seconds", over the
  whole run and, under "steady", from the first episode end past the warm-up) and the
  checkpoints. With the JAX renderer and the
  physics on the learner's device the run is `dmcr_jax.train.device_loop.train` (same
  outputs).

  Raises:
    ValueError: a bad config or device count (before anything is built).
    FileExistsError: `out_dir` already holds checkpoints and `resume` is False.
    FileNotFoundError: `resume` and no checkpoint.
  """
  check_config(cfg)
  physics_device = cfg.physics_device()
  check_train_devices(cfg, devices)
  note = one_device_note(len(cfg.agents()), jax.local_device_count(), devices,
                         cfg.device_driver())
  frames_note = shared_frames_note(
      cfg.renderer, cfg.egl_devices or os.environ.get("MUJOCO_EGL_DEVICE_ID"),
      jax.default_backend(), jax.local_device_count(), mesh_devices(len(cfg.agents()), devices))
  for line in (note, frames_note):
    if line:
      print(f"{cfg.task}: {line}", file=sys.stderr, flush=True)
  if cfg.device_driver():
    from dmcr_jax.train import device_loop
    return device_loop.train(cfg, resume=resume, progress=progress)
  manager = open_run(cfg, resume)
  groups = cfg.env_groups
  k, n = len(cfg.agents()), cfg.num_envs // groups
  extra = dict(obs_on_device=True) if cfg.renderer == "jax" else {}
  with contextlib.ExitStack() as stack:
    envs = [stack.enter_context(make_env(cfg, n, physics_device=physics_device,
                                         physics_workers=cfg.physics_pool_workers(), **extra))
            for _ in range(groups)]
    obs_shape = envs[0].single_observation_space.shape
    mesh = agent_mesh(k, devices)
    on_cpu = jax.default_backend() == "cpu"
    spec = step_spec(cfg, envs[0])
    agents, buffers, key, start = initial_state(cfg, manager, resume, obs_shape,
                                                envs[0].task.action_size)
    learner = train_step.init_learner(put_agents(agents, mesh), put_agents(buffers, mesh),
                                      key, start, spec)
    put = lambda x: put_agents(jnp.asarray(x), mesh)
    physics_first = physics_before_updates(physics_device)
    first_update = updates_from(cfg, start)

    def learn(learner, owed, ready, step):
      """`dmcr_jax.train.step.learn` with the pairs planned at `step` (host counters)."""
      owed, ready, pairs = train_step.plan_updates(
          owed, ready, step, lambda: train_step.can_sample_jit(learner.buffers), spec,
          updates_from=first_update)
      learner = train_step.learn_jit(learner, pairs=int(pairs), spec=spec, mesh=mesh,
                                     unroll=on_cpu)
      return learner, owed, ready

    log = RunLog(cfg, start, resume, progress)

    def settled(learning, current):
      """`learn`'s (learner, owed, ready) once the launch of the updates in flight
      is done (timed as "learn"), or `current` when none are in flight."""
      if learning is None:
        return current
      with log.timed("learn"):
        return learning.result()

    env_seconds = lambda: {part: sum(env.timings[part] for env in envs)
                           for part in envs[0].timing_parts}
    owed, ready = np.float32(0), False
    # Per group: its current observations and episode-start flags; `in_flight`
    # holds what `store` needs of a group stepping (dispatched, not yet waited).
    obs, first, in_flight = [None] * groups, [None] * groups, {}
    # The launch of the latest updates, a future of (learner, owed, ready).
    updates, learning = stack.enter_context(ThreadPoolExecutor(1, "updates")), None
    try:
      for g, env in enumerate(envs):
        obs[g], info = env.reset(seed=group_seed(int(cfg.seeds[0]) + start, g))
        first[g] = info["episode_step"] == 0
      acted = stored = start  # transitions per agent acted on / stored
      g = 0
      while True:
        acting = acted < cfg.steps and not log.stopped
        if acting:  # group g acts and steps; the updates owed run meanwhile
          # (env groups: updates still in flight if no group was stored since)
          (learner, owed, ready), learning = settled(learning, (learner, owed, ready)), None
          with log.timed("act"):
            o, f = put(obs[g]), put(first[g])
            learner, action, env_action = train_step.act_jit(learner, o, spec=spec,
                                                             mesh=mesh)
          # The updates owed are launched from another thread (launching their
          # kernels holds a thread for a large part of their run) while this one
          # steps the env. Physics on the updates' device is dispatched first (it
          # then leaves the queue first, and the host renders while the updates
          # run); else the updates are launched before the actions are waited
          # for, so that they queue right behind `act` on the device.
          if not physics_first:
            learning = updates.submit(learn, learner, owed, ready, acted)
          with log.timed("act"):  # waits for what the device runs before `act`
            env_action = np.asarray(env_action)
          with log.timed("env_step_async"):
            envs[g].step_async(env_action)
          if physics_first:
            learning = updates.submit(learn, learner, owed, ready, acted)
          in_flight[g] = (o, f, action)
          acted += n
        g = (g + 1) % groups  # the group stepped longest ago finishes and acts next
        if g in in_flight:
          with log.timed("env_step_wait"):
            next_obs, reward, _, truncated, info = envs[g].step_wait()
          o, f, action = in_flight.pop(g)
          # The updates must be launched: they read the buffers `store` writes.
          (learner, owed, ready), learning = settled(learning, (learner, owed, ready)), None
          with log.timed("store"):
            learner = train_step.store_jit(learner, o, f, action, put(reward), spec=spec,
                                           mesh=mesh, group=g)
          before, stored = stored, stored + n
          obs[g], first[g] = next_obs, info["episode_step"] == 0
          wall = log.wall()
          metrics = jax.device_get(learner.metrics) if truncated.any() else {}
          if truncated.any() and stored > cfg.warmup_steps:
            log.mark_steady(stored, env_seconds())
          for i in np.flatnonzero(truncated):
            log.episode(stored, int(i // n), float(info["episode_return"][i]), wall,
                        metrics)
          if log.due(before, stored):
            log.progress(stored)
          if crossed(cfg.checkpoint_every, before, stored):
            _save(manager, stored, learner.agents, learner.key)
        if not acting and not in_flight:
          break
      log.env_s = env_seconds()
      if manager.latest_step() != stored:
        _save(manager, stored, learner.agents, learner.key)
    finally:
      log.close()
  return finish(cfg, stored, log)


def agent_label(seed: int, aug: str, augs, looks: str | None = None) -> str:
  """How logs and plots name an agent: "seed 0", or "seed 0, cj+drq" when several
  augmentations are trained (then ", levels:10", its training looks, when given)."""
  label = f"seed {seed}" if len(augs) == 1 else f"seed {seed}, {aug}"
  return label if looks is None else f"{label}, {looks}"


def plot_learning_curve(log_path: str, png_path: str, specs, looks=None) -> dict:
  """Episode return against training step per agent (PNG).

  Episodes that end at the same step (the agent's N envs) are averaged into one
  point.

  Args:
    log_path: the run's log.csv.
    png_path: where the plot goes.
    specs: (seed, augmentation) per agent (`TrainConfig.agents`).
    looks: each agent's training looks (`look_label`) when the run has several
      ranges, else None.

  Returns:
    {agent label: mean return of the agent's episodes that ended last}.
  """
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  with open(log_path) as f:
    rows = list(csv.DictReader(f))
  augs = sorted({aug for _, aug in specs})
  fig, ax = plt.subplots(figsize=(6, 3.5))
  last = {}
  for a, (seed, aug) in enumerate(specs):
    look = None if looks is None else looks[a]
    by_step: dict[int, list[float]] = {}
    for r in rows:
      if int(r["agent"]) == a:
        by_step.setdefault(int(r["step"]), []).append(float(r["episode_return"]))
    if by_step:
      steps = sorted(by_step)
      means = [float(np.mean(by_step[t])) for t in steps]
      label = agent_label(seed, aug, augs, look)
      # Markers: a run with one finished episode per agent still shows its point.
      ax.plot(steps, means, marker="o", ms=4, label=label)
      last[label] = means[-1]
  ax.set_xlabel("training step (transitions per agent)")
  ax.set_ylabel("episode return")
  if last:
    ax.legend()
  fig.tight_layout()
  fig.savefig(png_path, dpi=100)
  plt.close(fig)
  return last
