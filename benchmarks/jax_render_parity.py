"""The JAX ray caster against MuJoCo's renderer: per-body silhouette IoU and mean
absolute pixel difference over dm_control states × visual seeds.

`compare` renders a domain's dm_control states (`dm_states`) in each look with
`mujoco.Renderer` (RGB and segmentation) and with `dmcr_jax.visuals.jax_render`
(RGB and body ids); `parity_row` summarises one domain as a JSON row and
`parity_markdown` tabulates rows.

    python -m dmcr_jax.benchmarks.jax_render_parity [--compare DOMAIN …] --seeds 100 --states 3 \\
        --out docs/ [--json FILE] [--worst N]

writes docs/jax_render_parity.png (MuJoCo | JAX | 3×|diff|) and prints, per domain,
the per-body silhouette IoU and the mean absolute pixel difference as JSON lines
(appended to FILE, with a Markdown table beside it);
benchmarks/results/jax_render_parity_cpu.md holds such a table.
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.benchmarks import rows as R
from dmcr_jax.visuals.jax_render import (build_scene, device_looks, poses, render,
                                         render_with_ids)


TASK_OF = {"ball_in_cup": "catch", "cartpole": "swingup", "cheetah": "run",
           "finger": "turn_easy", "fish": "swim", "hopper": "hop", "humanoid": "walk",
           "pendulum": "swingup", "reacher": "easy", "walker": "walk"}


def dm_states(domain: str, count: int, steps: int = 20):
  """`count` dm_control states of the domain's task (dynamics seeds 0, 1, …,
  `steps` random actions after reset): a list of (qpos, model variables)."""
  from dm_control import suite
  from dmcr_jax.visuals import show
  out = []
  for s in range(count):
    env = suite.load(domain, TASK_OF[domain], task_kwargs={"random": s})
    env.reset()
    rng = np.random.default_rng(s)
    spec = env.action_spec()
    for _ in range(steps * s):
      env.step(rng.uniform(spec.minimum, spec.maximum))
    out.append(show.physics_state(env.physics, domain))
    env.physics.free()
  return out


def body_iou(ref_body: np.ndarray, body: np.ndarray, min_pixels: int = 1) -> dict[int, float]:
  """IoU of every body's silhouette (bodies whose union has ≥ `min_pixels`)."""
  out = {}
  for b in np.union1d(np.unique(ref_body), np.unique(body)):
    if b < 0:
      continue
    a, c = ref_body == b, body == b
    union = np.sum(a | c)
    if union >= min_pixels:
      out[int(b)] = float(np.sum(a & c) / union)
  return out


def compare(domain: str, seeds, states: int = 2, size: int = 84, rm=None,
            supersample: int = 1, min_pixels: int = 1):
  """Renders a domain's states × looks with MuJoCo and with the ray caster.

  Args:
    domain: a DMCR domain.
    seeds: visual seeds (vary="all").
    states: dm_control states (`dm_states`).
    size: image size.
    rm: render model (default `build_render_model(domain)`).
    supersample: the ray caster's rays per pixel per axis.
    min_pixels: bodies whose silhouettes (union) are smaller are not scored.

  Returns:
    dict with "mad" (list of mean absolute pixel differences, one per frame),
    "iou" (list of per-frame {body: IoU}), "frames" (list of (ref, jax) images),
    "ids" (list of (ref, jax) body-id images, −1 for background).
  """
  import mujoco
  from dmcr_jax.visuals import render_model as rmod
  rm = rmod.build_render_model(domain) if rm is None else rm
  scene = build_scene(rm)
  m = rm.model
  params = rm.sample(list(seeds))
  looks = rmod.prepare(rm, params)
  dl = device_looks(scene, rm, looks)
  keys = {k for k, _, _ in scene.variables}
  res = {"mad": [], "iou": [], "frames": [], "ids": []}
  fr = rmod.FrameRenderer(rm, size, size)
  try:
    data = mujoco.MjData(m)
    for qpos, variables in dm_states(domain, states):
      var = {k: jnp.asarray(v, jnp.float32) for k, v in variables.items() if k in keys}
      for i in range(len(seeds)):
        ref = fr.render(looks, qpos, index=i, model_variables=variables)
        fr.renderer.enable_segmentation_rendering()
        seg = fr.renderer.render().copy()
        fr.renderer.disable_segmentation_rendering()
        obj, typ = seg[..., 0], seg[..., 1]
        site_body = (m.site_bodyid[np.clip(obj, 0, m.nsite - 1)] if m.nsite
                     else np.full_like(obj, -1))
        ref_body = np.where(obj < 0, -1, np.where(
            typ == int(mujoco.mjtObj.mjOBJ_SITE), site_body,
            m.geom_bodyid[np.clip(obj, 0, m.ngeom - 1)]))
        data.qpos[:] = qpos
        mujoco.mj_fwdPosition(m, data)
        bp = poses(data)
        img, body = render_with_ids(scene, bp, dl.take(i), var or None, height=size,
                                    width=size)
        if supersample > 1:
          img = render(scene, bp, dl.take(i), var or None, height=size, width=size,
                       supersample=supersample)
        img, body = np.asarray(img), np.asarray(body)
        res["mad"].append(float(np.abs(ref.astype(np.int32) - img).mean()))
        res["iou"].append(body_iou(ref_body, body, min_pixels))
        res["frames"].append((ref, img))
        res["ids"].append((ref_body, body))
  finally:
    fr.close()
  return res


