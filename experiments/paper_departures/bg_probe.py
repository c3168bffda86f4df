import os; os.environ.setdefault("MUJOCO_GL", "egl")
"""Background-factor probe: ours vs the original DMCR's landscape photos.

Renders camera 0 at 84x84 for a few dm_control reset states of a task, at the training look
(visual seed 0) and under held-out looks with only `background` varied, for
  ours   : our procedural skybox bank (the evaluation's 100 test visual seeds),
  photos : the original's 119 sky PNGs (800x800) repeated on all six cube faces, as MuJoCo's
           LoadCubeSingle does for a single square file with gridsize "1 1", rendered
           through OUR render model (dm_control's geometry, narrow cheetah ground),
and prints: sky fraction of the frame (segmentation: no geom), mean |delta| from the training
frame (0-255, mean over RGB) over the whole frame, over the sky pixels and over the non-sky
pixels, and the spread (std over looks) of the sky's mean brightness.

usage: bg_probe.py DOMAIN TASK OUTPREFIX [EVAL_JSON]
"""
import dataclasses, glob, json, sys
import numpy as np, imageio.v3 as iio
from PIL import Image
from dmcr_jax.visuals import render_model as RM, textures as T
from dmcr_jax.visuals.show import task_state

SKIES = "/tmp/dmcr_skies"   # the original's assets/skies/*.png, read from the git mirror (not shipped)


def photo_bank(base):
  files = sorted(glob.glob(SKIES + "/*.png"))
  W = base.backgrounds.shape[2]
  cubes = []
  for f in files:
    im = np.asarray(Image.open(f).convert("RGB").resize((W, W), Image.BOX))
    cubes.append(np.broadcast_to(im, (6, W, W, 3)))
  return T.TextureBank(floors=base.floors, backgrounds=np.ascontiguousarray(np.stack(cubes)),
                       floor_names=base.floor_names,
                       background_names=tuple(os.path.basename(f) for f in files),
                       source="dmcr-original-skies-cube1x1")


SHIFTS = (5.0, 20.0, 50.0)   # rootx offsets: states mid-run, away from the floor's x = -2 edge


def states_for(domain, task):
  """dm_control reset states (dynamics seeds 0-2), each moved forward by SHIFTS[k] metres
  (rootx is qpos[0] in cheetah and hopper), as the agent sees them while running."""
  out = []
  for k, dx in enumerate(SHIFTS):
    q, v = task_state(domain, task, k, 0)
    q = q.copy(); q[0] += dx
    out.append((q, v))
  return out


def render_set(rm, seeds, states, vary="background"):
  looks = RM.prepare(rm, rm.sample(seeds, vary))
  out = np.empty((len(states), len(seeds), 84, 84, 3), np.uint8)
  with RM.FrameRenderer(rm, 84, 84) as fr:
    for s, (qpos, var) in enumerate(states):
      for i in range(len(seeds)):
        out[s, i] = fr.render(looks, qpos, index=i, model_variables=var)
    fr.renderer.enable_segmentation_rendering()
    seg = np.stack([fr.render(looks, q, index=0, model_variables=v)[..., 0].astype(np.int32)
                    for q, v in states])
    fr.renderer.disable_segmentation_rendering()
  return out, seg


def stats(frames, seg, label):
  """frames (S, 1+N, 84, 84, 3): index 0 = training look; seg (S, 84, 84) geom ids (-1 = sky)."""
  f = frames.astype(np.float32)
  d = np.abs(f[:, 1:] - f[:, :1]).mean(-1)                 # (S, N, 84, 84)
  sky = (seg == -1)[:, None]                                 # (S, 1, 84, 84)
  sky_b = np.broadcast_to(sky, d.shape)
  frac = sky.mean()
  whole = d.mean()
  in_sky = d[sky_b].mean()
  out_sky = d[~sky_b].mean()
  changed = (d > 8).mean()
  lum = f[:, 1:].mean(-1)                                     # (S, N, 84, 84)
  sky_lum = np.array([[lum[s, i][sky[s, 0]].mean() for i in range(lum.shape[1])]
                      for s in range(lum.shape[0])])
  train_sky = np.array([f[s, 0].mean(-1)[sky[s, 0]].mean() for s in range(f.shape[0])])
  rows = np.nonzero(sky[0, 0].any(1))[0]
  print(f"{label:28s} sky frac {frac*100:5.1f}% (rows {rows.min()}-{rows.max()}, lowest sky row in "
        f"col 0: {np.nonzero(sky[0,0][:,0])[0].max()}) | mean|d| whole {whole:5.1f}  sky {in_sky:5.1f}  "
        f"non-sky {out_sky:5.1f} | px with |d|>8: {changed*100:5.1f}% | sky brightness train "
        f"{train_sky.mean():5.1f}, looks {sky_lum.mean():5.1f} +- {sky_lum.std():4.1f}")
  return dict(sky_frac=float(frac), d_whole=float(whole), d_sky=float(in_sky),
              d_nonsky=float(out_sky), frac_changed=float(changed),
              sky_lum_train=float(train_sky.mean()), sky_lum_mean=float(sky_lum.mean()),
              sky_lum_std=float(sky_lum.std()))


def grid(frames, path, n=16):
  tiles = frames[0, :n]
  g = np.full((2 * 86 + 2, 8 * 86 + 2, 3), 255, np.uint8)
  for k, t in enumerate(tiles):
    r, c = divmod(k, 8); g[2 + r * 86:2 + r * 86 + 84, 2 + c * 86:2 + c * 86 + 84] = t
  iio.imwrite(path, g)


if __name__ == "__main__":
  domain, task, out = sys.argv[1], sys.argv[2], sys.argv[3]
  ev = sys.argv[4] if len(sys.argv) > 4 else None
  test = json.load(open(ev))["test_visual_seeds"] if ev else list(range(1, 101))
  seeds = [0] + list(test)
  states = states_for(domain, task)
  base = T.load_bank(progress=False)
  res = {}
  ours, seg = render_set(RM.build_render_model(domain, base), seeds, states)
  res["ours"] = stats(ours, seg, f"{domain} ours (procedural)")
  grid(ours, out + "_ours.png")
  pb = photo_bank(base)
  ph, seg2 = render_set(RM.build_render_model(domain, pb), seeds, states)
  assert (ph[:, 0] == ours[:, 0]).all() and (seg2 == seg).all()
  res["photos_our_geometry"] = stats(ph, seg2, f"{domain} orig photos, our geom")
  grid(ph, out + "_photos_ourgeom.png")
  np.savez_compressed(out + "_frames.npz", ours=ours, photos=ph, seg=seg)
  json.dump(res, open(out + "_stats.json", "w"), indent=1)
