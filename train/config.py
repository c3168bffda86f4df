"""A training run's configuration: `TrainConfig`, its checks, and the plan it resolves to.

`TrainConfig` says what a run does (every field has the paper's default where it
has one); `resolve(cfg, devices)` checks it once (`check_config`, the device
count) and fixes everything that follows from it and the machine into a
`Plan`: the agents and their training looks (`visual_seeds` parsed once), the
driver (host env or device scan), where the physics and the frames run, the
physics workers, how the agents' updates are batched and over how many devices.
`dmcr_jax.train.loop.train` runs a plan.

Where things run (the resolved backend; `TrainConfig.renderer`, `physics`,
`physics_workers`):
- frames: "pool" (MuJoCo renderers in CPU worker processes, the exact
  dm_control look) or "jax" (the JAX ray caster, on the learner's device);
- physics: "auto" steps small batches (K·N ≤ `CPU_PHYSICS_MAX_ENVS`) on the host
  CPU when the learner runs on an accelerator (a few dozen envs step there faster
  than an accelerator's launch latency allows, beside the updates), larger ones
  on the accelerator; on the host CPU it steps in `physics_workers` processes
  (`dmcr_jax.physics_pool`; default `default_physics_workers`);
- the driver: the device driver (`dmcr_jax.train.device_loop`: chunks of
  training as one XLA call each) for the ray caster with the physics on the
  device, else the host driver (`dmcr_jax.train.loop`).

Agents: one per (training looks, augmentation, seed): the look groups of
`visual_seeds` × `sac.aug_names` × `seeds` (e.g. ``aug="drq,cj+drq"`` with 3
seeds trains 6 agents; ``visual_seeds="levels:1,10,100"`` makes that 18, each
agent's envs drawing their looks from its own range). An agent's network init
depends only on its seed, so augmentations and ranges are compared from the
same start.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os

import jax
import numpy as np

from dmcr_jax.checks import positive_int
from dmcr_jax.env_checks import (RENDERERS, check_physics_workers,  # noqa: F401 (RENDERERS: CLIs)
                                 check_renderer_name)
from dmcr_jax.visuals.levels import TEST_SEEDS, TRAIN_SEEDS, SeedRange
from dmcr_jax.train import devices as devs
from dmcr_jax.train import sac

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
             "egl_devices", "eval_every", "eval_looks", "eval_dynamics",
             "eval_train_episodes", "eval_conditions", "eval_renderer", "loggers")
"""`TrainConfig` fields a resumed run may change (a larger `steps` extends it; the
others change neither the agents nor the data); `out_dir` may name the folder
differently. Every other field must equal the run's config.json."""
EVAL_RENDERERS = ("jax", "pool")
"""What `TrainConfig.eval_renderer` accepts."""


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
    moving, intensity: factors that move within each episode ("none", "all" or
      names of `dmcr_jax.visuals.moving.MOVING_FACTORS`, comma-separated) and how
      far, in [0, 1] (`dmcr_jax.make`'s `moving`, `intensity`; docs/moving.md).
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
    renderer: "pool" (the CPU render pool) or "jax" (the JAX ray caster; module
      doc).
    chunk_steps: with the device driver (renderer "jax", physics on the device),
      vector steps (of all envs) per XLA call; logs, checkpoints and the stop
      flag are handled between chunks.
    physics: where the physics steps: "auto", "cpu" or "device" (module doc).
    physics_workers: with the physics on the host CPU, processes that step it
      (`dmcr_jax.physics_pool`; 0: the training process; None:
      `default_physics_workers`).
    out_dir: where the CSV, the PNG and the checkpoints go.
    sac: the learner's hyperparameters.
    eval_every: training steps per agent between evaluations during training
      (`dmcr_jax.train.eval_curve`: a reduced protocol on the current agents,
      also at the last step; 0 or None: none).
    eval_looks: held-out looks per condition of those evaluations.
    eval_dynamics: initial states per held-out look.
    eval_train_episodes: episodes at each agent's training looks (the train
      return and E_G), at most eval_looks · eval_dynamics.
    eval_conditions: the conditions evaluated (None: every one that applies,
      `dmcr_jax.protocol.conditions_for`).
    eval_renderer: "jax" (the ray caster) or "pool" (MuJoCo's pixels).
    loggers: where the curves go (`dmcr_jax.train.loggers.LOGGERS`): "csv" (log.csv,
      always written), "tensorboard" (event files), "wandb" (Weights & Biases).
  """
  task: str = "cartpole-balance"
  steps: int = 50_000
  seeds: tuple[int, ...] = (0,)
  num_envs: int = 32
  action_repeat: int | None = None
  visual_seeds: int | str = 0
  vary: str = "all"
  moving: str = "none"
  intensity: float = 0.0
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
  physics_workers: int | None = None
  sac: sac.SACConfig = sac.SACConfig()
  eval_every: int = 0
  eval_looks: int = 10
  eval_dynamics: int = 1
  eval_train_episodes: int = 10
  eval_conditions: tuple[str, ...] | None = None
  eval_renderer: str = "jax"
  loggers: tuple[str, ...] = ("csv",)

  def __post_init__(self):
    if self.image_size is None:
      size = self.sac.curl_crop + 16 if self.sac.algo == "curl" else 84
      object.__setattr__(self, "image_size", size)

  @property
  def looks(self) -> tuple[int | SeedRange, ...]:
    """`visual_seeds` parsed (`parse_visual_seeds`, once per value): the training
    looks of each look group."""
    try:
      return _parsed_visual_seeds(self.visual_seeds)
    except TypeError:  # unhashable: parsed (and refused) as it is
      return parse_visual_seeds(self.visual_seeds)

  def agents(self) -> list[tuple[int, str]]:
    """(seed, augmentation) of each agent, in the order of the agent axis (look
    groups outermost, then augmentations, then seeds; `agent_looks`)."""
    return [(seed, aug) for _ in self.looks for aug in self.sac.aug_names
            for seed in self.seeds]

  def agent_looks(self) -> list[int | SeedRange]:
    """The training looks of each agent (a fixed seed or a `SeedRange`), in the
    order of the agent axis."""
    per_group = len(self.sac.aug_names) * len(self.seeds)
    return [look for look in self.looks for _ in range(per_group)]


ALL_LEVELS = "all"
"""The count `levels:` takes for the whole training range (`TRAIN_SEEDS`)."""
VISUAL_SEEDS_FORM = (
    "an int in [0, 2**31 - 1] (one fixed look; 0 = dm_control's) or "
    f"'levels:<n>[,<n>...]': distinct ints 1 <= n <= {len(TRAIN_SEEDS)} (2**30) or "
    f"'{ALL_LEVELS}', one agent per range of the first n seeds (levels:1 = seed 0 only, "
    "dm_control's look), e.g. levels:1,10,100,1000,10000,all")
"""The valid forms of `TrainConfig.visual_seeds` (named by its errors)."""


def default_physics_workers(cores: int, backend: str) -> int:
  """Physics worker processes when `TrainConfig.physics_workers` is None and the
  physics steps on the host CPU.

  Args:
    cores: the host's CPU cores.
    backend: JAX's default backend, where the learner runs ("cpu", "gpu", "tpu").

  Returns:
    Half the cores, at most `PHYSICS_WORKERS_MAX`, when the learner runs on an
    accelerator (the other half render and launch the updates); 0, the physics in
    the training process, when that leaves fewer than two or when the learner
    itself runs on the CPU's cores.
  """
  if backend == "cpu":
    return 0
  workers = min(PHYSICS_WORKERS_MAX, int(cores) // 2)
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


@functools.lru_cache(maxsize=64, typed=True)
def _parsed_visual_seeds(value) -> tuple[int | SeedRange, ...]:
  return parse_visual_seeds(value)


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
  from dmcr_jax.visuals.moving import check_moving
  from dmcr_jax.visuals.tiled import check_quality
  domain, _ = models.split_name(cfg.task)
  check_vary(domain, cfg.vary)
  moving, _ = check_moving(domain, cfg.moving, cfg.intensity)
  if moving and cfg.intensity == 0:
    raise ValueError(f"moving {cfg.moving!r} needs an intensity in (0, 1] (intensity 0 is "
                     "static looks; pass moving 'none' for those)")
  check_quality(cfg.quality)
  cfg.looks  # noqa: B018 - parsed (and checked) once per config
  for name in ("steps", "num_envs", "buffer_capacity", "image_size", "frame_stack",
               "log_every"):
    positive_int(name, getattr(cfg, name))
  if (not cfg.seeds or len(set(cfg.seeds)) != len(cfg.seeds)
      or any(isinstance(s, bool) or not isinstance(s, (int, np.integer))
             or not 0 <= s < 2**31 for s in cfg.seeds)):
    raise ValueError(f"seeds must be distinct ints in [0, 2**31), got {cfg.seeds!r}")
  if cfg.workers is not None:
    positive_int("workers", cfg.workers)
  # The env's own check; "cpu" because the workers only apply there.
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
  if cfg.agent_loop is not None and cfg.agent_loop not in AGENT_LOOPS:
    raise ValueError(f"agent_loop must be one of {', '.join(AGENT_LOOPS)}, got "
                     f"{cfg.agent_loop!r}")
  check_eval(cfg)
  from dmcr_jax.train.loggers import check_loggers
  check_loggers(cfg.loggers)
  if cfg.image_size < 16:
    raise ValueError(f"image_size must be >= 16 for the encoder, got {cfg.image_size}")
  if cfg.sac.algo == "curl" and cfg.image_size <= cfg.sac.curl_crop:
    raise ValueError(f"CURL crops {cfg.sac.curl_crop}-pixel windows: image_size must be "
                     f"> curl_crop ({cfg.sac.curl_crop}; CURL renders "
                     f"{cfg.sac.curl_crop + 16}), got {cfg.image_size}")


def check_eval(cfg: TrainConfig) -> None:
  """ValueError naming the problem with the evaluation-during-training fields
  (`eval_every` and the reduced protocol's options)."""
  from dmcr_jax.protocol_plan import conditions_for
  if cfg.eval_every is not None and (
      isinstance(cfg.eval_every, bool) or not isinstance(cfg.eval_every, (int, np.integer))
      or cfg.eval_every < 0):
    raise ValueError(f"eval_every must be an int >= 0 (0 or None: no evaluation during "
                     f"training), got {cfg.eval_every!r}")
  for name in ("eval_looks", "eval_dynamics", "eval_train_episodes"):
    positive_int(name, getattr(cfg, name))
  if cfg.eval_train_episodes > cfg.eval_looks * cfg.eval_dynamics:
    raise ValueError(f"eval_train_episodes ({cfg.eval_train_episodes}) must be at most "
                     f"eval_looks · eval_dynamics = {cfg.eval_looks * cfg.eval_dynamics}")
  if cfg.eval_renderer not in EVAL_RENDERERS:
    raise ValueError(f"eval_renderer must be one of {', '.join(EVAL_RENDERERS)}, got "
                     f"{cfg.eval_renderer!r}")
  if cfg.eval_conditions is not None:
    valid = conditions_for(cfg.task)
    given = tuple(cfg.eval_conditions)
    bad = [c for c in given if c not in valid]
    if bad or not given or len(set(given)) != len(given):
      why = (f"{', '.join(map(repr, bad))} not valid" if bad else
             "empty" if not given else "a condition named twice")
      raise ValueError(f"eval_conditions {','.join(given)!r}: {why} for {cfg.task}; valid: "
                       f"{', '.join(valid)} (comma-separated, each once)")


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


def save_config(cfg: TrainConfig, out_dir: str) -> None:
  """Writes `cfg` as `<out_dir>/config.json` (read back by `load_config`)."""
  with open(os.path.join(out_dir, "config.json"), "w") as f:
    json.dump(dataclasses.asdict(cfg), f, indent=1)


def load_config(out_dir: str) -> TrainConfig:
  """The `TrainConfig` a run in `out_dir` was started with."""
  path = os.path.join(out_dir, "config.json")
  if not os.path.exists(path):
    raise FileNotFoundError(f"{path} does not exist: is {out_dir!r} a `train` output folder?")
  try:
    with open(path) as f:
      raw = json.load(f)
  except ValueError as e:
    raise ValueError(f"{path} is not a readable run config (damaged JSON: {e}): restore it "
                     "from a copy, or start a new run in another folder") from None
  raw["seeds"] = tuple(raw["seeds"])
  for name in ("egl_devices", "eval_conditions", "loggers"):
    if raw.get(name) is not None:
      raw[name] = tuple(raw[name])
  # Fields a later version removed (execution modes that did not pay) are dropped.
  raw["sac"] = sac.SACConfig.from_dict(raw["sac"])
  known = {f.name for f in dataclasses.fields(TrainConfig)}
  return TrainConfig(**{k: v for k, v in raw.items() if k in known})


# The plan ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Plan:
  """A checked `TrainConfig` with what follows from it on this machine (`resolve`).

  Attributes:
    cfg: the config.
    agents: (seed, augmentation) per agent, in the order of the agent axis.
    agent_looks: each agent's training looks (a seed or a `SeedRange`).
    look_labels: each agent's `look_label` when the run has several look ranges,
      else None (logs and plots then name agents by seed and augmentation only).
    device_driver: the device driver (the ray caster with the physics on the
      device; one device) rather than the host driver.
    physics_device: `dmcr_jax.make`'s `physics_device` ("cpu", or None: the
      learner's device).
    physics_workers: physics worker processes (0: in the training process).
    agent_loop: "vmap" or "map".
    devices: local devices the agent axis is sharded over (1 with the device
      driver).
    notes: lines `train` prints before it starts (why devices stay idle, where
      the pool's frames go).
  """
  cfg: TrainConfig
  agents: tuple[tuple[int, str], ...]
  agent_looks: tuple
  look_labels: tuple[str, ...] | None
  device_driver: bool
  physics_device: str | None
  physics_workers: int
  agent_loop: str
  devices: int
  notes: tuple[str, ...] = ()

  def describe(self) -> str:
    """Where the run's parts go, in words (`train` prints it as it starts)."""
    frames = ("the JAX ray caster" if self.cfg.renderer == "jax"
              else f"the render pool ({self.cfg.quality})")
    physics = ("on the learner's device" if self.physics_device is None else
               f"on the host CPU in {self.physics_workers} worker processes"
               if self.physics_workers else "on the host CPU in this process")
    driver = ("the device driver, chunks of training as one XLA call" if self.device_driver
              else f"the host driver, the agents on {self.devices} device"
              + ("s" if self.devices > 1 else ""))
    return (f"{len(self.agents)} agent{'s' if len(self.agents) > 1 else ''} × "
            f"{self.cfg.num_envs} envs; frames by {frames}, physics {physics}; {driver}")


def resolve(cfg: TrainConfig, devices: int | None = None) -> Plan:
  """Checks `cfg` (`check_config`) and `devices` once and resolves the run's `Plan`.

  Args:
    cfg: the config.
    devices: local devices to shard the agents over (None: all of them when the
      agent count is a multiple of theirs, else one; `devices.mesh_devices`).

  Raises:
    ValueError: naming the problem, before anything is built.
  """
  check_config(cfg)
  agents = tuple(cfg.agents())
  k = len(agents)
  backend = jax.default_backend()
  on_host = cfg.physics == "cpu" or (cfg.physics == "auto" and backend != "cpu"
                                     and k * cfg.num_envs <= CPU_PHYSICS_MAX_ENVS)
  physics_device = "cpu" if on_host else None
  workers = 0
  if on_host:
    workers = (default_physics_workers(os.cpu_count() or 1, backend)
               if cfg.physics_workers is None else int(cfg.physics_workers))
  device_driver = cfg.renderer == "jax" and physics_device is None
  available = jax.local_device_count()
  if devices is not None:
    devs.check_devices(devices, k, available)
    if devices > 1 and device_driver:
      raise ValueError(f"devices {devices}: the device driver (renderer 'jax' with the "
                       "physics on the device) runs on one device; valid counts: 1 (or "
                       "physics 'cpu', or the pool renderer, to shard the agents)")
  used = 1 if device_driver else devs.mesh_devices(k, devices, available)
  notes = (devs.one_device_note(k, available, devices, device_driver),
           devs.shared_frames_note(cfg.renderer,
                                   cfg.egl_devices or os.environ.get("MUJOCO_EGL_DEVICE_ID"),
                                   backend, available, used))
  looks = tuple(cfg.agent_looks())
  return Plan(cfg=cfg, agents=agents, agent_looks=looks,
              look_labels=tuple(map(look_label, looks)) if len(cfg.looks) > 1 else None,
              device_driver=device_driver, physics_device=physics_device,
              physics_workers=workers,
              agent_loop=cfg.agent_loop or ("vmap" if backend == "cpu" else "map"),
              devices=used, notes=tuple(n for n in notes if n))

