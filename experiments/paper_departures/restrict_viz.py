import os, sys; sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
"""Frames of the restricted banks (agent_probe.py's *_upper variants) at the bg_probe states:
grid image and mean |delta| from the training frame per row band and overall."""
from agent_probe import *
import imageio.v3 as iio
from bg_probe import states_for, grid, stats
base = T.load_bank(progress=False); rm0 = RM.build_render_model("cheetah", base); W = base.backgrounds.shape[2]
dflt = default_sky_cube(rm0, W); sc = cut_sin(rm0, [q for q, _ in states_for("cheetah", "run")])
print("cut", sc, np.degrees(np.arcsin(sc[0])))
ev = json.load(open("/work/main/benchmarks/results/eval_cheetah_h200_drq_seed0.json"))["test_visual_seeds"]
proc_ids = np.asarray(rm0.sample(ev, "background").background_id)
ph, files = photo_cubes(W); ph_ids = np.arange(len(files))
states = states_for("cheetah", "run")
out = {}
for name, bgs, ids in [("dfltcheck", dflt[None], [0]), ("ours_upper", restrict(base.backgrounds, dflt, sc[0]), proc_ids),
                       ("photos_upper", restrict(ph, dflt, sc[0]), ph_ids), ("photos", ph, ph_ids)]:
  rm = RM.build_render_model("cheetah", bank_with(base, bgs, name))
  lk = looks_with_ids(rm, list(ids))
  tr = RM.prepare(rm0, rm0.sample([0], "none"))
  fr_all = []
  with RM.FrameRenderer(rm, 84, 84) as fr, RM.FrameRenderer(rm0, 84, 84) as f0:
    for q, v in states:
      t = f0.render(tr, q, index=0)
      fr_all.append([t] + [fr.render(lk, q, index=i) for i in range(len(ids))])
    f0.renderer.enable_segmentation_rendering()
    seg = np.stack([f0.render(tr, q, index=0)[..., 0].astype(np.int32) for q, _ in states])
  F = np.asarray(fr_all)
  d = np.abs(F[:, 1:].astype(np.float32) - F[:, :1]).mean(-1)
  band = d.mean((0, 1, 3))
  print(f"{name:13s} whole {d.mean():5.1f} rows0-45 {band[:46].mean():5.1f} rows46-83 {band[46:].mean():5.1f} "
        f"rows with mean|d|>2: {np.nonzero(band > 2)[0].min() if (band>2).any() else None}-{np.nonzero(band > 2)[0].max() if (band>2).any() else None}")
  out[name] = stats(F, seg, name)
  grid(F, f"cheetah_{name}.png")
json.dump(out, open("restrict_viz_stats.json", "w"), indent=1)
