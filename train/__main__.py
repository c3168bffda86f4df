"""`train` / `python -m dmcr_jax.train`: train SAC+AUG, CURL or SAC+AE agents on a DMCR task from pixels.

    dmcr-train --task cartpole-balance --steps 50000 --seeds 0,1,2 --aug drq
    dmcr-train --task cartpole-balance --algo curl      # or --algo sac_ae

One agent per seed and augmentation (`--aug drq,cj+drq --seeds 0,1,2`: 6 agents,
trained together in one process), and per training-look range
(`--visual-seeds levels:1,10,100,1000,10000,all`: one agent per range of the
first n visual seeds, each drawing a new look at every reset; levels:1 is seed 0,
dm_control's look; ranges multiply with the seeds and augmentations). `--steps` counts the paper's training steps
(transitions stored) per agent; with `--num-envs N` an agent collects N per step.

Arguments are checked before anything is compiled. Outputs go to `--out`
(default `runs/<task>-<aug>`): log.csv, learning_curve.png, summary.json and
orbax checkpoints; `--resume` continues from the latest checkpoint (see
`dmcr_jax.train.loop` for what is restored: agents, step and RNG key, not the buffers).

Where things run is resolved once per run (`dmcr_jax.train.config.resolve`):
`--renderer jax` renders with the JAX ray caster on the device; with the physics
on the device too (`--physics device`, or `auto` past 64 envs) training runs in
chunks of `--chunk-steps` vector steps, each one XLA call (the device driver,
`dmcr_jax.train.device_loop`). `--physics auto` (the default) steps small batches'
physics on the host CPU in `--physics-workers` processes, beside the learner's
updates on the accelerator (the host driver, `dmcr_jax.train.loop`). `--quality`,
`--workers` and `--egl-devices` belong to the default CPU render pool
(`--renderer pool`).

`--aug` also takes your own augmentation as `package.module:function` (e.g.
`examples.augmentations:hue_rotation+drq`, a function of ONE uint8 sample, see
`dmcr_jax.augment.from_function`): it is imported, from the current directory
first, and must pass `dmcr_jax.augment.check` at the run's image size before
anything is compiled.

`--algo` picks the learner (`dmcr_jax.train.sac.ALGOS`); unset options take its defaults
(`dmcr_jax.train.sac.ALGO_DEFAULTS`: CURL renders at 100 and crops to 84 and takes no
`--aug`; SAC+AE uses batch 128 and no augmentation unless `--aug` names one).
CURL on cheetah uses learning rate 2e-4 for the critic, actor and encoder (the
paper's Table 6) unless `--lr` is given.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

from dmcr_jax.checks import positive_int
from dmcr_jax.train import compile_cache
from dmcr_jax.train.config import (AGENT_LOOPS, CPU_PHYSICS_MAX_ENVS, EVAL_RENDERERS, PHYSICS,
                                   PHYSICS_WORKERS_MAX, RENDERERS, RESUMABLE, TrainConfig,
                                   egl_devices_arg, load_config, resolve)
from dmcr_jax.train.loggers import parse_loggers
from dmcr_jax.train.loop import train
from dmcr_jax.train.runlog import progress_every
from dmcr_jax.train.sac import ALGOS, COMPUTE_DTYPES, SACConfig


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
  """argparse's help with "(default: …)" after every option whose default is a value
  (None and off switches say nothing: their help says what happens)."""

  def _get_help_string(self, action):
    if action.default is None or action.default is False:
      return action.help
    return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
  """The `train` command line (defaults from `TrainConfig` and `SACConfig`)."""
  from dmcr_jax.visuals.tiled import QUALITY
  d, s = TrainConfig(), SACConfig()
  p = argparse.ArgumentParser(prog="dmcr-train", description=__doc__.splitlines()[0],
                              formatter_class=HelpFormatter)
  p.add_argument("--task", default=d.task, help="a DMCR task")
  p.add_argument("--algo", default=s.algo, choices=ALGOS, help="learner")
  p.add_argument("--aug", default=None,
                 help="augmentation name, e.g. drq, cj+drq, nr+drq, or your own as "
                      "package.module:function (e.g. examples.augmentations:"
                      "hue_rotation+drq); comma-separated names train one agent per "
                      "name and seed (default: drq for sac_aug, none for sac_ae; curl "
                      "takes none)")
  p.add_argument("--lr", type=float, default=None,
                 help="learning rate of the critic, actor and encoder (default 1e-3; "
                      "2e-4 for curl on cheetah)")
  p.add_argument("--steps", type=int, default=d.steps,
                 help="training steps (transitions) per agent; with --resume, a larger "
                      "value extends the run")
  p.add_argument("--seeds", type=seeds_arg, default=",".join(map(str, d.seeds)),
                 metavar="S[,S…]", help="comma-separated ints: one agent per seed")
  p.add_argument("--num-envs", type=int, default=d.num_envs, help="envs per agent")
  p.add_argument("--visual-seeds", default=str(d.visual_seeds),
                 help="an int (fixed look, 0 = dm_control's) or levels:<n>[,<n>...] "
                      "(few-shot: one agent per range of the first n seeds; 'all' = "
                      "the whole training range; levels:1 = seed 0)")
  p.add_argument("--vary", default=d.vary,
                 help="factors the visual seeds change: all, none or a comma-separated "
                      "subset of camera, light, body, target, floor, background, "
                      "reflectance")
  p.add_argument("--moving", default=d.moving,
                 help="factors that move within each episode: none, all or a "
                      "comma-separated subset of camera, light, body, floor, background "
                      "(docs/moving.md)")
  p.add_argument("--intensity", type=float, default=d.intensity,
                 help="how far --moving factors move, in [0, 1] (DCS's difficulty: .1, "
                      ".2, .3)")
  p.add_argument("--action-repeat", type=int, default=None,
                 help="default: the paper's Table 4 value for the task")
  p.add_argument("--utd", type=float, default=d.utd, help="updates per training step")
  p.add_argument("--warmup-steps", type=int, default=d.warmup_steps,
                 help="random-action training steps per agent before learning")
  p.add_argument("--buffer-capacity", type=int, default=d.buffer_capacity,
                 help="replay buffer size, transitions per agent")
  p.add_argument("--batch-size", type=int, default=None,
                 help="default: 256 (128 for sac_ae)")
  p.add_argument("--image-size", type=int, default=None,
                 help="rendered side (default: 84; 100 for curl)")
  p.add_argument("--renderer", default=d.renderer, metavar="{" + ",".join(RENDERERS) + "}",
                 help="where frames are drawn: pool (MuJoCo in CPU worker processes, "
                      "dm_control's exact look; on a host with a spare GPU, --egl-devices "
                      "keeps its frames off the learner's) or jax (the JAX ray caster on "
                      "the learner's device: the faster training on one GPU, "
                      "benchmarks/results/README.md)")
  p.add_argument("--physics", default=d.physics, choices=PHYSICS,
                 help="where the physics steps: auto (the host CPU, in --physics-workers "
                      f"processes, for at most {CPU_PHYSICS_MAX_ENVS} envs in all when the "
                      "learner runs on an accelerator, which there trains faster than "
                      "physics on the accelerator; else the device, where --renderer jax "
                      "runs --chunk-steps of training as one XLA call), cpu or device")
  p.add_argument("--physics-workers", type=int, default=d.physics_workers,
                 help="with the physics on the host CPU (--physics auto on an "
                      "accelerator, or cpu): processes that step it, each a slice of the "
                      "envs (0: in the training process; default: half the cores, at most "
                      f"{PHYSICS_WORKERS_MAX}, when the learner is on an accelerator, where "
                      "they pay; else 0)")
  p.add_argument("--chunk-steps", type=int, default=d.chunk_steps,
                 help="--renderer jax with the physics on the device: vector steps per "
                      "device call")
  p.add_argument("--quality", default=d.quality, metavar="{" + ",".join(QUALITY) + "}",
                 help="render preset (--renderer pool)")
  p.add_argument("--workers", type=int, default=None,
                 help="render workers (--renderer pool; default: one per core, at most 16)")
  p.add_argument("--egl-devices", type=egl_devices_arg, default=None, metavar="D[,D…]",
                 help="EGL device indices the render workers are spread over (--renderer "
                      "pool; default: MuJoCo's, MUJOCO_EGL_DEVICE_ID or the first), e.g. "
                      "a GPU other than the learner's")
  p.add_argument("--dtype", default=s.compute_dtype,
                 metavar="{" + ",".join(COMPUTE_DTYPES) + "}",
                 help="compute dtype of the networks")
  p.add_argument("--agent-loop", default=d.agent_loop, metavar="{" + ",".join(AGENT_LOOPS) + "}",
                 help="how K agents' updates are batched (default: map on accelerators, "
                      "vmap on CPU)")
  p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every,
                 help="steps between checkpoints (0: only at the end and on Ctrl-C)")
  p.add_argument("--log-every", type=int, default=d.log_every,
                 help="steps between progress updates; `train` makes it at most 2%% of "
                      "--steps (recorded in config.json)")
  p.add_argument("--eval-every", type=int, default=d.eval_every,
                 help="training steps per agent between evaluations during training: a "
                      "reduced zero-shot protocol on the current agents (also at the last "
                      "step), written as eval_curve.csv and eval_curve.png; 0: none")
  p.add_argument("--eval-looks", type=int, default=d.eval_looks,
                 help="--eval-every: held-out looks per condition")
  p.add_argument("--eval-dynamics", type=int, default=d.eval_dynamics,
                 help="--eval-every: initial states per held-out look")
  p.add_argument("--eval-train-episodes", type=int, default=d.eval_train_episodes,
                 help="--eval-every: episodes at the training looks (train return, E_G)")
  p.add_argument("--eval-conditions", type=conditions_arg, default=None, metavar="C[,C…]",
                 help="--eval-every: comma-separated conditions, e.g. none,all (default: "
                      "every one that applies to the task)")
  p.add_argument("--eval-renderer", default=d.eval_renderer, choices=EVAL_RENDERERS,
                 help="--eval-every: jax (the ray caster) or pool (MuJoCo's pixels)")
  p.add_argument("--logger", "--loggers", dest="loggers", type=loggers_arg, default="csv",
                 metavar="L[,L…]",
                 help="where the curves go, comma-separated: csv (log.csv, always written), "
                      "tensorboard (event files in OUT/tensorboard, one run per agent; "
                      "needs tensorboardX), wandb (Weights & Biases, one run per agent, "
                      "offline without an API key; needs wandb)")
  p.add_argument("--out", default=None, help="output folder (default: runs/<task>-<aug>)")
  p.add_argument("--resume", action="store_true",
                 help="continue the run in --out from its latest checkpoint, with the "
                      "settings in its config.json (flags that differ from them are "
                      f"refused, except {', '.join('--' + f.replace('_', '-') for f in RESUMABLE)})")
  p.add_argument("--no-progress", action="store_true",
                 help="no progress bar (progress lines on stderr instead)")
  compile_cache.add_arguments(p)
  return p


FLAG_FIELDS = {
    "task": lambda c: c.task, "algo": lambda c: c.sac.algo, "aug": lambda c: c.sac.aug,
    "lr": lambda c: (c.sac.critic_lr, c.sac.actor_lr, c.sac.encoder_lr),
    "steps": lambda c: c.steps, "seeds": lambda c: tuple(c.seeds),
    "num_envs": lambda c: c.num_envs, "visual_seeds": lambda c: c.visual_seeds,
    "vary": lambda c: c.vary, "moving": lambda c: c.moving,
    "intensity": lambda c: c.intensity, "action_repeat": lambda c: c.action_repeat,
    "utd": lambda c: c.utd, "warmup_steps": lambda c: c.warmup_steps,
    "buffer_capacity": lambda c: c.buffer_capacity, "batch_size": lambda c: c.sac.batch_size,
    "image_size": lambda c: c.image_size, "renderer": lambda c: c.renderer,
    "chunk_steps": lambda c: c.chunk_steps, "physics": lambda c: c.physics,
    "physics_workers": lambda c: c.physics_workers,
    "quality": lambda c: c.quality,
    "workers": lambda c: c.workers, "egl_devices": lambda c: c.egl_devices,
    "dtype": lambda c: c.sac.compute_dtype,
    "agent_loop": lambda c: c.agent_loop, "checkpoint_every": lambda c: c.checkpoint_every,
    "log_every": lambda c: c.log_every, "eval_every": lambda c: c.eval_every,
    "eval_looks": lambda c: c.eval_looks, "eval_dynamics": lambda c: c.eval_dynamics,
    "eval_train_episodes": lambda c: c.eval_train_episodes,
    "eval_conditions": lambda c: c.eval_conditions,
    "eval_renderer": lambda c: c.eval_renderer, "loggers": lambda c: tuple(c.loggers)}
"""Each flag's value in a `TrainConfig` (for `--resume`'s comparison)."""


def explicit_flags(argv) -> set[str]:
  """The options given on the command line (argparse dests), defaults left out."""
  q = build_parser()
  for action in q._actions:
    action.default = argparse.SUPPRESS
  return set(vars(q.parse_args(argv)))


def seeds_arg(text: str) -> tuple[int, ...]:
  """A command line's `--seeds` ("0", "0,1,2") as a tuple of ints (an argparse
  type: a bad value is reported as the flag's error, naming the form)."""
  parts = [p.strip() for p in text.split(",")]
  if not all(p.lstrip("+-").isdigit() for p in parts):
    raise argparse.ArgumentTypeError(
        f"want distinct ints in [0, 2**31) separated by commas, e.g. 0,1,2; got {text!r}")
  return tuple(int(p) for p in parts)


