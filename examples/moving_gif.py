"""A GIF of one episode per moving factor: static, camera, light, body, floor,
background and all, side by side (docs/moving.gif).

    python -m examples.moving_gif --out docs/moving.gif

Every tile steps the same physics (same dynamics seed, same random actions) from
the same visual seed; only the moving factor differs. Frames are taken every
`--every` agent steps. See docs/moving.md.
"""

from __future__ import annotations

import argparse

import numpy as np

CONDITIONS = ("none", "camera", "light", "body", "floor", "background", "all")


def episode_frames(task: str, moving: str, intensity: float, *, steps: int, every: int,
                   size: int, visual_seed: int, renderer: str, seed: int) -> np.ndarray:
  """uint8 (steps // every, size, size, 3): one env's frames under `moving`."""
  import dmcr_jax
  rng = np.random.default_rng(seed)
  options = dict(workers=1) if renderer == "pool" else {}
  with dmcr_jax.make(task, num_envs=1, visual_seeds=visual_seed, vary="all",
                     image_size=size, frame_stack=1, seed=seed, renderer=renderer,
                     moving=None if moving == "none" else moving, intensity=intensity,
                     **options) as env:
    obs, _ = env.reset(seed=seed)
    frames = []
    for t in range(steps):
      if t % every == 0:
        frames.append(np.asarray(obs)[0])
      action = rng.uniform(env.single_action_space.low, env.single_action_space.high)
      obs, *_ = env.step(action[None].astype(np.float32))
  return np.stack(frames)


def label(frames: np.ndarray, text: str, height: int = 11) -> np.ndarray:
  """`frames` (T, H, W, 3) with `text` written in a black band above them."""
  from PIL import Image, ImageDraw
  band = Image.new("RGB", (frames.shape[2], height))
  ImageDraw.Draw(band).text((2, 0), text, fill=(255, 255, 255))
  band = np.broadcast_to(np.asarray(band), (len(frames),) + np.asarray(band).shape)
  return np.concatenate([band, frames], axis=1)


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--task", default="walker-walk")
  p.add_argument("--intensity", type=float, default=0.2)
  p.add_argument("--steps", type=int, default=200, help="agent steps of the episode shown")
  p.add_argument("--every", type=int, default=4, help="agent steps between GIF frames")
  p.add_argument("--size", type=int, default=64)
  p.add_argument("--visual-seed", type=int, default=0, help="0: dm_control's look")
  p.add_argument("--renderer", default="pool", choices=("pool", "jax"))
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--out", default="docs/moving.gif")
  a = p.parse_args(argv)
  import imageio
  tiles = [label(episode_frames(a.task, c, a.intensity, steps=a.steps, every=a.every,
                                size=a.size, visual_seed=a.visual_seed,
                                renderer=a.renderer, seed=a.seed), c)
           for c in CONDITIONS]
  strip = np.concatenate(tiles, axis=2)
  imageio.mimsave(a.out, list(strip), duration=0.08, loop=0)
  print(f"wrote {a.out}: {len(strip)} frames of {strip.shape[2]}x{strip.shape[1]}")


if __name__ == "__main__":
  main()
