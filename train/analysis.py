"""What a trained encoder sees: invariance to looks (paper Fig. 5), attention maps
(paper Fig. 7 / appendix) and episode videos across visual seeds.

- `encoder_invariance`: one physical state (reached by the agent from a fixed
  start at the training look) rendered under many held-out looks that change one
  factor (the paper: floor) or all of them; the per-dimension standard deviation
  of the encoder's features over those looks, sorted (0 everywhere = a perfectly
  invariant encoder). Every env of the batch starts from env 0's state and
  receives env 0's actions, so all of them hold the same physical state.
- `attention_maps`: the channel mean of each ReLU'd convolution of the encoder,
  upsampled and overlaid on the observation, for the training look and under a
  changed floor.
- `episode_video`: one episode per visual seed, tiled into one MP4 (GIF if no
  ffmpeg is available).
"""

from __future__ import annotations

import json
import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.protocol_plan import held_out_seeds
from dmcr_jax.train import layouts, loop, sac
from dmcr_jax.train.networks import center_crop
from dmcr_jax.train.step import to_env_action


@jax.jit
def greedy_action(agent: sac.AgentState, obs: jax.Array) -> jax.Array:
  """The evaluation policy of one agent (`evaluate.greedy_policy`), jitted: tanh of
  the mean action, (N, A) in [−1, 1]."""
  return sac.act(agent, obs, None, deterministic=True)


def _agent(run_dir: str, index: int):
  cfg, stacked, step = loop.load_run(run_dir)
  k = stacked.step.shape[0]
  if not 0 <= index < k:
    raise ValueError(f"agent must be in [0, {k}), got {index}")
  return cfg, jax.tree.map(lambda x: x[index], stacked), step


def _one_training_look(cfg: loop.TrainConfig, agent: int) -> int:
  """An agent's training look as one seed (a few-shot range's first seed)."""
  look = cfg.agent_looks()[agent]
  return look if isinstance(look, int) else int(look.start)


def _make_env(cfg: loop.TrainConfig, n: int, seeds, vary: str, quality: str,
              workers: int | None, seed: int):
  import dmcr_jax
  return dmcr_jax.make(cfg.task, num_envs=n, visual_seeds=seeds, vary=vary,
                       frame_skip=cfg.action_repeat, frame_stack=cfg.frame_stack,
                       image_size=cfg.image_size, seed=seed, quality=quality,
                       workers=workers)


def same_state_observations(env, agent, steps: int, seed: int = 0) -> np.ndarray:
  """Observations of one physical state under each env's look.

  Resets `env`, gives every env env 0's state, then takes `steps` agent steps in
  which every env receives the action the agent picks from env 0's observation.

  Returns:
    uint8 (N, H, W, C): the observations after those steps.
  """
  env.reset(seed=seed)
  first = jax.tree.map(lambda x: jnp.broadcast_to(x[:1], x.shape), env.state)
  obs, _ = env.set_state(first.replace(visual_seed=env.state.visual_seed))
  low, high = env.single_action_space.low, env.single_action_space.high
  for _ in range(steps):
    action = np.asarray(greedy_action(agent, obs[:1]))
    obs, *_ = env.step(to_env_action(np.repeat(action, env.num_envs, 0), low, high))
  return obs


def encoder_invariance(run_dir: str, out_dir: str, agent: int = 0, looks: int = 100,
                       steps: int = 20, vary: tuple[str, ...] = ("floor", "all"),
                       seed: int = 0, quality: str = "exact",
                       workers: int | None = None) -> dict:
  """The encoder's feature std over looks of one state (paper Fig. 5); PNG + JSON.

  Args:
    run_dir: a `train` output folder.
    out_dir: where invariance.json / invariance.png go.
    agent: which agent of the run.
    looks: held-out visual seeds per factor setting.
    steps: agent steps from the start before the state is taken.
    vary: factor settings to compare (each a `vary` argument).
    seed: seeds the looks' draw and the start state.
    quality, workers: render options.

  Returns:
    "std": {vary: sorted per-dimension std (list)}; "physical_state_equal":
    {vary: all envs hold env 0's qpos}; "looks_differing": {vary: how many
    observations differ from the first held-out one}; and the run's details.
  """
  cfg, state, step = _agent(run_dir, agent)
  train_look = _one_training_look(cfg, agent)
  seeds = np.concatenate([[train_look], held_out_seeds(looks, seed)])
  result = dict(run_dir=run_dir, agent=agent, checkpoint_step=step, looks=looks,
                steps=steps, std={}, physical_state_equal={}, looks_differing={})
  for setting in vary:
    with _make_env(cfg, looks + 1, seeds, setting, quality, workers, seed) as env:
      obs = same_state_observations(env, state, steps, seed)
      qpos = np.asarray(env.state.task.data.qpos)
      result["physical_state_equal"][setting] = bool((qpos == qpos[:1]).all())
      result["looks_differing"][setting] = int((obs[1:] != obs[1:2]).any(axis=(1, 2, 3)).sum())
    features = np.asarray(state.networks.encoder.apply(state.params["encoder"],
                                                       jnp.asarray(obs[1:])))
    result["std"][setting] = np.sort(features.std(axis=0)).tolist()
  os.makedirs(out_dir, exist_ok=True)
  with open(os.path.join(out_dir, "invariance.json"), "w") as f:
    json.dump(result, f, indent=1)
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, ax = plt.subplots(figsize=(5, 3.2))
  for setting, std in result["std"].items():
    ax.plot(std, marker=".", label=f"vary {setting}")
  ax.set_xlabel("feature dimension (sorted by std)")
  ax.set_ylabel("std over looks")
  ax.set_title(f"{cfg.task}: encoder output over {looks} looks of one state", fontsize=9)
  ax.legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(os.path.join(out_dir, "invariance.png"), dpi=100)
  plt.close(fig)
  return result


