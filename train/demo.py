"""`dmcr-demo` / `python -m dmcr_jax.train.demo`: the project's main job, sized for a laptop CPU.

    dmcr-demo                                   # cartpole-balance into dmcr_demo/
    dmcr-demo --out my_demo --steps 8000        # longer training

Trains one small SAC+AUG (DrQ) agent on a few visual seeds (few-shot looks:
`dmcr_jax.levels`) with pixels from the JAX ray caster (`dmcr_jax.train.loop.train`, the
`train` command's run), then evaluates it zero-shot on held-out looks, one visual
factor at a time and all together (`dmcr_jax.train.evaluate.evaluate`, the paper's protocol
with fewer looks and initial states), and writes into `--out`:

  visual_seeds.png                 the training looks (top row) and held-out test
                                   looks (bottom row), drawn by MuJoCo at 96 px
  run/learning_curve.png, log.csv  the training run (`train`'s outputs, checkpoint
                                   included, so `evaluate OUT/run` works on it)
  eval/eval.md, eval.png, eval.json  the per-factor table: return per visual
                                   condition and E_G = (train − test) / train

What is small (`Demo`): the image (32 px), the networks and batch (`DEMO_SAC`),
the training steps, and the evaluation (a few looks × one initial state per
condition). The numbers it prints are therefore a smoke test of the pipeline, not
a result; it ends with the full-size commands.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import numpy as np

from dmcr_jax.train import evaluate as ev
from dmcr_jax.train import config, loop, sac

DEMO_SAC = sac.SACConfig(batch_size=32, hidden_dim=256, conv_channels=8)
"""The demo's learner: SAC+AUG with DrQ as in the paper, but batch 32 (paper: 256),
256-wide actor and critics (1,024) and 8 filters per convolution (32): small enough
that a few thousand gradient updates fit in the demo's minutes on a laptop CPU."""

GRID_TILE = 96
"""Side of a tile of visual_seeds.png, in pixels."""


