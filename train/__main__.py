"""`train` / `python -m train`: train SAC+AUG, CURL or SAC+AE agents on a DMCR task from pixels.

    train --task cartpole-balance --steps 50000 --seeds 0,1,2 --aug drq
    train --task cartpole-balance --algo curl      # or --algo sac_ae

One agent per seed and augmentation (`--aug drq,cj+drq --seeds 0,1,2`: 6 agents,
trained together in one process). `--steps` counts the paper's training steps
(transitions stored) per agent; with `--num-envs N` an agent collects N per step.

Arguments are checked before anything is compiled. Outputs go to `--out`
(default `runs/<task>-<aug>`): log.csv, learning_curve.png, summary.json and
orbax checkpoints; `--resume` continues from the latest checkpoint (see
`train.loop` for what is restored: agents, step and RNG key, not the buffers).

`--renderer jax` renders with the JAX ray caster on the device; with the physics
on the device too (`--physics device`) training runs in chunks of `--chunk-steps`
vector steps, each one XLA call (`train.device_loop`). `--physics auto` (the
default) steps small batches' physics on the host CPU, beside the learner's
updates on the accelerator (`train.loop`). `--quality` and `--workers` belong to
the default CPU render pool (`--renderer pool`).

`--algo` picks the learner (`train.sac.ALGOS`); unset options take its defaults
(`train.sac.ALGO_DEFAULTS`: CURL renders at 100 and crops to 84 and takes no
`--aug`; SAC+AE uses batch 128 and no augmentation unless `--aug` names one).
CURL on cheetah uses learning rate 2e-4 for the critic, actor and encoder (the
paper's Table 6) unless `--lr` is given.
"""

from __future__ import annotations

import argparse
import json
import sys

from train.loop import CPU_PHYSICS_MAX_ENVS, PHYSICS, TrainConfig, check_config, train
from train.sac import ALGOS, SACConfig


def parse(argv=None) -> tuple[TrainConfig, argparse.Namespace]:
  d, s = TrainConfig(), SACConfig()
  p = argparse.ArgumentParser(prog="train", description=__doc__.splitlines()[0])
  p.add_argument("--task", default=d.task, help="a DMCR task (default: %(default)s)")
  p.add_argument("--algo", default=s.algo, choices=ALGOS,
                 help="learner: sac_aug (default), curl or sac_ae")
  p.add_argument("--aug", default=None,
                 help="augmentation name, e.g. drq, cj+drq, nr+drq; comma-separated "
                      "names train one agent per name and seed (default: drq for "
                      "sac_aug, none for sac_ae; curl takes none)")
  p.add_argument("--lr", type=float, default=None,
                 help="learning rate of the critic, actor and encoder (default 1e-3; "
                      "2e-4 for curl on cheetah)")
  p.add_argument("--steps", type=int, default=d.steps,
                 help="training steps (transitions) per agent")
  p.add_argument("--seeds", default="0", help="comma-separated: one agent per seed")
  p.add_argument("--num-envs", type=int, default=d.num_envs, help="envs per agent")
  p.add_argument("--visual-seeds", default=str(d.visual_seeds),
                 help="an int (fixed look, 0 = dm_control's) or levels:<n> (few-shot)")
  p.add_argument("--vary", default=d.vary, help="factors the visual seeds change")
  p.add_argument("--action-repeat", type=int, default=None,
                 help="default: the paper's Table 4 value for the task")
  p.add_argument("--utd", type=float, default=d.utd, help="updates per training step")
  p.add_argument("--warmup-steps", type=int, default=d.warmup_steps,
                 help="random-action training steps per agent before learning")
  p.add_argument("--buffer-capacity", type=int, default=d.buffer_capacity)
  p.add_argument("--batch-size", type=int, default=None,
                 help="default: 256 (128 for sac_ae)")
  p.add_argument("--image-size", type=int, default=None,
                 help="rendered side (default: 84; 100 for curl)")
  p.add_argument("--renderer", default=d.renderer,
                 help="pool (MuJoCo in CPU workers, the default) or jax (the JAX ray "
                      "caster; training runs in chunks of --chunk-steps on the device)")
  p.add_argument("--physics", default=d.physics, choices=PHYSICS,
                 help="where the physics steps: auto (the host CPU for at most "
                      f"{CPU_PHYSICS_MAX_ENVS} envs in all when the learner runs on "
                      "an accelerator, else the device), cpu or device (default: "
                      "%(default)s)")
  p.add_argument("--chunk-steps", type=int, default=d.chunk_steps,
                 help="--renderer jax: vector steps per device call (default: %(default)s)")
  p.add_argument("--quality", default=d.quality,
                 help="render preset: exact, fast, fastest (--renderer pool)")
  p.add_argument("--workers", type=int, default=None, help="render workers (--renderer pool)")
  p.add_argument("--dtype", default=s.compute_dtype,
                 help="compute dtype of the networks: float32 or bfloat16")
  p.add_argument("--agent-loop", default=d.agent_loop,
                 help="how K agents' updates are batched: vmap or map")
  p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every)
  p.add_argument("--log-every", type=int, default=d.log_every)
  p.add_argument("--out", default=None, help="output folder (default: runs/<task>-<aug>)")
  p.add_argument("--resume", action="store_true", help="continue from the latest checkpoint")
  p.add_argument("--no-progress", action="store_true")
  a = p.parse_args(argv)
  try:
    seeds = tuple(int(x) for x in a.seeds.split(","))
    lr = a.lr
    if lr is None and a.algo == "curl" and a.task.startswith("cheetah"):
      lr = 2e-4
    rates = {} if lr is None else dict(critic_lr=lr, actor_lr=lr, encoder_lr=lr)
    sac_cfg = SACConfig(algo=a.algo, aug=a.aug, batch_size=a.batch_size,
                        compute_dtype=a.dtype, **rates)
    visual = a.visual_seeds if a.visual_seeds.startswith("levels:") else int(a.visual_seeds)
    cfg = TrainConfig(task=a.task, steps=a.steps, seeds=seeds, num_envs=a.num_envs,
                      action_repeat=a.action_repeat, visual_seeds=visual, vary=a.vary,
                      warmup_steps=a.warmup_steps, utd=a.utd,
                      buffer_capacity=a.buffer_capacity, image_size=a.image_size,
                      quality=a.quality, workers=a.workers, log_every=a.log_every,
                      checkpoint_every=a.checkpoint_every, agent_loop=a.agent_loop,
                      renderer=a.renderer, chunk_steps=a.chunk_steps, physics=a.physics,
                      out_dir=a.out or default_out(a.task, sac_cfg),
                      sac=sac_cfg)
    check_config(cfg)
  except ValueError as e:
    p.error(str(e))
  return cfg, a


def default_out(task: str, sac_cfg: SACConfig) -> str:
  """runs/<task>-<aug> for SAC+AUG, runs/<task>-<algo>[-<aug>] otherwise."""
  aug = sac_cfg.aug.replace(",", "_")
  if sac_cfg.algo == "sac_aug":
    return f"runs/{task}-{aug}"
  return f"runs/{task}-{sac_cfg.algo}" + ("" if aug == "none" else f"-{aug}")


def main(argv=None) -> None:
  cfg, a = parse(argv)
  try:
    summary = train(cfg, resume=a.resume, progress=not a.no_progress)
  except (FileExistsError, FileNotFoundError) as e:
    sys.exit(f"train: error: {e}")
  print(json.dumps(summary, indent=1))
  if summary["interrupted"]:
    sys.exit(130)


if __name__ == "__main__":
  main()
