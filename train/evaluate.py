"""Zero-shot generalisation of trained agents: `dmcr-evaluate RUN`, the paper's protocol
(Sec. 4.2–4.3) for a `dmcr-train` run, through `dmcr_jax.protocol`.

For a `train` run, each agent's greedy policy (tanh of the mean action,
`greedy_policy`) is evaluated with `dmcr_jax.protocol`: at its training look over
`train_episodes` initial states (paper: 100), the "train" return, and under each
visual condition over `visual_seeds` held-out looks × `dynamics_seeds` initial
states each (paper: 100 × 3 = 300 episodes): "none" (nothing varied), one factor at
a time (light, camera, body, floor, then background, target and reflectance where
they apply to the domain) and "all"; with `--moving-intensities` (or
``moving-<factor>@<intensity>`` names in `--conditions`) also moving conditions,
dm_control's look with one factor (or all) moving within each episode
(`dmcr_jax.protocol_plan.parse_condition`). Conditions change factors away from
dm_control's default look, as in the paper, whose agents trained on it (visual
seed 0). Test looks are drawn from the held-out `dmcr_jax.TEST_SEEDS`, which no
training range can overlap, with a NumPy generator seeded by `EvalConfig.seed`.
The agents are the policy's leading params axis: every episode of every agent
and condition runs as one batch (blocks of at most `EvalConfig.max_envs` envs),
on the device with the JAX ray caster, or with the CPU render pool.

The generalisation error of a condition is E_G = (train − test) / train (paper
Sec. 3). Outputs (`dmcr_jax.protocol_report`): a JSON file, a Markdown table laid
out like the paper's Table 4 (with the paper's row for the task and each method
when it has one) and a bar chart. A run that trained several augmentations
(``dmcr-train --aug drq,cj+drq,mine+drq``) is compared side by side: per
augmentation the mean over its seeds, each condition's return and E_G, beside the
paper's rows (``"augs"`` in the JSON; one row per augmentation in both tables, per
augmentation and training-look range in a few-shot run; grouped bars in the chart).

Few-shot runs (`dmcr-train --visual-seeds levels:1,10,…`, one agent per training-look
range): every agent meets the same held-out test looks; an agent's "train" return
is taken at looks drawn from its own range (seeds drawn with the same generator
seed). The run's generalisation curve follows: test return per condition and
E_G against the number of training looks (`few_shot.json`, `few_shot.md`,
`few_shot.png`), with the zero-shot agents' (levels:1, dm_control's look) "all"
returns as reference lines where the run has them.

An interrupted evaluation goes on where it stopped when called again with the same
arguments: finished blocks wait in the output folder's `progress.npz`.

    dmcr-evaluate runs/cartpole-balance-drq            # or: python -m dmcr_jax.train.evaluate …
    dmcr-evaluate runs/cartpole-balance-drq --invariance --attention --video
    dmcr-evaluate runs/walker-walk --renderer jax --moving-intensities 0.1,0.2,0.3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import jax
import numpy as np

from dmcr_jax import protocol
from dmcr_jax.checks import positive_int
from dmcr_jax.env_checks import default_frame_skip
from dmcr_jax.protocol import (PROGRESS_FILE, check_conditions, conditions_for,
                               generalization_error, held_out_seeds)
from dmcr_jax.protocol_report import aug_groups, few_shot_markdown, few_shot_rows, markdown, write
from dmcr_jax.train import loop, paper_results, sac

__all__ = ["EvalConfig", "PROGRESS_FILE", "check_eval_config", "conditions_for", "evaluate",
           "generalization_error", "greedy_policy", "held_out_seeds",
           "main", "markdown", "policy_params"]


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """What `evaluate` runs (defaults: the paper's protocol).

  Attributes:
    visual_seeds: held-out looks per condition (paper: 100).
    dynamics_seeds: initial states per look (paper: 3).
    train_episodes: episodes at the training look (paper: 100); at most
      visual_seeds · dynamics_seeds (the first ones of the batch are used).
    seed: seeds the held-out looks' draw and the initial states.
    conditions: the conditions to run; None = every one that applies.
    quality: render preset (the default, "exact", is dm_control's look).
    workers: render workers (None: the pool pass's, `protocol_pool.pass_workers`:
      a few where a GPU draws, one per core where the frames are drawn in software).
    egl_devices: EGL device indices the render workers are spread over (None:
      MuJoCo's default; `dmcr_jax.visuals.render_pool`).
    renderer: "pool" (MuJoCo's pixels from the CPU render pool, the reference) or
      "jax" (the JAX ray caster on the device: fast, close to MuJoCo's pixels but
      not equal; `quality`, `workers` and `egl_devices` do not apply).
    max_envs: at most this many envs per block (all agents' together); None:
      every episode in one block (`dmcr_jax.protocol.prepare`).
    moving_intensities: also every moving condition (each moving factor of the
      domain, then "all", ``moving-<factor>@<intensity>``) at each of these
      intensities (docs/protocol.md); () none.
  """
  visual_seeds: int = 100
  dynamics_seeds: int = 3
  train_episodes: int = 100
  seed: int = 0
  conditions: tuple[str, ...] | None = None
  quality: str = "exact"
  workers: int | None = None
  egl_devices: tuple[int, ...] | None = None
  renderer: str = "pool"
  max_envs: int | None = None
  moving_intensities: tuple[float, ...] = ()


def check_eval_config(cfg: EvalConfig, task: str) -> tuple[str, ...]:
  """Validates `cfg` for `task`; returns the conditions to run."""
  from dmcr_jax.visuals.tiled import check_quality
  for name in ("visual_seeds", "dynamics_seeds", "train_episodes"):
    positive_int(name, getattr(cfg, name))
  if cfg.train_episodes > cfg.visual_seeds * cfg.dynamics_seeds:
    raise ValueError(f"train_episodes ({cfg.train_episodes}) must be at most "
                     f"visual_seeds · dynamics_seeds = {cfg.visual_seeds * cfg.dynamics_seeds}")
  check_quality(cfg.quality)
  loop.check_renderer(cfg.renderer, cfg.quality, cfg.workers, cfg.egl_devices)
  if cfg.workers is not None:
    positive_int("workers", cfg.workers)
  if cfg.max_envs is not None:
    positive_int("max_envs", cfg.max_envs)
  return check_conditions(task, cfg.conditions, cfg.moving_intensities)


def render_options(cfg: EvalConfig) -> dict:
  """`dmcr_jax.protocol.prepare`'s renderer keywords for `cfg`."""
  if cfg.renderer == "jax":
    return {}
  return dict(quality=cfg.quality, workers=cfg.workers, egl_devices=cfg.egl_devices)


def greedy_policy(agent: sac.AgentState, obs: jax.Array, key: jax.Array) -> jax.Array:
  """The evaluation policy as a `dmcr_jax.protocol.Policy`: tanh of the mean action,
  (B, A) in [−1, 1] (`key` unused); `agent` as `policy_params` makes it."""
  return sac.act(agent, obs, None, deterministic=True)


def policy_params(stacked: sac.AgentState, chosen: list[int]) -> sac.AgentState:
  """The chosen agents (leading axis, in `chosen` order) with only what acting reads:
  the encoder's and the actor's params (the optimiser states and critics dropped)."""
  pick = lambda tree: jax.tree.map(lambda x: x[np.asarray(chosen)], tree)
  params = {name: pick(stacked.params[name]) for name in ("encoder", "actor")}
  return sac.AgentState(params=params, log_alpha=None, target_params=None,
                        critic_opt_state=None, actor_opt_state=None, alpha_opt_state=None,
                        aux_opt_state=None, step=None, aug_index=None,
                        networks=stacked.networks)


def evaluate(run_dir: str, cfg: EvalConfig = EvalConfig(), out_dir: str | None = None,
             agents: list[int] | None = None, progress: bool = True) -> dict:
  """Runs the protocol for a `train` run's agents; writes JSON, Markdown and PNG.

  Args:
    run_dir: the run's output folder (config.json + checkpoints).
    cfg: the protocol's sizes and options.
    out_dir: where the results go (default `<run_dir>/eval`).
    agents: indices of the agents to evaluate (default: all).
    progress: a progress bar on a terminal, else a line per block on stderr.

  Returns:
    The results (also in `<out_dir>/eval.json`, where an undefined E_G, NaN
    here, is null): per agent the train return, every condition's mean, std and
    per-episode returns, E_G per condition, and the wall time (of every attempt,
    when resumed).

  Each finished block is kept in `<out_dir>/progress.npz` until the results are
  written: called again after an interruption with the same run, agents and
  protocol, it runs only the blocks still missing (the episodes are the same
  either way: every episode's look, initial state and policy keys follow from
  `cfg.seed`).

  Raises:
    FileNotFoundError: no config.json or no checkpoint in `run_dir`.
    ValueError: a bad `cfg` or agent index (before anything is loaded).
  """
  conditions = check_eval_config(cfg, check_run(run_dir, agents).task)
  train_cfg, stacked, step = loop.load_run(run_dir)
  specs = train_cfg.agents()
  chosen = list(range(len(specs))) if agents is None else list(agents)
  out_dir = out_dir or os.path.join(run_dir, "eval")
  os.makedirs(out_dir, exist_ok=True)
  looks = train_cfg.agent_looks()
  proto = protocol.prepare(
      train_cfg.task, greedy_policy, agents=len(chosen), renderer=cfg.renderer,
      visual_seeds=cfg.visual_seeds, dynamics_seeds=cfg.dynamics_seeds,
      train_episodes=cfg.train_episodes, conditions=conditions,
      train_look=[looks[a] for a in chosen], train_vary=train_cfg.vary, seed=cfg.seed,
      image_size=train_cfg.image_size, frame_stack=train_cfg.frame_stack,
      action_repeat=train_cfg.action_repeat, max_envs=cfg.max_envs, **render_options(cfg))
  progress_key = dict(run_dir=os.path.abspath(run_dir), checkpoint_step=int(step),
                      agents=chosen)
  result = proto(policy_params(stacked, chosen), progress=progress,
                 progress_file=os.path.join(out_dir, PROGRESS_FILE),
                 progress_key=progress_key)
  summary = result.summary()
  algo = train_cfg.sac.algo
  for row, a in zip(summary["agents"], chosen):
    seed, aug = specs[a]
    row.pop("label")
    row.update(agent=a, seed=seed, aug=aug, algo=algo,
               method=paper_results.method_name(algo, aug),
               train_look=loop.look_label(looks[a]), looks=loop.num_looks(looks[a]))
  summary = dict(run_dir=run_dir, task=train_cfg.task, checkpoint_step=step,
                 action_repeat=train_cfg.action_repeat or default_frame_skip(train_cfg.task),
                 device=result.device, training=training_record(run_dir),
                 config=dataclasses.asdict(cfg), conditions=list(conditions),
                 test_visual_seeds=summary["test_visual_seeds"],
                 train_look=str(train_cfg.visual_seeds), agents=summary["agents"],
                 wall_s=result.wall_s, compile_s=result.compile_s,
                 agent_steps=result.agent_steps, moving=summary["moving"],
                 mean=summary["mean"])
  summary["augs"] = aug_groups(summary)
  write(summary, out_dir, few_shot=len(loop.parse_visual_seeds(train_cfg.visual_seeds)) > 1)
  return summary


def training_record(run_dir: str) -> dict | None:
  """How the run trained, from its summary.json: {"wall_s": the training loops' total
  over every process of the run, "devices": the learner's device kinds, "num_envs"},
  or None without a summary (e.g. agents imported by `export_params` from a run
  exported without one)."""
  path = os.path.join(run_dir, "summary.json")
  if not os.path.exists(path):
    return None
  with open(path) as f:
    summary = json.load(f)
  segments = summary.get("segments", [])
  return dict(wall_s=summary.get("train_wall_s", summary.get("wall_s")),
              devices=sorted({s["device"] for s in segments if s.get("device")}),
              num_envs=summary.get("num_envs"))



def checkpoint_steps(run_dir: str) -> list[int]:
  """The steps of the checkpoints in `<run_dir>/checkpoints` (read from the folder
  names, without starting orbax)."""
  ckpt = os.path.join(run_dir, "checkpoints")
  if not os.path.isdir(ckpt):
    return []
  return sorted(int(d) for d in os.listdir(ckpt)
                if d.isdigit() and os.path.isdir(os.path.join(ckpt, d)))


def check_run(run_dir: str, agents: list[int] | None) -> loop.TrainConfig:
  """The run's config, once `run_dir` is known to hold a config and a checkpoint
  and `agents` (None: all) are indices of its agents; else ValueError or
  FileNotFoundError saying which."""
  train_cfg = loop.load_config(run_dir)
  if not checkpoint_steps(run_dir):
    raise FileNotFoundError(f"{run_dir!r} holds a config.json but no checkpoint (in "
                            f"{os.path.join(run_dir, 'checkpoints')}): was the run stopped "
                            "before its first checkpoint?")
  k = len(train_cfg.agents())
  if agents is not None and (not agents or any(not 0 <= a < k for a in agents)):
    raise ValueError(f"agents must be indices in [0, {k}) (the run trained {k} agent"
                     f"{'s' if k > 1 else ''}), got {','.join(map(str, agents))}")
  return train_cfg


def intensities_arg(text: str) -> tuple[float, ...]:
  """--moving-intensities: comma-separated numbers ("0.1,0.2,0.3"); their range is
  checked with the conditions (`protocol_plan.check_conditions`)."""
  try:
    return tuple(float(x) for x in text.split(",") if x.strip())
  except ValueError:
    raise argparse.ArgumentTypeError(f"comma-separated numbers in [0, 1] such as 0.1,0.2,0.3, "
                                     f"got {text!r}") from None


def main(argv=None) -> None:
  """`dmcr-evaluate RUN_DIR [options]` (the compilation cache:
  `dmcr_jax.train.compile_cache`)."""
  from dmcr_jax.train import compile_cache
  from dmcr_jax.visuals.tiled import QUALITY
  from dmcr_jax.train.__main__ import HelpFormatter
  d = EvalConfig()
  p = argparse.ArgumentParser(prog="dmcr-evaluate", description=__doc__.splitlines()[0],
                              formatter_class=HelpFormatter)
  p.add_argument("run_dir", help="a `train` output folder")
  p.add_argument("--visual-seeds", type=int, default=d.visual_seeds,
                 help="held-out looks per condition")
  p.add_argument("--dynamics-seeds", type=int, default=d.dynamics_seeds,
                 help="initial states per look")
  p.add_argument("--train-episodes", type=int, default=d.train_episodes,
                 help="episodes at the training look")
  p.add_argument("--seed", type=int, default=d.seed,
                 help="seeds the held-out looks and the initial states")
  p.add_argument("--conditions", default=None,
                 help="comma-separated (default: every static condition that applies); "
                      "static names (none, floor, all, ...) or moving ones, "
                      "moving-<factor>@<intensity> (e.g. moving-camera@0.2, moving-all@0.1)")
  p.add_argument("--moving-intensities", type=intensities_arg, default=(), metavar="I[,I…]",
                 help="also every moving condition (each moving factor, then all) at each "
                      "intensity, e.g. 0.1,0.2,0.3 (the Distracting Control Suite's "
                      "difficulties)")
  p.add_argument("--agents", default=None, help="comma-separated agent indices (default: all)")
  p.add_argument("--quality", default=d.quality, metavar="{" + ",".join(QUALITY) + "}",
                 help="render preset (--renderer pool)")
  p.add_argument("--workers", type=int, default=None,
                 help="render workers (default: the pool pass's, 4 where a GPU draws, "
                      "one per core, at most 16, where software draws)")
  p.add_argument("--egl-devices", type=loop.egl_devices_arg, default=None, metavar="D[,D…]",
                 help="EGL device indices the render workers are spread over (default: "
                      "MuJoCo's, MUJOCO_EGL_DEVICE_ID or the first); e.g. 0,1 draws the "
                      "exact frames on two GPUs")
  p.add_argument("--renderer", default=d.renderer, metavar="{" + ",".join(loop.RENDERERS) + "}",
                 help="for the protocol: pool (MuJoCo's pixels) or jax (the JAX ray caster); "
                      "the extras render with the pool")
  p.add_argument("--out", default=None, help="default: RUN_DIR/eval")
  p.add_argument("--no-progress", action="store_true",
                 help="no progress bar: a line per block on stderr")
  p.add_argument("--max-envs", type=int, default=None,
                 help="at most this many envs per block, all agents' together (default: "
                      "every episode in one block)")
  p.add_argument("--invariance", action="store_true",
                 help="also the encoder-invariance plot (paper Fig. 5) of the first agent")
  p.add_argument("--attention", action="store_true",
                 help="also the encoder attention maps (paper Fig. 7) of the first agent")
  p.add_argument("--video", action="store_true",
                 help="also an episode video across visual seeds (MP4, else GIF)")
  p.add_argument("--skip-protocol", action="store_true",
                 help="only the extras asked for")
  compile_cache.add_arguments(p)
  a = p.parse_args(argv)
  try:
    cfg = EvalConfig(visual_seeds=a.visual_seeds, dynamics_seeds=a.dynamics_seeds,
                     train_episodes=a.train_episodes, seed=a.seed, quality=a.quality,
                     workers=a.workers, egl_devices=a.egl_devices, renderer=a.renderer,
                     max_envs=a.max_envs, moving_intensities=a.moving_intensities,
                     conditions=tuple(a.conditions.split(",")) if a.conditions else None)
    try:
      agents = [int(x) for x in a.agents.split(",")] if a.agents else None
    except ValueError:
      raise ValueError(f"--agents takes comma-separated agent indices, got {a.agents!r}")
    task = check_run(a.run_dir, agents).task
    if a.skip_protocol:
      from dmcr_jax.visuals.tiled import check_quality
      check_quality(cfg.quality)
      loop.check_renderer(cfg.renderer, cfg.quality, cfg.workers, cfg.egl_devices)
    else:
      check_eval_config(cfg, task)
  except (ValueError, FileNotFoundError) as e:
    p.error(str(e))
  out = a.out or os.path.join(a.run_dir, "eval")
  compile_cache.use(compile_cache.chosen(a))
  try:
    if not a.skip_protocol:
      summary = evaluate(a.run_dir, cfg, out_dir=out, agents=agents,
                         progress=not a.no_progress)
      print(markdown(summary))
      if len({r["train_look"] for r in summary["agents"]}) > 1:
        print(few_shot_markdown(summary, few_shot_rows(summary)))
        print(f"wrote {out}/few_shot.png, few_shot.md and few_shot.json")
    from dmcr_jax.train import analysis
    first = (agents or [0])[0]
    extra = dict(seed=cfg.seed, quality=cfg.quality, workers=cfg.workers)
    if a.invariance:
      analysis.encoder_invariance(a.run_dir, out, agent=first, looks=cfg.visual_seeds,
                                  **extra)
      print(f"wrote {out}/invariance.png and invariance.json")
    if a.attention:
      print("wrote", analysis.attention_maps(a.run_dir, out, agent=first, **extra))
    if a.video:
      print("wrote", analysis.episode_video(a.run_dir, out, agent=first, **extra))
  except (ValueError, FileNotFoundError) as e:
    sys.exit(f"evaluate: error: {e}")


if __name__ == "__main__":
  main()
