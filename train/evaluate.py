"""Zero-shot generalisation of trained agents: the DMCR paper's protocol (Sec. 4.2–4.3).

For a `train` run, each agent (deterministic policy: tanh of the mean action) is
evaluated
- at its training look over `train_episodes` initial states (paper: 100), the
  "train" return;
- under each visual condition over `visual_seeds` held-out looks × `dynamics_seeds`
  initial states each (paper: 100 × 3 = 300 episodes): "none" (nothing varied),
  one factor at a time (light, camera, body, floor, then background, target and
  reflectance where they apply to the domain) and "all".
Conditions change factors away from dm_control's default look, as in the paper,
whose agents trained on it (visual seed 0). Test looks are drawn from the
held-out `dmcr_jax.TEST_SEEDS`, which no training range can overlap, with a NumPy
generator seeded by `EvalConfig.seed`. All agents run in one env, a block of V·D
envs per agent: env i of every block shows the same look and starts from the same
initial state (the same per-env reset seed, `reset_seeds`), so agents and
conditions differ only in the policy and the looks, and every condition's episodes
of all agents run as one batch; the looks are swapped with
`PixelVectorEnv.set_visuals` without recompiling the physics. When an agent's
training look is seed 0 (dm_control's, which "none" also shows), its train
episodes are the first `train_episodes` of its "none" block (same looks, same
initial states); the train batch runs only for the agents that need it.

The generalisation error of a condition is E_G = (train − test) / train (paper
Sec. 3). Outputs: a JSON file, a Markdown table laid out like the paper's Table 4
(with the paper's row for the task and each method when it has one) and a bar
chart. A run that trained several augmentations (``dmcr-train --aug drq,cj+drq,mine+drq``)
is compared side by side: per augmentation the mean over its seeds, each
condition's return and E_G, beside the paper's rows (``"augs"`` in the JSON; one
row per augmentation in both tables, per augmentation and training-look range in
a few-shot run; grouped bars in the chart).

Few-shot runs (`dmcr-train --visual-seeds levels:1,10,…`, one agent per training-look
range): every agent meets the same held-out test looks; an agent's "train" return
is taken at looks drawn from its own range (seeds drawn with the same generator
seed). The run's generalisation curve follows: test return per condition and
E_G against the number of training looks (`few_shot.json`, `few_shot.md`,
`few_shot.png`), with the zero-shot agents' (levels:1, dm_control's look) "all"
returns as reference lines where the run has them.

An interrupted evaluation goes on where it stopped when called again with the same
arguments: finished conditions wait in the output folder's `progress.npz`.

    dmcr-evaluate runs/cartpole-balance-drq            # or: python -m dmcr_jax.train.evaluate …
    dmcr-evaluate runs/cartpole-balance-drq --invariance --attention --video
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import numpy as np

from dmcr_jax import SeedRange
from dmcr_jax._files import write_atomic
from dmcr_jax.checks import positive_int
from dmcr_jax.env import default_frame_skip
from dmcr_jax.train import loop, paper_results, sac
from dmcr_jax.train.step import to_env_action

FACTOR_CONDITIONS: tuple[str, ...] = ("light", "camera", "body", "floor", "background",
                                      "target", "reflectance")
"""Single-factor conditions in table order (those that apply to a domain are used)."""


def conditions_for(task: str) -> tuple[str, ...]:
  """The conditions evaluated for `task`: none, each applicable factor, all."""
  from dmcr_jax.visuals.factors import active_factors
  domain = task.split("-", 1)[0]
  factors = active_factors(domain, "all")
  return ("none",) + tuple(f for f in FACTOR_CONDITIONS if f in factors) + ("all",)


def held_out_seeds(n: int, seed: int = 0) -> np.ndarray:
  """`n` distinct visual seeds drawn from `dmcr_jax.TEST_SEEDS` (int64, sorted).

  Args:
    n: how many.
    seed: seed of the NumPy generator that draws them.

  Returns:
    (n,) seeds, all in [TEST_SEEDS.start, TEST_SEEDS.stop).
  """
  from dmcr_jax import TEST_SEEDS
  rng = np.random.default_rng(seed)
  size = TEST_SEEDS.stop - TEST_SEEDS.start
  seeds = TEST_SEEDS.start + np.sort(rng.choice(size, size=n, replace=False))
  return seeds.astype(np.int64)


def generalization_error(train: float, test: float) -> float:
  """E_G = (train − test) / train (paper Sec. 3); NaN when train is 0."""
  return float("nan") if train == 0 else (train - test) / train


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
    workers: render workers (None: one per core).
    egl_devices: EGL device indices the render workers are spread over (None:
      MuJoCo's default; `dmcr_jax.visuals.render_pool`).
    renderer: "pool" (MuJoCo's pixels from the CPU render pool, the reference) or
      "jax" (the JAX ray caster on the device: fast, close to MuJoCo's pixels but
      not equal; `quality`, `workers` and `egl_devices` do not apply).
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
  valid = conditions_for(task)
  conditions = valid if cfg.conditions is None else tuple(cfg.conditions)
  bad = [c for c in conditions if c not in valid]
  if bad or not conditions:
    raise ValueError(f"conditions {bad or conditions!r} are not valid for {task}; valid: "
                     f"{', '.join(valid)}")
  return conditions


def render_options(cfg: EvalConfig) -> dict:
  """`dmcr_jax.make`'s renderer keywords for `cfg`."""
  if cfg.renderer == "jax":
    return dict(renderer="jax")
  return dict(quality=cfg.quality, workers=cfg.workers, egl_devices=cfg.egl_devices)