def conv_activations(encoder, params, obs: jax.Array) -> list[jax.Array]:
  """The channel mean of every ReLU'd convolution of `encoder`: [(B, h_i, w_i)].

  The encoder runs on pixels (``impl="pixels"``: the same function) so that every
  layer's output is an image.
  """
  _, state = encoder.clone(impl="pixels").apply(
      params, obs, capture_intermediates=lambda m, _: isinstance(m, layouts.Conv),
      mutable=["intermediates"])
  inter = state["intermediates"]
  names = sorted((k for k in inter if k.startswith("conv")), key=lambda k: int(k[4:]))
  return [jnp.mean(nn.relu(inter[k]["__call__"][0].astype(jnp.float32)), axis=-1)
          for k in names]


def attention_maps(run_dir: str, out_dir: str, agent: int = 0, steps: int = 20,
                   seed: int = 0, quality: str = "exact", workers: int | None = None) -> str:
  """Encoder activation maps for the training look and a changed floor (PNG path)."""
  cfg, state, _ = _agent(run_dir, agent)
  train_look = _one_training_look(cfg, agent)
  seeds = np.array([train_look, held_out_seeds(1, seed)[0]])
  with _make_env(cfg, 2, seeds, "floor", quality, workers, seed) as env:
    obs = same_state_observations(env, state, steps, seed)
  if state.networks.encoder.input_size is not None:  # CURL: show what the encoder sees
    obs = np.asarray(center_crop(jnp.asarray(obs), state.networks.encoder.input_size))
  maps = [np.asarray(m) for m in conv_activations(state.networks.encoder,
                                                  state.params["encoder"], jnp.asarray(obs))]
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  rows, cols = 2, 1 + len(maps)
  fig, axes = plt.subplots(rows, cols, figsize=(1.9 * cols, 2.0 * rows))
  for r, label in enumerate(("training look", "changed floor")):
    frame = obs[r, ..., -3:]
    axes[r, 0].imshow(frame)
    axes[r, 0].set_title(label, fontsize=8)
    for c, m in enumerate(maps, start=1):
      heat = np.asarray(jax.image.resize(m[r], frame.shape[:2], "bilinear"))
      axes[r, c].imshow(frame)
      axes[r, c].imshow(heat, cmap="jet", alpha=0.5)
      axes[r, c].set_title(f"conv {c - 1}", fontsize=8)
  for ax in axes.flat:
    ax.axis("off")
  fig.tight_layout()
  os.makedirs(out_dir, exist_ok=True)
  path = os.path.join(out_dir, "attention.png")
  fig.savefig(path, dpi=100)
  plt.close(fig)
  return path


def episode_video(run_dir: str, out_dir: str, agent: int = 0, looks: int = 4,
                  vary: str = "all", seed: int = 0, quality: str = "exact",
                  workers: int | None = None, scale: int = 2, fps: int = 30) -> str:
  """One episode of the agent under the training look and `looks` − 1 held-out
  looks, tiled side by side; MP4 (GIF when ffmpeg is missing). Returns the path."""
  import imageio.v2 as imageio
  cfg, state, _ = _agent(run_dir, agent)
  train_look = _one_training_look(cfg, agent)
  seeds = np.concatenate([[train_look], held_out_seeds(looks - 1, seed)])
  frames = []
  with _make_env(cfg, looks, seeds, vary, quality, workers, seed) as env:
    obs, _ = env.reset(seed=seed)
    low, high = env.single_action_space.low, env.single_action_space.high
    for _ in range(env.episode_length):
      tile = np.concatenate(list(obs[..., -3:]), axis=1)
      frames.append(np.repeat(np.repeat(tile, scale, 0), scale, 1))
      action = to_env_action(np.asarray(greedy_action(state, obs)), low, high)
      obs, *_ = env.step(action)
  os.makedirs(out_dir, exist_ok=True)
  path = os.path.join(out_dir, "episode.mp4")
  try:
    imageio.mimwrite(path, frames, fps=fps, macro_block_size=1)
  except Exception:  # no ffmpeg backend: fall back to a GIF
    path = os.path.join(out_dir, "episode.gif")
    imageio.mimwrite(path, frames, duration=1.0 / fps)
  return path
