import os; os.environ.setdefault("MUJOCO_GL", "egl")
"""The ORIGINAL DMCR's look rendered natively with MuJoCo 3.17 (its own MJCF and assets, read
from the git mirror of jakegrigsby/dmc_remastered 12fda99): the training look (seed 0, which in
the original still has the cheetah ground widened to "100 15 .5") and the background factor
alone (each of its 119 sky PNGs as the skybox file, builtin "none"; colorspace "linear" so
MuMoCo 3.17 uploads the bytes as MuJoCo 2.x did). Same states as bg_probe.py (dm_control
reset, dynamics seeds 0-2, moved forward 5/20/50 m), 84x84, camera 0. Prints the same statistics as bg_probe.py.

usage: native_probe.py DOMAIN TASK OUTPREFIX [narrow]   (narrow: keep dm_control's ground width)
"""
import glob, json, subprocess, sys, xml.etree.ElementTree as ET
import numpy as np, mujoco, imageio.v3 as iio
sys.path.insert(0, os.path.dirname(__file__))
from bg_probe import stats, grid, SKIES, states_for
from dmcr_jax.visuals.show import task_state

REPO = "/work/.mirror/jakegrigsby+dmc_remastered/repo"
def git(p): return subprocess.run(["git", "--git-dir", REPO, "show", f"HEAD:{p}"],
                                  capture_output=True, check=True).stdout


def model(domain, sky_png=None, narrow=False):
  root = ET.fromstring(git(f"dmc_remastered/assets/{domain}.xml").decode())
  if domain == "cheetah" and not narrow:
    root[7][0].attrib["size"] = "100 15 .5"          # cheetah.get_model, every seed incl. 0
  sky = ET.fromstring(git("dmc_remastered/assets/skybox.xml"))
  assets = {"./common/materials.xml": git("dmc_remastered/assets/materials.xml"),
            "./common/visual.xml": git("dmc_remastered/assets/visual.xml")}
  if sky_png:
    sky[0][0].attrib["builtin"] = "none"; sky[0][0].attrib["file"] = "sky.png"
    sky[0][0].attrib["colorspace"] = "linear"
    assets["sky.png"] = open(sky_png, "rb").read()
  assets["./common/skybox.xml"] = ET.tostring(sky)
  return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"), assets)


def render(m, qpos, seg=False):
  d = mujoco.MjData(m); d.qpos[:] = qpos; mujoco.mj_forward(m, d)
  with mujoco.Renderer(m, 84, 84) as r:
    if seg: r.enable_segmentation_rendering()
    r.update_scene(d, camera=0); x = r.render()
  return x[..., 0].astype(np.int32) if seg else x


if __name__ == "__main__":
  domain, task, out = sys.argv[1], sys.argv[2], sys.argv[3]
  narrow = len(sys.argv) > 4 and sys.argv[4] == "narrow"
  states = [q for q, _ in states_for(domain, task)]
  files = sorted(glob.glob(SKIES + "/*.png"))
  models = [model(domain, narrow=narrow)] + [model(domain, f, narrow) for f in files]
  frames = np.stack([[render(m, q) for m in models] for q in states])
  seg = np.stack([render(models[0], q, seg=True) for q in states])
  label = f"{domain} ORIGINAL native" + (" narrow" if narrow else "")
  res = stats(frames, seg, label)
  grid(frames, out + "_native.png")
  np.savez_compressed(out + "_native_frames.npz", frames=frames, seg=seg)
  json.dump(res, open(out + "_native_stats.json", "w"), indent=1)