def loggers_arg(text: str) -> tuple[str, ...]:
  """A command line's `--logger` ("csv,tensorboard") as `TrainConfig.loggers` (an
  argparse type: an unknown name is reported as the flag's error, naming the valid
  ones; `dmcr_jax.train.loggers.parse_loggers`)."""
  try:
    return parse_loggers(text)
  except ValueError as e:
    raise argparse.ArgumentTypeError(str(e)) from None


def conditions_arg(text: str) -> tuple[str, ...]:
  """A command line's `--eval-conditions` ("none,all") as a tuple of names (checked
  against the task's conditions with the config)."""
  return tuple(p.strip() for p in text.split(","))


def parse(argv=None) -> tuple[TrainConfig, argparse.Namespace]:
  """The command line's `TrainConfig` (checked; a resumed run's from its
  config.json) and the parsed arguments, whose `plan` is the config resolved
  (`dmcr_jax.train.config.resolve`, once). A bad argument ends the process with
  argparse's error."""
  p = build_parser()
  a = p.parse_args(argv)
  try:
    if a.algo == "curl" and a.aug not in (None, "none"):
      raise ValueError(f"--algo curl takes no --aug (got {a.aug!r}): CURL trains on its "
                       "own random crops of a larger render (--image-size, default 100, "
                       "cropped to 84); drop --aug, or use --algo sac_aug with it")
    seeds = a.seeds
    lr = a.lr
    if lr is None and a.algo == "curl" and a.task.startswith("cheetah"):
      lr = 2e-4
    rates = {} if lr is None else dict(critic_lr=lr, actor_lr=lr, encoder_lr=lr)
    sac_cfg = SACConfig(algo=a.algo, aug=a.aug, batch_size=a.batch_size,
                        compute_dtype=a.dtype, **rates)
    visual = a.visual_seeds
    if visual.lstrip("-").isdigit():
      visual = int(visual)
    cfg = TrainConfig(task=a.task, steps=a.steps, seeds=seeds, num_envs=a.num_envs,
                      action_repeat=a.action_repeat, visual_seeds=visual, vary=a.vary,
                      moving=a.moving, intensity=a.intensity,
                      warmup_steps=a.warmup_steps, utd=a.utd,
                      buffer_capacity=a.buffer_capacity, image_size=a.image_size,
                      quality=a.quality, workers=a.workers, egl_devices=a.egl_devices,
                      log_every=a.log_every,
                      checkpoint_every=a.checkpoint_every, agent_loop=a.agent_loop,
                      renderer=a.renderer, chunk_steps=a.chunk_steps, physics=a.physics,
                      physics_workers=a.physics_workers, eval_every=a.eval_every,
                      eval_looks=a.eval_looks, eval_dynamics=a.eval_dynamics,
                      eval_train_episodes=a.eval_train_episodes,
                      eval_conditions=a.eval_conditions, eval_renderer=a.eval_renderer,
                      loggers=a.loggers,
                      out_dir=a.out or default_out(a.task, sac_cfg),
                      sac=sac_cfg)
    if a.resume:
      cfg = resumed_config(cfg, explicit_flags(argv))
    # Progress at least every 2 % of the run, whatever --log-every says.
    positive_int("log_every", cfg.log_every)
    cfg = dataclasses.replace(cfg, log_every=progress_every(cfg))
    a.plan = resolve(cfg)
    check_own_augmentations(cfg)
  except (ValueError, FileNotFoundError) as e:
    p.error(str(e))
  return cfg, a


