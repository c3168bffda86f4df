"""A gallery of `dmcr_jax.augment`: one observation under every augmentation.

Like the paper's Figure 8 ("Examples of our augmentation implementations"):
renders a short dm_control rollout (walker-walk by default) with
``physics.render(84, 84, camera_id=0)``, stacks its last three frames into one
84×84×9 observation, applies every augmentation in `dmcr_jax.augment.NAMES` to a
batch of copies of it (so each copy draws its own parameters) and writes a PNG
grid: one labelled cell per augmentation, showing the newest frame of
``--samples`` augmented copies side by side. Headless rendering uses
``MUJOCO_GL=egl`` unless the environment already sets MUJOCO_GL.

Usage::

    python -m dmcr_jax.augment_gallery --out docs/augment_gallery.png
"""

from __future__ import annotations

import argparse
import os

LABELS = {"none": "none (original)", "cj": "cj (Color Jitter)",
          "nr": "nr (Network Randomization)"}


def render_observation(domain: str = "walker", task: str = "walk", steps: int = 20,
                       stack: int = 3, size: int = 84, seed: int = 0):
  """Renders `steps` random-action control steps; stacks the last `stack` frames.

  Args:
    domain: dm_control suite domain.
    task: its task.
    steps: control steps to take (≥ stack).
    stack: frames to stack on the channel axis (oldest first).
    size: rendered height and width.
    seed: seeds the task's initial state and the random actions.

  Returns:
    uint8 numpy array (size, size, 3·stack).
  """
  os.environ.setdefault("MUJOCO_GL", "egl")
  os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
  import numpy as np
  from dm_control import suite

  env = suite.load(domain, task, task_kwargs={"random": seed})
  env.reset()
  spec = env.action_spec()
  rng = np.random.default_rng(seed)
  frames = []
  for _ in range(max(steps, stack)):
    env.step(rng.uniform(spec.minimum, spec.maximum))
    frames.append(env.physics.render(size, size, camera_id=0))
  return np.concatenate(frames[-stack:], axis=-1)


def gallery(obs, names=None, samples: int = 4, seed: int = 5):
  """Augments `samples` copies of `obs` under each name.

  Copy i is augmented in its own call with key ``fold_in(key(seed), i)``, so
  per-batch augmentations (Network Randomization) also show `samples` draws.

  Args:
    obs: uint8 (H, W, 3·stack).
    names: augmentation names (default: all of `dmcr_jax.augment.NAMES`).
    samples: augmented copies per augmentation.
    seed: the `jax.random` key seed.

  Returns:
    A list of (name, uint8 array (samples, H, W, 3·stack)).
  """
  import jax
  import numpy as np

  from dmcr_jax.augment_registry import NAMES, get

  names = NAMES if names is None else names
  key = jax.random.key(seed)
  return [(name, np.concatenate([
      np.asarray(get(name)(jax.random.fold_in(key, i), obs[None]))
      for i in range(samples)])) for name in names]


def write_png(results, path: str, cols: int = 4, gap: int = 2) -> None:
  """Writes the gallery grid (newest frame of each sample) with labels.

  Args:
    results: output of `gallery`.
    path: PNG path (its folder is created).
    cols: cells per row.
    gap: white pixels between the samples of a cell.
  """
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  import numpy as np

  rows = -(-len(results) // cols)
  n, h, w, _ = results[0][1].shape
  strip_w = n * w + (n - 1) * gap
  cell_in = 0.95  # inches per 84-pixel sample
  fig, axes = plt.subplots(rows, cols, squeeze=False,
                           figsize=(cols * strip_w / w * cell_in + 0.2,
                                    rows * (cell_in + 0.28) + 0.1))
  for ax in axes.ravel():
    ax.axis("off")
  for ax, (name, imgs) in zip(axes.ravel(), results):
    strip = np.full((h, strip_w, 3), 255, np.uint8)
    for i in range(n):
      strip[:, i * (w + gap):i * (w + gap) + w] = imgs[i, ..., -3:]
    ax.imshow(strip, interpolation="nearest")
    ax.set_title(LABELS.get(name, name), fontsize=9, family="monospace")
  fig.tight_layout(pad=0.3, h_pad=0.4, w_pad=0.4)
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  fig.savefig(path, dpi=110)
  plt.close(fig)


def main(argv=None):
  """Command-line entry: render, augment and write the gallery PNG."""
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--out", default="augment_gallery.png", help="PNG path")
  parser.add_argument("--domain", default="walker")
  parser.add_argument("--task", default="walk")
  parser.add_argument("--steps", type=int, default=20,
                      help="random-action control steps before the observation")
  parser.add_argument("--samples", type=int, default=4,
                      help="augmented copies shown per augmentation")
  parser.add_argument("--cols", type=int, default=4, help="cells per row")
  parser.add_argument("--names", default=None,
                      help="comma-separated names (default: all of augment.NAMES)")
  parser.add_argument("--seed", type=int, default=0,
                      help="seed of the rollout (initial state and actions)")
  parser.add_argument("--aug-seed", type=int, default=5,
                      help="seed of the augmentation keys (the default 5 shows "
                           "three rotation angles and both flip outcomes)")
  args = parser.parse_args(argv)

  obs = render_observation(args.domain, args.task, args.steps, seed=args.seed)
  names = None if args.names is None else args.names.split(",")
  write_png(gallery(obs, names, args.samples, args.aug_seed), args.out, args.cols)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
