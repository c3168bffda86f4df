"""`dmcr-show`: render a PNG grid of visual seeds for one task.

    dmcr-show walker-walk --seeds 0-15 --vary floor,background

renders camera 0 of the task's initial state (dm_control's own reset with a
fixed dynamics seed, so every tile shows the same state) once per visual seed
and writes the tiles, row by row in seed order, to one PNG. Uses the reference
renderer (`render_model.FrameRenderer`) with MuJoCo's GL backend: EGL unless
`MUJOCO_GL` says otherwise (`import dmcr_jax` picks EGL without a display).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def parse_seeds(spec: str) -> list[int]:
  """Parses "0-15", "3,7,11" or "0-3,100-103" into a list of ints.

  Args:
    spec: comma-separated seeds or inclusive ranges "a-b".

  Returns:
    The seeds in the given order.

  Raises:
    ValueError: on malformed input, negative seeds or seeds ≥ 2**31.
  """
  seeds: list[int] = []
  for part in spec.split(","):
    part = part.strip()
    if not part:
      continue
    try:
      if "-" in part[1:]:
        a, b = part.split("-", 1)
        lo, hi = int(a), int(b)
        if hi < lo:
          raise ValueError
        seeds.extend(range(lo, hi + 1))
      else:
        seeds.append(int(part))
    except ValueError:
      raise ValueError(f"Bad seed spec {part!r} (use e.g. 0-15 or 1,5,9).") from None
  if not seeds:
    raise ValueError("No seeds given.")
  bad = [s for s in seeds if not 0 <= s < 2**31]
  if bad:
    raise ValueError(f"Visual seeds must be in [0, 2**31); got {bad[0]}.")
  return seeds


def physics_state(physics, domain: str):
  """The state of a dm_control `Physics` as (qpos, model_variables).

  Args:
    physics: a dm_control suite physics (after reset/steps).
    domain: its DMCR domain.

  Returns:
    (qpos, model_variables): positions and the task's model variables as
    "<field>:<name>" → value, for every named geom/site/body whose pose, size
    or colour the task changed from the model's defaults (e.g. reacher's
    target, finger-spin's hidden target and tip sites).
  """
  import mujoco
  from dmcr_jax.models.names import FIELD_OBJECTS, suite_model
  base = suite_model(domain)
  variables = {}
  for field in ("geom_pos", "geom_quat", "geom_size", "geom_rgba", "site_pos",
                "site_quat", "site_size", "site_rgba", "body_pos", "body_quat"):
    obj = field.split("_")[0]
    now, orig = np.asarray(getattr(physics.model, field)), getattr(base, field)
    for i in np.nonzero(np.any(now != orig, axis=-1))[0]:
      name = mujoco.mj_id2name(base, FIELD_OBJECTS[obj], int(i))
      if name:
        variables[f"{field}:{name}"] = now[i].copy()
  return physics.data.qpos.copy(), variables


def task_state(domain: str, task: str, dynamics_seed: int = 0, steps: int = 0):
  """dm_control's state after reset (and `steps` zero-action steps).

  Args:
    domain, task: the dm_control task.
    dynamics_seed: the task's random seed.
    steps: control steps with zero actions after reset.

  Returns:
    (qpos, model_variables) as `physics_state`.
  """
  from dm_control import suite
  env = suite.load(domain, task, task_kwargs={"random": dynamics_seed})
  env.reset()
  spec = env.action_spec()
  for _ in range(steps):
    env.step(np.zeros(spec.shape, spec.dtype))
  return physics_state(env.physics, domain)


def render_grid(task: str, seeds: list[int], vary: str = "all", *, size: int = 128,
                cols: int | None = None, dynamics_seed: int = 0, steps: int = 0,
                floor_dir: str | None = None, background_dir: str | None = None,
                pad: int = 2) -> np.ndarray:
  """Renders one tile per visual seed and returns the grid image.

  Args:
    task: a task name such as "walker-walk".
    seeds: visual seeds.
    vary: factors to vary ("all", "none" or e.g. "floor,background").
    size: tile height and width in pixels (≤ 480).
    cols: tiles per row (default: about square).
    dynamics_seed, steps: which state to draw (see `task_state`).
    floor_dir, background_dir: optional user image folders for the bank.
    pad: white pixels between tiles.

  Returns:
    uint8 array (H, W, 3).
  """
  from dmcr_jax.visuals.factors import check_domain
  from dmcr_jax.visuals.render_model import FrameRenderer, build_render_model, prepare
  from dmcr_jax.visuals.textures import load_bank
  if "-" not in task:
    raise ValueError(f"Expected a task name like walker-walk, got {task!r}.")
  domain, task_name = task.split("-", 1)
  check_domain(domain)
  bank = load_bank(floor_dir, background_dir)
  rm = build_render_model(domain, bank)
  looks = prepare(rm, rm.sample(seeds, vary))
  qpos, variables = task_state(domain, task_name, dynamics_seed, steps)
  with FrameRenderer(rm, size, size) as fr:
    tiles = [fr.render(looks, qpos, index=i, model_variables=variables)
             for i in range(len(seeds))]
  cols = cols or int(np.ceil(np.sqrt(len(tiles))))
  rows = int(np.ceil(len(tiles) / cols))
  grid = np.full((rows * (size + pad) + pad, cols * (size + pad) + pad, 3), 255, np.uint8)
  for k, tile in enumerate(tiles):
    r, c = divmod(k, cols)
    y, x = pad + r * (size + pad), pad + c * (size + pad)
    grid[y:y + size, x:x + size] = tile
  return grid


def main(argv: list[str] | None = None) -> int:
  """Command-line entry point of `dmcr-show` (see the module docstring)."""
  ap = argparse.ArgumentParser(
      prog="dmcr-show", description="Render a PNG grid of DMCR visual seeds.")
  ap.add_argument("task", help="task name, e.g. walker-walk")
  ap.add_argument("--seeds", default="0-15", help="e.g. 0-15 or 0,5,9 (default 0-15)")
  ap.add_argument("--vary", default="all",
                  help="factors: all, none or a comma list of camera,light,body,"
                       "target,floor,background,reflectance (default all)")
  ap.add_argument("--out", default=None, help="output PNG (default dmcr_<task>_<seeds>.png)")
  ap.add_argument("--size", type=int, default=128, help="tile size in pixels (default 128)")
  ap.add_argument("--cols", type=int, default=None, help="tiles per row")
  ap.add_argument("--dynamics-seed", type=int, default=0, help="task reset seed (default 0)")
  ap.add_argument("--steps", type=int, default=0, help="zero-action steps after reset")
  ap.add_argument("--floors", default=None, help="folder of floor images")
  ap.add_argument("--backgrounds", default=None, help="folder of background images")
  args = ap.parse_args(argv)
  os.environ.setdefault("MUJOCO_GL", "egl")
  try:
    seeds = parse_seeds(args.seeds)
    if not 1 <= args.size <= 480:
      raise ValueError("--size must be in [1, 480].")
    grid = render_grid(args.task, seeds, args.vary, size=args.size, cols=args.cols,
                       dynamics_seed=args.dynamics_seed, steps=args.steps,
                       floor_dir=args.floors, background_dir=args.backgrounds)
  except (ValueError, TypeError) as e:
    print(f"dmcr-show: error: {e}", file=sys.stderr)
    return 2
  import imageio.v3 as iio
  out = args.out or f"dmcr_{args.task}_{args.seeds.replace(',', '_')}.png"
  iio.imwrite(out, grid)
  print(f"wrote {out} ({len(seeds)} seeds, vary={args.vary})")
  return 0


if __name__ == "__main__":
  sys.exit(main())