def _grid(rows: list[np.ndarray]) -> np.ndarray:
  return np.concatenate(rows, axis=0)


def _side_by_side(ref: np.ndarray, img: np.ndarray) -> np.ndarray:
  """MuJoCo | JAX | 3×|difference|, one row of the comparison pictures."""
  diff = np.clip(np.abs(ref.astype(np.int32) - img) * 3, 0, 255).astype(np.uint8)
  return np.concatenate([ref, img, diff], axis=1)


def parity_row(domain: str, res: dict, body_names: Sequence[str], **settings) -> dict:
  """One JSON row summarising `compare`'s result for a domain.

  Per body (keys "id:name"): mean and minimum IoU over the frames where the body
  was scored, and the fraction of those frames with IoU ≥ 0.95.
  """
  per_body: dict[int, list[float]] = {}
  for frame in res["iou"]:
    for b, v in frame.items():
      per_body.setdefault(b, []).append(v)
  ious = np.asarray([v for vs in per_body.values() for v in vs])
  name = lambda b: f"{b}:{body_names[b] or 'world'}"
  return dict(domain=domain, frames=len(res["mad"]), **settings,
              mad_mean=float(np.mean(res["mad"])), mad_max=float(np.max(res["mad"])),
              iou_min=float(ious.min()), iou_mean=float(ious.mean()),
              frac_body_iou_ge_095=float(np.mean(ious >= 0.95)),
              iou_per_body={name(b): round(float(np.mean(v)), 4)
                            for b, v in sorted(per_body.items())},
              iou_min_per_body={name(b): round(float(np.min(v)), 4)
                                for b, v in sorted(per_body.items())},
              frac_ge_095_per_body={name(b): round(float(np.mean(np.asarray(v) >= 0.95)), 4)
                                    for b, v in sorted(per_body.items())},
              frames_per_body={name(b): len(v) for b, v in sorted(per_body.items())})


def parity_markdown(rows: Sequence[dict]) -> str:
  """A Markdown table of `parity_row` rows: one line per domain and scoring
  threshold (bodies whose silhouette covers fewer pixels are not scored), with the
  body of the lowest mean IoU."""
  def worst(r):
    body = min(r["iou_per_body"], key=r["iou_per_body"].get)
    return (f"{body} ({r['iou_per_body'][body]:.3f} mean, "
            f"{r['frac_ge_095_per_body'][body]:.0%} ≥ 0.95 of "
            f"{r.get('frames_per_body', {}).get(body, '?')} frames)")
  return R.table(rows, [
      ("domain", "domain"), ("min. pixels", "min_pixels"),
      ("frames", lambda r: f"{r['frames']:,}"),
      ("mean abs. diff (mean / max)", lambda r: f"{r['mad_mean']:.2f} / {r['mad_max']:.2f}"),
      ("body-frames scored", lambda r: sum(r.get("frames_per_body", {}).values()) or None),
      ("body IoU mean", lambda r: f"{r['iou_mean']:.4f}"),
      ("min", lambda r: f"{r['iou_min']:.3f}"),
      ("share ≥ 0.95", lambda r: f"{r['frac_body_iou_ge_095']:.1%}"),
      ("body with the lowest mean IoU", worst)])