def check_own_augmentations(cfg: TrainConfig) -> None:
  """Runs `dmcr_jax.augment.check` at the run's image size on every part of
  `--aug` that is not built in (imported or registered); ValueError with one
  paragraph naming what fails."""
  from dmcr_jax import augment
  from dmcr_jax.augment_check import AugmentationCheckError, observations
  own = dict.fromkeys(part for name in cfg.sac.aug_names for part in name.split("+")
                      if part not in augment.NAMES)
  if own:
    try:
      observations(cfg.image_size)  # rendered once per size, then cached
    except Exception as e:  # noqa: BLE001 - MuJoCo/GL errors have many types
      raise ValueError(f"--aug: the augmentation checker could not render its "
                       f"observations ({type(e).__name__}: {e}); MuJoCo needs a GL "
                       "backend (MUJOCO_GL=egl or osmesa)") from None
  for part in own:
    try:
      augment.check(part, size=cfg.image_size)
    except AugmentationCheckError as e:
      raise ValueError(f"--aug: {e.report.paragraph()}") from None


def resumed_config(cli: TrainConfig, given: set[str]) -> TrainConfig:
  """The config of the run in `cli.out_dir` (its config.json), with the flags in
  `given` that may change (`RESUMABLE`) applied.

  Raises:
    FileNotFoundError: no config.json there (nothing is created).
    ValueError: a given flag differs from the run's setting and may not change.
  """
  if not os.path.exists(os.path.join(cli.out_dir, "config.json")):
    raise FileNotFoundError(f"--resume: no run in {cli.out_dir!r} (no config.json); "
                            "check the folder (--out)")
  saved = load_config(cli.out_dir)
  refused = [f"--{f.replace('_', '-')} {FLAG_FIELDS[f](cli)!r} (the run has "
             f"{FLAG_FIELDS[f](saved)!r})"
             for f in sorted(given & set(FLAG_FIELDS))
             if f not in RESUMABLE and FLAG_FIELDS[f](cli) != FLAG_FIELDS[f](saved)]
  if refused:
    raise ValueError(f"--resume continues {cli.out_dir} with the settings in its "
                     f"config.json; these flags differ from them: {'; '.join(refused)}. "
                     f"Drop them, or start a new run with another --out (only "
                     f"{', '.join('--' + f.replace('_', '-') for f in RESUMABLE)} may "
                     "change on resume)")
  changes = {f: getattr(cli, f) for f in RESUMABLE if f in given}
  return dataclasses.replace(saved, out_dir=cli.out_dir, **changes)


def default_out(task: str, sac_cfg: SACConfig) -> str:
  """runs/<task>-<aug> for SAC+AUG, runs/<task>-<algo>[-<aug>] otherwise."""
  aug = sac_cfg.aug.replace(",", "_").replace(":", ".")
  if sac_cfg.algo == "sac_aug":
    return f"runs/{task}-{aug}"
  return f"runs/{task}-{sac_cfg.algo}" + ("" if aug == "none" else f"-{aug}")


def main(argv=None) -> None:
  """`dmcr-train`: parses the command line, sets the compilation cache
  (`dmcr_jax.train.compile_cache`), trains, prints the summary as JSON (exit
  status 130 when interrupted)."""
  _, a = parse(argv)
  compile_cache.use(compile_cache.chosen(a))
  try:
    summary = train(a.plan, resume=a.resume, progress=not a.no_progress)
  except (ValueError, FileExistsError, FileNotFoundError) as e:
    sys.exit(f"train: error: {e}")
  print(json.dumps(summary, indent=1))
  if summary["interrupted"]:
    sys.exit(130)


if __name__ == "__main__":
  main()