@dataclasses.dataclass(frozen=True)
class Demo:
  """What `run` trains and evaluates (defaults: the `dmcr-demo` command's).

  Attributes:
    task: a DMCR task (the defaults are sized for cartpole-balance).
    steps: training steps (transitions) of the agent.
    num_envs: envs the agent acts in.
    train_looks: the agent trains on visual seeds [0, train_looks) (a new look
      drawn at every episode).
    vary: the factors the training seeds change.
    image_size: rendered side in pixels.
    warmup_steps: random-action steps before learning; None = min(500, steps // 4).
    action_repeat: None = the paper's value for the task.
    sac: the learner's hyperparameters.
    eval_looks: held-out visual seeds per evaluation condition.
    eval_states: initial states per held-out look.
    seed: the agent's seed (network init, exploration, initial states) and the
      held-out looks' draw.
  """
  task: str = "cartpole-balance"
  steps: int = 4000
  num_envs: int = 4
  train_looks: int = 4
  vary: str = "all"
  image_size: int = 32
  warmup_steps: int | None = None
  action_repeat: int | None = None
  sac: sac.SACConfig = DEMO_SAC
  eval_looks: int = 8
  eval_states: int = 1
  seed: int = 0

  def train_config(self, out: str) -> config.TrainConfig:
    """The `TrainConfig` of the demo's run in `<out>/run` (JAX renderer, one
    checkpoint at the end)."""
    warmup = min(500, self.steps // 4) if self.warmup_steps is None else self.warmup_steps
    return config.TrainConfig(
        task=self.task, steps=self.steps, seeds=(self.seed,), num_envs=self.num_envs,
        action_repeat=self.action_repeat, visual_seeds=f"levels:{self.train_looks}",
        vary=self.vary, warmup_steps=warmup,
        buffer_capacity=max(self.steps, self.num_envs * 4), image_size=self.image_size,
        renderer="jax", checkpoint_every=0, out_dir=os.path.join(out, "run"), sac=self.sac)

  def eval_config(self) -> ev.EvalConfig:
    """The evaluation: `eval_looks` × `eval_states` episodes per condition, as many
    at the training looks, rendered by the JAX ray caster."""
    n = self.eval_looks * self.eval_states
    return ev.EvalConfig(visual_seeds=self.eval_looks, dynamics_seeds=self.eval_states,
                         train_episodes=n, seed=self.seed, renderer="jax")


def check(demo: Demo, out: str) -> config.Plan:
  """The demo's training run resolved (`dmcr_jax.train.config.resolve`, its one
  check); ValueError naming the problem (a bad setting, or `out` already holding
  a demo run), before anything is created or compiled."""
  from dmcr_jax.checks import positive_int
  for name in ("steps", "train_looks", "eval_looks", "eval_states"):
    positive_int(name, getattr(demo, name))
  cfg = demo.train_config(out)
  plan = config.resolve(cfg)
  ev.check_eval_config(demo.eval_config(), demo.task)
  if ev.checkpoint_steps(cfg.out_dir):
    raise ValueError(f"{out!r} already holds a demo run ({cfg.out_dir}/checkpoints); "
                     "choose another --out or delete that folder")
  return plan


def seed_grid(demo: Demo, path: str) -> np.ndarray:
  """Writes `path`: the training looks (top row) and as many of the held-out looks
  of the "all" condition (bottom row), each drawn by MuJoCo (`dmcr-show`'s
  `render_grid`) at the task's initial state; returns the image."""
  import imageio.v3 as iio
  from dmcr_jax.visuals.show import render_grid
  train = list(range(demo.train_looks))
  test = [int(s) for s in ev.held_out_seeds(demo.eval_looks, demo.seed)[:len(train)]]
  cols = max(len(train), len(test))
  pad = 2
  rows = [render_grid(demo.task, train, demo.vary, size=GRID_TILE, cols=cols, pad=pad),
          render_grid(demo.task, test, "all", size=GRID_TILE, cols=cols, pad=pad)]
  grid = np.concatenate([rows[0], rows[1][pad:]], axis=0)  # one gap between the rows
  iio.imwrite(path, grid)
  return grid


def full_size_commands(task: str) -> list[str]:
  """The commands of the paper-sized run of `task` (a GPU machine)."""
  run = f"runs/{task}-drq"
  return [f"dmcr-train --task {task} --steps 50000 --dtype bfloat16 --out {run}",
          f"dmcr-evaluate {run}",
          f"dmcr-train --task {task} --visual-seeds levels:10 --dtype bfloat16 "
          f"--out {run}-levels10   # few-shot looks, as this demo"]


def run(demo: Demo = Demo(), out: str = "dmcr_demo", progress: bool = True,
        plan: config.Plan | None = None) -> dict:
  """Runs the demo; returns what it wrote and measured.

  Args:
    demo: the settings.
    out: the output folder (created).
    progress: progress bars (else progress lines on stderr).
    plan: `check(demo, out)` when already made (None: made here).

  Returns:
    dict: files (name → path), train (`dmcr_jax.train.loop.train`'s summary), eval
    (`dmcr_jax.train.evaluate.evaluate`'s results), first_return and last_return (mean
    return of the first and the last episodes on the learning curve), wall_s.

  Raises:
    ValueError: a bad setting, or `out` already holds a demo run (nothing is
      created then).
  """
  plan = plan or check(demo, out)
  t0 = time.perf_counter()
  cfg = plan.cfg
  os.makedirs(out, exist_ok=True)
  files = {}
  say = lambda *a: print(*a, flush=True)

  say(f"[1/3] visual seeds: {demo.train_looks} training looks (seeds 0-"
      f"{demo.train_looks - 1}, vary={demo.vary}) and held-out test looks")
  grid_path = os.path.join(out, "visual_seeds.png")
  try:
    seed_grid(demo, grid_path)
    files["visual seeds"] = grid_path
  except Exception as e:  # MuJoCo's GL may be missing; the run itself needs none
    say(f"      skipped the picture (MuJoCo could not render: {type(e).__name__}: {e}); "
        "training and evaluation use the JAX ray caster and go on")

  say(f"[2/3] training SAC+AUG (drq) on {demo.task}: {demo.steps:,} steps, "
      f"{demo.num_envs} envs, {cfg.image_size}x{cfg.image_size} pixels from the JAX "
      f"ray caster")
  summary = loop.train(plan, progress=progress)
  files["learning curve"] = os.path.join(cfg.out_dir, "learning_curve.png")
  files["training log"] = os.path.join(cfg.out_dir, "log.csv")

  ecfg = demo.eval_config()
  say(f"[3/3] zero-shot evaluation: {ecfg.visual_seeds} held-out looks × "
      f"{ecfg.dynamics_seeds} initial state(s) per condition")
  eval_dir = os.path.join(out, "eval")
  results = ev.evaluate(cfg.out_dir, ecfg, out_dir=eval_dir, progress=progress)
  for name in ("eval.md", "eval.png", "eval.json"):
    files["per-factor table" if name == "eval.md" else name] = os.path.join(eval_dir, name)
  first, last = _first_and_last_returns(files["training log"])
  return dict(files=files, train=summary, eval=results, first_return=first,
              last_return=last, wall_s=time.perf_counter() - t0)


def _first_and_last_returns(log_path: str) -> tuple[float | None, float | None]:
  """Mean return of the episodes that ended at the first and at the last logged step."""
  import csv
  with open(log_path) as f:
    rows = [(int(r["step"]), float(r["episode_return"])) for r in csv.DictReader(f)]
  if not rows:
    return None, None
  steps = sorted({s for s, _ in rows})
  mean_at = lambda t: float(np.mean([r for s, r in rows if s == t]))
  return mean_at(steps[0]), mean_at(steps[-1])


def report(demo: Demo, result: dict) -> str:
  """The demo's closing text: the table, the files, what a run this size shows,
  and the full-size commands."""
  r = result["eval"]["agents"][0]
  first, last = result["first_return"], result["last_return"]
  curve = ("no episode finished" if first is None else
           f"episode return {first:.0f} in the first episodes, {last:.0f} in the last")
  lines = [ev.markdown(result["eval"]), "Wrote:"]
  lines += [f"  {name:<17} {path}" for name, path in result["files"].items()]
  lines += [
      "",
      f"Done in {result['wall_s'] / 60:.1f} min. Training: {curve}; evaluation: "
      f"{r['train']['mean']:.0f} at the training looks, "
      f"{r['conditions'][result['eval']['conditions'][-1]]['mean']:.0f} with every "
      "factor new.",
      f"What this CPU-sized run shows: the whole pipeline on your machine - visual seeds, "
      f"pixels rendered in JAX, SAC+AUG training, the zero-shot protocol and its table. "
      f"What it cannot show: a trained agent or a generalisation result. "
      f"{demo.steps:,} training steps of a small network (batch {demo.sac.batch_size}, "
      f"{demo.image_size} px) are a fraction of the paper's 50,000 steps at batch 256 "
      f"and 84 px: expect returns near those of the first, random-action episodes "
      f"(a few times more --steps begin to learn; the README says how far). "
      f"With {demo.eval_looks * demo.eval_states} episodes per condition the E_G column "
      "is noise.",
      "",
      "The full-size run (the paper's settings; a GPU: see docs/training.md and "
      "docs/evaluation.md for what it takes):"]
  lines += [f"  {c}" for c in full_size_commands(demo.task)]
  return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
  """The `dmcr-demo` command line (defaults from `Demo`)."""
  from dmcr_jax.train.__main__ import HelpFormatter
  d = Demo()
  p = argparse.ArgumentParser(
      prog="dmcr-demo", formatter_class=HelpFormatter,
      description="Train a small SAC+AUG agent on a few visual seeds with the JAX "
                  "renderer, evaluate it zero-shot on held-out looks, and write a seed "
                  "grid, the learning curve and the per-factor table (a few minutes on "
                  "a 2-core CPU).")
  p.add_argument("--out", default="dmcr_demo", help="output folder")
  p.add_argument("--steps", type=int, default=d.steps,
                 help="training steps (transitions) of the agent; the first "
                      "min(500, steps/4) take random actions")
  p.add_argument("--task", default=d.task,
                 help="a DMCR task (the other defaults are sized for cartpole-balance)")
  p.add_argument("--no-progress", action="store_true",
                 help="no progress bars (progress lines on stderr instead)")
  return p


def main(argv=None) -> None:
  """`dmcr-demo [--out DIR] [--steps N] [--task TASK]`."""
  p = build_parser()
  a = p.parse_args(argv)
  demo = Demo(task=a.task, steps=a.steps)
  try:
    plan = check(demo, a.out)
  except ValueError as e:
    p.error(str(e))
  try:
    result = run(demo, a.out, progress=not a.no_progress, plan=plan)
  except (ValueError, FileExistsError, FileNotFoundError) as e:
    sys.exit(f"dmcr-demo: error: {e}")
  print(report(demo, result))


if __name__ == "__main__":
  main()