def main(argv=None) -> None:
  """`python -m dmcr_jax.benchmarks.jax_render_parity --compare DOMAIN … --seeds N --out DIR`."""
  import argparse
  import json
  import os
  import sys
  import time
  from dmcr_jax.visuals import render_model as rmod
  from dmcr_jax.visuals.factors import DOMAINS
  p = argparse.ArgumentParser(description="JAX ray caster vs MuJoCo's renderer.")
  p.add_argument("--compare", nargs="*", default=list(DOMAINS))
  p.add_argument("--seeds", type=int, default=10, help="visual seeds 0 … N−1")
  p.add_argument("--states", type=int, default=2)
  p.add_argument("--size", type=int, default=84)
  p.add_argument("--supersample", type=int, default=1)
  p.add_argument("--min-pixels", type=int, default=10)
  p.add_argument("--out", default=None, help="folder for jax_render_parity.png")
  p.add_argument("--worst", type=int, default=0,
                 help="also write jax_render_worst.png in --out: each domain's N frames "
                      "of the largest mean absolute difference")
  p.add_argument("--json", default=None,
                 help="append one JSON line per domain here; a Markdown table of the "
                      "file's rows is written beside it (.md)")
  args = p.parse_args(sys.argv[1:] if argv is None else argv)
  domains = [d.split("-")[0] for d in args.compare]
  bad = sorted(set(domains) - set(DOMAINS))
  if bad:
    p.error(f"unknown domain(s) {', '.join(bad)}; valid: {', '.join(DOMAINS)}")
  rows, worst_rows = [], []
  for domain in domains:
    rm = rmod.build_render_model(domain)
    res = compare(domain, range(args.seeds), args.states, args.size, rm=rm,
                  supersample=args.supersample, min_pixels=args.min_pixels)
    names = [rm.model.body(b).name for b in range(rm.model.nbody)]
    row = parity_row(domain, res, names, size=args.size, seeds=args.seeds,
                     states=args.states, supersample=args.supersample,
                     min_pixels=args.min_pixels, platform=jax.default_backend(),
                     mujoco_gl=os.environ.get("MUJOCO_GL"),
                     time_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    print(json.dumps(row), flush=True)
    if args.json:
      with open(args.json, "a") as f:
        f.write(json.dumps(row) + "\n")
    frames = res["frames"]
    rows += [_side_by_side(*frames[k]) for k in (0, min(3, len(frames) - 1))]
    worst_rows += [_side_by_side(*frames[k]) for k in np.argsort(res["mad"])[::-1][:args.worst]]
  if args.json:
    with open(args.json) as f:
      table = parity_markdown([json.loads(line) for line in f if line.strip()])
    R.write_markdown(args.json, (
        f"Rows of `python -m dmcr_jax.benchmarks.jax_render_parity --json {args.json}` (the "
        "JSONL beside this file holds each row's settings, platform and time): the "
        "ray caster against `mujoco.Renderer` at visual seeds 0 … seeds − 1 × "
        "dm_control states (`dm_states`); IoU of each body's silhouette against "
        "MuJoCo's segmentation rendering, for bodies whose silhouettes (union) cover "
        "at least `min. pixels`.\n\n") + table)
    print(table)
  if args.out and rows:
    from PIL import Image
    os.makedirs(args.out, exist_ok=True)
    for name, grid, what in (("jax_render_parity.png", rows, "seed 0 and seed 3"),
                             ("jax_render_worst.png", worst_rows,
                              f"the {args.worst} largest differences")):
      if grid:
        path = os.path.join(args.out, name)
        # 256-colour palette keeps the committed picture small (< 500 KB)
        Image.fromarray(_grid(grid)).quantize(256, dither=Image.Dither.NONE).save(
            path, optimize=True)
        print(f"wrote {path} (MuJoCo | JAX | 3×|diff|; rows: {what} per domain)")


if __name__ == "__main__":
  main()