@jax.jit
def greedy_action(agent: sac.AgentState, obs: jax.Array) -> jax.Array:
  """The evaluation policy: tanh of the mean action, (N, A) in [−1, 1]."""
  return sac.act(agent, obs, None, deterministic=True)


@jax.jit
def greedy_actions(agents: sac.AgentState, obs: jax.Array) -> jax.Array:
  """`greedy_action` of K stacked agents, each on its own block of N envs.

  Args:
    agents: K agents stacked on a leading axis.
    obs: uint8 observations (K·N, H, W, C), agent k's in rows [k·N, (k+1)·N).

  Returns:
    (K·N, A) actions in [−1, 1], in the order of `obs`.
  """
  k = agents.step.shape[0]
  blocks = obs.reshape((k, obs.shape[0] // k) + obs.shape[1:])
  actions = jax.vmap(greedy_action)(agents, blocks)
  return actions.reshape((obs.shape[0],) + actions.shape[2:])


def reset_seeds(n: int, seed: int) -> np.ndarray:
  """The per-env reset seeds of one agent's block, (n,) uint32 in [0, 2**32): env i's
  initial states depend on (`seed`, i) alone, whatever the number of agents."""
  return np.random.default_rng((seed, 1)).integers(0, 2**32, n, dtype=np.uint32)


def run_episodes(env, policy, seed) -> np.ndarray:
  """One episode in every env of `env`, all starting together; their returns (N,).

  Args:
    env: a `PixelVectorEnv`.
    policy: uint8 observations (N, H, W, C) → actions in [−1, 1], (N, A).
    seed: the reset seed (fixes the initial states): an int, or one per env.
  """
  obs, _ = env.reset(seed=seed)
  low, high = env.single_action_space.low, env.single_action_space.high
  for _ in range(env.episode_length):
    action = to_env_action(np.asarray(policy(obs)), low, high)
    obs, _, _, truncated, info = env.step(action)
  if not truncated.all():
    raise RuntimeError("episodes did not all end together; the env's episode length is off")
  return np.asarray(info["episode_return"], np.float64)


PROGRESS_FILE = "progress.npz"
"""In `evaluate`'s output folder while it runs: the finished passes' returns."""


def load_progress(path: str, key: dict) -> tuple[dict, float]:
  """The passes finished by an earlier, interrupted `evaluate` of the same protocol.

  Args:
    path: the progress file (`PROGRESS_FILE` in the output folder).
    key: what fixes the episodes (run, checkpoint step, agents, protocol); a file
      written under another key is ignored.

  Returns:
    ({pass: (returns (K, n) float64, wall s)}, wall s spent on them); empty when
    there is no usable file.
  """
  if not os.path.exists(path):
    return {}, 0.0
  try:
    with np.load(path) as f:
      meta = json.loads(str(f["meta"]))
      if meta["key"] != json.loads(json.dumps(key)):
        print(f"evaluate: ignoring {path} (written for another run or protocol)",
              file=sys.stderr, flush=True)
        return {}, 0.0
      done = {name: (f[f"returns/{name}"], wall) for name, wall in meta["walls"].items()}
  except (OSError, ValueError, KeyError) as e:
    print(f"evaluate: ignoring {path} ({e})", file=sys.stderr, flush=True)
    return {}, 0.0
  return done, float(meta["elapsed_s"])


def save_progress(path: str, key: dict, done: dict, elapsed_s: float) -> None:
  """Writes the finished passes (`load_progress`'s format) atomically: a crash
  while writing leaves the previous file."""
  meta = dict(key=key, walls={name: wall for name, (_, wall) in done.items()},
              elapsed_s=elapsed_s)
  arrays = {f"returns/{name}": returns for name, (returns, _) in done.items()}
  write_atomic(path, lambda f: np.savez(f, meta=json.dumps(meta), **arrays))


def _is_default_look(train_look) -> bool:
  """Whether every training episode showed seed 0's look, which "none" also shows
  (a fixed seed 0, or the range levels:1 = [0, 1))."""
  if isinstance(train_look, SeedRange):
    return train_look == SeedRange(0, 1)
  return bool(np.all(np.asarray(train_look) == 0))


def train_look_seeds(train_look, n: int, seed: int) -> np.ndarray:
  """`n` visual seeds of an agent's training looks, one per env of the train batch:
  the fixed seed, or draws from its range with a NumPy generator seeded by `seed`
  (so every agent of a run is measured with one compilation of fixed seeds)."""
  if isinstance(train_look, SeedRange):
    rng = np.random.default_rng(seed)
    return rng.integers(train_look.start, train_look.stop, n).astype(np.int64)
  return np.full(n, int(train_look), np.int64)


def _check_disjoint(test_seeds: np.ndarray, train_look) -> None:
  if isinstance(train_look, SeedRange):
    inside = (test_seeds >= train_look.start) & (test_seeds < train_look.stop)
  else:
    inside = np.isin(test_seeds, np.atleast_1d(train_look))
  if inside.any():
    raise RuntimeError(f"test visual seeds {test_seeds[inside][:4]} lie in the training "
                       "looks; the held-out range must never overlap them")


def evaluate(run_dir: str, cfg: EvalConfig = EvalConfig(), out_dir: str | None = None,
             agents: list[int] | None = None, progress: bool = True) -> dict:
  """Runs the protocol for a `train` run's agents; writes JSON, Markdown and PNG.

  Args:
    run_dir: the run's output folder (config.json + checkpoints).
    cfg: the protocol's sizes and options.
    out_dir: where the results go (default `<run_dir>/eval`).
    agents: indices of the agents to evaluate (default: all).
    progress: show a progress bar (else a line per condition on stderr).

  Returns:
    The results (also in `<out_dir>/eval.json`, where an undefined E_G, NaN
    here, is null): per agent the train return, every condition's mean, std and
    per-episode returns, E_G per condition, and the wall time (of every attempt,
    when resumed).

  Each finished condition is kept in `<out_dir>/progress.npz` until the results
  are written: called again after an interruption with the same run, agents and
  protocol, it runs only the conditions still missing (the episodes are the same
  either way: every condition's looks and initial states follow from `cfg.seed`).

  Raises:
    FileNotFoundError: no config.json or no checkpoint in `run_dir`.
    ValueError: a bad `cfg` or agent index (before anything is loaded).
  """
  import dmcr_jax
  conditions = check_eval_config(cfg, check_run(run_dir, agents).task)
  train_cfg, stacked, step = loop.load_run(run_dir)
  specs = train_cfg.agents()
  chosen = list(range(len(specs))) if agents is None else list(agents)
  out_dir = out_dir or os.path.join(run_dir, "eval")
  os.makedirs(out_dir, exist_ok=True)
  test_seeds = held_out_seeds(cfg.visual_seeds, cfg.seed)
  looks = train_cfg.agent_looks()
  for look in set(looks):
    _check_disjoint(test_seeds, look)
  per_env_seeds = np.repeat(test_seeds, cfg.dynamics_seeds)
  n = per_env_seeds.size
  several = len(loop.parse_visual_seeds(train_cfg.visual_seeds)) > 1

  shares = {a: "none" in conditions and _is_default_look(looks[a]) for a in chosen}
  k = len(chosen)
  env_reset_seeds = np.tile(reset_seeds(n, cfg.seed), k)
  test_looks = np.tile(per_env_seeds, k)
  agents_chosen = jax.tree.map(lambda x: x[np.asarray(chosen)], stacked)
  policy = lambda obs: greedy_actions(agents_chosen, obs)
  t_start = time.perf_counter()
  env = dmcr_jax.make(train_cfg.task, num_envs=k * n, visual_seeds=test_looks,
                      vary=train_cfg.vary, frame_skip=train_cfg.action_repeat,
                      frame_stack=train_cfg.frame_stack, image_size=train_cfg.image_size,
                      seed=cfg.seed, **render_options(cfg))
  need_train = [a for a in chosen if not shares[a]]
  # Every finished pass is kept in the output folder, so that evaluating again after
  # a crash or a machine taken back runs only the passes still missing.
  progress_path = os.path.join(out_dir, PROGRESS_FILE)
  progress_key = dict(run_dir=os.path.abspath(run_dir), checkpoint_step=int(step),
                      agents=chosen, conditions=list(conditions),
                      config={name: v for name, v in dataclasses.asdict(cfg).items()
                              if name not in ("workers", "egl_devices")})  # same pixels either way
  done, earlier_s = load_progress(progress_path, progress_key)
  if done:
    print(f"evaluate: resuming from {progress_path}: {', '.join(done)} already done",
          file=sys.stderr, flush=True)
  bar, passes, finished = None, len(conditions) + bool(need_train), len(done)
  if progress:
    from tqdm.auto import tqdm
    bar = tqdm(total=passes, initial=finished, desc="evaluate", unit="condition")

  def run(visual_seeds, vary: str, label: str) -> tuple[np.ndarray, float]:
    """Every agent's block under these looks: returns (K, n) and the wall time."""
    nonlocal finished
    env.set_visuals(visual_seeds, vary=vary)
    t0 = time.perf_counter()
    returns = run_episodes(env, policy, env_reset_seeds).reshape(k, n)
    wall, finished = time.perf_counter() - t0, finished + 1
    if bar is not None:
      bar.update(1)
      bar.set_postfix(condition=label, ret=f"{returns.mean():.0f}")
    else:  # without a bar, a line per condition on stderr
      print(f"evaluate: {label} done ({finished}/{passes}), mean return "
            f"{returns.mean():.1f}, {wall:.0f} s", file=sys.stderr, flush=True)
    return returns, wall

  def keep(name: str, result: tuple[np.ndarray, float]) -> None:
    done[name] = result
    save_progress(progress_path, progress_key, done,
                  earlier_s + time.perf_counter() - t_start)

  with env:
    for condition in conditions:
      if condition not in done:
        keep(condition, run(test_looks, "none" if condition == "none" else condition,
                            condition))
    if need_train and "train" not in done:
      # Agents that share "none" keep dm_control's look in their block (unused).
      train_seeds = np.concatenate([per_env_seeds if shares[a] else
                                    train_look_seeds(looks[a], n, cfg.seed) for a in chosen])
      keep("train", run(train_seeds, train_cfg.vary, "train"))
  results = []
  for i, a in enumerate(chosen):
    seed, aug = specs[a]
    algo = train_cfg.sac.algo
    row = dict(agent=a, seed=seed, aug=aug, algo=algo,
               method=paper_results.method_name(algo, aug),
               train_look=loop.look_label(looks[a]), looks=loop.num_looks(looks[a]),
               conditions={})
    # The training look is the default one, which "none" shows too, and the same
    # reset seeds give the same initial states: the train episodes are the first
    # ones of the agent's "none" block.
    train, train_wall = done["none" if shares[a] else "train"]
    train_returns = train[i, :cfg.train_episodes]
    row["train"] = dict(mean=float(train_returns.mean()), std=float(train_returns.std()),
                        episodes=train_returns.tolist(), wall_s=train_wall)
    for condition in conditions:
      returns, wall = done[condition]
      mean = float(returns[i].mean())
      row["conditions"][condition] = dict(
          mean=mean, std=float(returns[i].std()), episodes=returns[i].tolist(),
          e_g=generalization_error(row["train"]["mean"], mean), wall_s=wall)
    results.append(row)
  if bar is not None:
    bar.close()
  summary = dict(run_dir=run_dir, task=train_cfg.task, checkpoint_step=step,
                 action_repeat=train_cfg.action_repeat or default_frame_skip(train_cfg.task),
                 device=jax.devices()[0].device_kind, training=training_record(run_dir),
                 config=dataclasses.asdict(cfg), conditions=list(conditions),
                 test_visual_seeds=test_seeds.tolist(),
                 train_look=str(train_cfg.visual_seeds), agents=results,
                 wall_s=earlier_s + time.perf_counter() - t_start)
  summary["mean"] = _mean_row(results, conditions)
  summary["augs"] = aug_groups(summary)
  with open(os.path.join(out_dir, "eval.json"), "w") as f:
    json.dump(loop.json_safe(summary), f, indent=1, allow_nan=False)  # NaN E_G → null
  with open(os.path.join(out_dir, "eval.md"), "w") as f:
    f.write(markdown(summary))
  plot(summary, os.path.join(out_dir, "eval.png"))
  if several:
    write_few_shot(summary, out_dir)
  os.remove(progress_path)
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


def _mean_row(results: list[dict], conditions) -> dict:
  """The agents' mean train return, condition means and E_G of those means."""
  train = float(np.mean([r["train"]["mean"] for r in results]))
  means = {c: float(np.mean([r["conditions"][c]["mean"] for r in results]))
           for c in conditions}
  return dict(train=train, conditions=means,
              e_g={c: generalization_error(train, m) for c, m in means.items()})


def _label(row: dict) -> str:
  """An agent's name in the table: its augmentation (SAC+AUG) or algorithm (+ aug)."""
  algo, aug = row.get("algo", "sac_aug"), row["aug"]
  if algo == "sac_aug":
    return aug
  return algo if aug == "none" else f"{algo}, {aug}"


def _several_ranges(summary: dict) -> bool:
  """Whether the summary's agents trained on more than one training-look range."""
  return len({r.get("train_look") for r in summary["agents"]}) > 1


def aug_groups(summary: dict) -> list[dict]:
  """The agents grouped by augmentation (by algorithm and augmentation), in run order;
  in a run with several training-look ranges, by augmentation and range (a mean
  over agents trained on different looks would mix what the few-shot curve
  separates).

  Args:
    summary: `evaluate`'s results (its "agents", "conditions" and "task").

  Returns:
    One dict per group: label (`_label`), aug, method (the paper's name or None),
    agents (indices), seeds, `_mean_row`'s train / conditions / e_g over its
    agents, and paper: the paper's Table 4 row for the task and method as
    {"returns": {condition: return}, "e_g": {condition: E_G}} (its "None"
    column taken as the train return), or None.
  """
  conditions = summary["conditions"]
  ranges = _several_ranges(summary)
  groups: dict[str, list[dict]] = {}
  for r in summary["agents"]:
    groups.setdefault(_label(r) + (f", {r['train_look']}" if ranges else ""), []).append(r)
  out = []
  for label, rows in groups.items():
    method = rows[0].get("method")
    table = paper_results.table4(summary["task"], method) if method else None
    paper = None if table is None else dict(
        returns=table, e_g={c: generalization_error(table["none"], table[c])
                            for c in conditions if c in table})
    out.append(dict(label=label, aug=rows[0]["aug"], method=method,
                    agents=[r["agent"] for r in rows], seeds=[r["seed"] for r in rows],
                    **_mean_row(rows, conditions), paper=paper))
  return out


def _render_words(cfg: dict) -> str:
  if cfg.get("renderer", "pool") == "jax":
    return "rendered by the JAX ray caster"
  return f"render quality {cfg['quality']}"


def markdown(summary: dict) -> str:
  """The results as the paper's Table 4 (returns per condition) plus train and E_G.

  Rows: every agent; the mean over agents (per augmentation when the run trained
  several, if one has several seeds); the paper's row for each method it has. A second table gives E_G per
  condition for those means and the paper's rows, augmentations side by side.
  """
  conditions = summary["conditions"]
  cfg = summary["config"]
  groups = summary.get("augs") or aug_groups(summary)
  head = ["agent", "train"] + conditions + ["E_G (all)" if "all" in conditions else "E_G"]
  lines = [f"Zero-shot evaluation of `{summary['run_dir']}` ({summary['task']}, checkpoint "
           f"step {summary['checkpoint_step']:,}): train = mean return over "
           f"{cfg['train_episodes']} initial states at the training look "
           f"({summary['train_look']}); each condition = mean over {cfg['visual_seeds']} "
           f"held-out visual seeds × {cfg['dynamics_seeds']} initial states; "
           f"{_render_words(cfg)}; E_G = (train − test) / train. Wall time "
           f"{summary['wall_s']:.0f} s.", "",
           "| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
  last = "all" if "all" in conditions else conditions[-1]
  pct = lambda e: f"{100 * e:.1f} %" if e is not None and np.isfinite(e) else "–"

  def line(label, train, means, e_g):
    cells = [label, f"{train:.1f}"] + [f"{means[c]:.1f}" for c in conditions]
    return "| " + " | ".join(cells + [pct(e_g)]) + " |"

  def paper_line(g):
    row = g["paper"]["returns"]
    cells = [f"paper, {g['method']}", f"{row['none']:.1f}"]
    cells += [f"{row[c]:.1f}" if c in row else "–" for c in conditions]
    return "| " + " | ".join(cells + [pct(g["paper"]["e_g"].get(last))]) + " |"

  ranges = _several_ranges(summary)
  for r in summary["agents"]:
    means = {c: r["conditions"][c]["mean"] for c in conditions}
    label = f"seed {r['seed']}, {_label(r)}" + (f", {r['train_look']}" if ranges else "")
    lines.append(line(label, r["train"]["mean"], means, r["conditions"][last]["e_g"]))
  if len(groups) == 1 and len(summary["agents"]) > 1 and not ranges:
    m = summary["mean"]
    lines.append(line("**mean**", m["train"], m["conditions"], m["e_g"][last]))
  elif 1 < len(groups) < len(summary["agents"]):
    for g in groups:
      lines.append(line(f"**{g['label']}** (mean of {len(g['agents'])})", g["train"],
                        g["conditions"], g["e_g"][last]))
  papers = list({g["method"]: g for g in groups if g["paper"] is not None}.values())
  lines += [paper_line(g) for g in papers]
  if papers:
    lines += ["", "Paper rows are its Table 4 (five runs; its \"None\" column, shown "
                  "under both train and none)."]
  lines += ["", "E_G per condition (mean return of each "
            + ("augmentation's agents per training-look range" if ranges
               else "augmentation's agents" if len(groups) > 1 else "agent set")
            + "; paper: from its Table 4 with \"None\" as train):", "",
            "| " + " | ".join(["augmentation", "train"] + conditions) + " |",
            "|---|" + "---:|" * (len(conditions) + 1)]
  for g in groups:
    cells = [g["label"], f"{g['train']:.1f}"] + [pct(g["e_g"][c]) for c in conditions]
    lines.append("| " + " | ".join(cells) + " |")
  for g in papers:
    row = g["paper"]
    cells = [f"paper, {g['method']}", f"{row['returns']['none']:.1f}"]
    cells += [pct(row["e_g"].get(c)) for c in conditions]
    lines.append("| " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def plot(summary: dict, png_path: str) -> None:
  """Grouped bars, one colour per augmentation: mean return at the training look
  and per condition (dots: agents; ×: the paper's row), and E_G per condition."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  conditions = summary["conditions"]
  groups = summary.get("augs") or aug_groups(summary)
  columns = ["train"] + list(conditions)
  x = np.arange(len(columns))
  width = 0.8 / len(groups)
  colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
  fig, (ax, ax_e) = plt.subplots(1, 2, figsize=(2.0 + 1.5 * len(columns), 3.8),
                                 gridspec_kw=dict(width_ratios=(len(columns),
                                                                len(conditions))))
  drawn_papers = set()
  for k, g in enumerate(groups):
    color, dx = colors[k % len(colors)], (k - (len(groups) - 1) / 2) * width
    means = [g["train"]] + [g["conditions"][c] for c in conditions]
    ax.bar(x + dx, means, width, color=color, alpha=0.8,
           label=f"{g['label']} ({len(g['agents'])})")
    for a in g["agents"]:
      r = next(r for r in summary["agents"] if r["agent"] == a)
      ax.plot(x + dx, [r["train"]["mean"]] + [r["conditions"][c]["mean"] for c in conditions],
              "k.", ms=4, alpha=0.6, ls="none")
    ax_e.bar(np.arange(len(conditions)) + dx, [g["e_g"][c] for c in conditions], width,
             color=color, alpha=0.8)
    if g["paper"] is not None and g["method"] not in drawn_papers:
      drawn_papers.add(g["method"])
      row = g["paper"]["returns"]
      ax.plot(np.array([i for i, c in enumerate(columns) if c in row or c == "train"]) + dx,
              [row["none"] if c == "train" else row[c] for c in columns
               if c in row or c == "train"],
              "X", color=color, mec="k", ms=8, mew=0.8, ls="none",
              label=f"paper {g['method']}")
      ax_e.plot([i + dx for i, c in enumerate(conditions) if c in row],
                [g["paper"]["e_g"][c] for c in conditions if c in row],
                "X", color=color, mec="k", ms=8, mew=0.8, ls="none")
  ax.set_xticks(x, columns, rotation=30)
  ax.set_ylabel("mean episode return")
  ax.set_title(f"{summary['task']}: zero-shot returns per visual condition", fontsize=10)
  ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0, -0.22), ncol=2,
            frameon=False)
  ax_e.set_xticks(np.arange(len(conditions)), conditions, rotation=30)
  ax_e.axhline(0, color="k", lw=0.8)
  ax_e.set_ylabel("E_G = (train − test) / train")
  ax_e.set_title("generalisation error (×: paper)", fontsize=10)
  fig.tight_layout()
  fig.savefig(png_path, dpi=100, bbox_inches="tight")
  plt.close(fig)


def few_shot_rows(summary: dict) -> list[dict]:
  """The generalisation curve of a few-shot run: one row per (augmentation, training
  looks), the means over that group's agents (seeds).

  Returns:
    Rows sorted by augmentation then number of looks, each with "aug", "method",
    "looks" (number of training looks), "train_look", "seeds", "train" (mean
    return at the training looks), "conditions" {condition: mean test return},
    "e_g" {condition: E_G of those means} and "all_std" (std of "all" over the
    seeds; 0 for one seed).
  """
  groups: dict[tuple, list[dict]] = {}
  for r in summary["agents"]:
    groups.setdefault((r["aug"], r["looks"], r["train_look"]), []).append(r)
  rows = []
  for (aug, looks, label), agents in sorted(groups.items(), key=lambda kv: kv[0][:2]):
    mean = _mean_row(agents, summary["conditions"])
    row = dict(aug=aug, method=agents[0].get("method"), looks=looks, train_look=label,
               seeds=[r["seed"] for r in agents], train=mean["train"],
               conditions=mean["conditions"], e_g=mean["e_g"])
    if "all" in summary["conditions"]:
      row["all_std"] = float(np.std([r["conditions"]["all"]["mean"] for r in agents]))
    rows.append(row)
  return rows


def zero_shot_references(rows: list[dict]) -> dict[str, float]:
  """{method or augmentation: test return under "all"} of the zero-shot rows
  (trained on dm_control's look alone: levels:1 or seed 0)."""
  return {(r["method"] or r["aug"]): r["conditions"]["all"] for r in rows
          if r["train_look"] in ("levels:1", "seed 0") and "all" in r["conditions"]}


def few_shot_markdown(summary: dict, rows: list[dict]) -> str:
  """The curve as a Markdown table: per augmentation and number of training looks,
  the train return, each condition's test return and E_G (all)."""
  conditions = summary["conditions"]
  cfg = summary["config"]
  last = "all" if "all" in conditions else conditions[-1]
  head = ["augmentation", "training looks", "seeds", "train"] + conditions + [f"E_G ({last})"]
  lines = [f"Few-shot generalisation of `{summary['run_dir']}` ({summary['task']}, "
           f"checkpoint step {summary['checkpoint_step']:,}): one agent per training-look "
           f"range and seed, all tested on the same {cfg['visual_seeds']} held-out visual "
           f"seeds × {cfg['dynamics_seeds']} initial states; train = mean return over "
           f"{cfg['train_episodes']} episodes at looks from the agent's own range; "
           f"{_render_words(cfg)}; means over seeds; E_G = (train − test) / train.", "",
           "| " + " | ".join(head) + " |", "|---|---|---:|" + "---:|" * (len(head) - 3)]
  for r in rows:
    e_g = r["e_g"][last]
    cells = [r["method"] or r["aug"], f"{r['looks']:,} ({r['train_look']})",
             str(len(r["seeds"])), f"{r['train']:.1f}"]
    cells += [f"{r['conditions'][c]:.1f}" for c in conditions]
    cells.append(f"{100 * e_g:.1f} %" if np.isfinite(e_g) else "–")
    lines.append("| " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def plot_few_shot(summary: dict, rows: list[dict], png_path: str) -> None:
  """Test return per condition ("all" bold) and E_G against the number of training
  looks (log x), one line style per augmentation; dashed: the run's zero-shot
  "all" returns (`zero_shot_references`)."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  conditions = summary["conditions"]
  last = "all" if "all" in conditions else conditions[-1]
  augs = list(dict.fromkeys(r["aug"] for r in rows))
  styles = ["-", "--", ":", "-."]
  colours = {c: ("black" if c == "all" else f"C{i}") for i, c in enumerate(conditions)}
  fig, (ax, ax_e) = plt.subplots(1, 2, figsize=(10, 4), gridspec_kw=dict(width_ratios=(3, 2)))
  for j, aug in enumerate(augs):
    mine = [r for r in rows if r["aug"] == aug]
    x = [r["looks"] for r in mine]
    name = mine[0]["method"] or aug
    for c in conditions:
      ax.plot(x, [r["conditions"][c] for r in mine], styles[j % 4], color=colours[c],
              marker="o", ms=3, lw=2.5 if c == last else 1,
              label=f"{c}" if len(augs) == 1 else f"{c}, {name}")
    ax_e.plot(x, [r["e_g"][last] for r in mine], styles[j % 4], color="black", marker="o",
              ms=3, label=name)
  for k, (name, value) in enumerate(zero_shot_references(rows).items()):
    ax.axhline(value, color=f"C{k + len(conditions)}", ls=(0, (5, 3)), lw=1.2,
               label=f"zero-shot {name} ({last})")
  ticks = sorted({r["looks"] for r in rows})
  for a in (ax, ax_e):
    a.set_xscale("log")
    a.set_xticks(ticks, [f"{t:,}" if t < 2**30 else "2^30 (all)" for t in ticks],
                 fontsize=7, rotation=30)
    a.minorticks_off()
    a.set_xlabel("training looks (visual seeds)")
  ax.set_ylabel("test return (held-out looks)")
  ax_e.set_ylabel(f"E_G ({last})")
  ax.set_title(f"{summary['task']}: test return against training looks", fontsize=9)
  ax_e.set_title("generalisation error (train − test) / train", fontsize=9)
  ax.legend(fontsize=6, loc="best", ncol=2)
  ax_e.legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(png_path, dpi=100)
  plt.close(fig)


def write_few_shot(summary: dict, out_dir: str) -> list[dict]:
  """Writes the generalisation curve of a few-shot run's evaluation: few_shot.json
  (rows and zero-shot references), few_shot.md and few_shot.png; returns the rows."""
  rows = few_shot_rows(summary)
  data = dict(task=summary["task"], run_dir=summary["run_dir"],
              checkpoint_step=summary["checkpoint_step"], conditions=summary["conditions"],
              rows=rows, zero_shot=zero_shot_references(rows))
  with open(os.path.join(out_dir, "few_shot.json"), "w") as f:
    json.dump(loop.json_safe(data), f, indent=1, allow_nan=False)
  with open(os.path.join(out_dir, "few_shot.md"), "w") as f:
    f.write(few_shot_markdown(summary, rows))
  plot_few_shot(summary, rows, os.path.join(out_dir, "few_shot.png"))
  return rows


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


def main(argv=None) -> None:
  """`dmcr-evaluate RUN_DIR [options]`."""
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
                 help="comma-separated (default: every condition that applies)")
  p.add_argument("--agents", default=None, help="comma-separated agent indices (default: all)")
  p.add_argument("--quality", default=d.quality, metavar="{" + ",".join(QUALITY) + "}",
                 help="render preset (--renderer pool)")
  p.add_argument("--workers", type=int, default=None,
                 help="render workers (default: one per core, at most 16)")
  p.add_argument("--egl-devices", type=loop.egl_devices_arg, default=None, metavar="D[,D…]",
                 help="EGL device indices the render workers are spread over (default: "
                      "MuJoCo's, MUJOCO_EGL_DEVICE_ID or the first); e.g. 0,1 draws the "
                      "exact frames on two GPUs")
  p.add_argument("--renderer", default=d.renderer, metavar="{" + ",".join(loop.RENDERERS) + "}",
                 help="for the protocol: pool (MuJoCo's pixels) or jax (the JAX ray caster); "
                      "the extras render with the pool")
  p.add_argument("--out", default=None, help="default: RUN_DIR/eval")
  p.add_argument("--no-progress", action="store_true",
                 help="no progress bar: a line per condition on stderr")
  p.add_argument("--invariance", action="store_true",
                 help="also the encoder-invariance plot (paper Fig. 5) of the first agent")
  p.add_argument("--attention", action="store_true",
                 help="also the encoder attention maps (paper Fig. 7) of the first agent")
  p.add_argument("--video", action="store_true",
                 help="also an episode video across visual seeds (MP4, else GIF)")
  p.add_argument("--skip-protocol", action="store_true",
                 help="only the extras asked for")
  a = p.parse_args(argv)
  try:
    cfg = EvalConfig(visual_seeds=a.visual_seeds, dynamics_seeds=a.dynamics_seeds,
                     train_episodes=a.train_episodes, seed=a.seed, quality=a.quality,
                     workers=a.workers, egl_devices=a.egl_devices, renderer=a.renderer,
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
