import os, sys
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from agent_probe import *          # sets MUJOCO_GL, JAX_PLATFORMS=cpu, single-threaded XLA
"""Runs a trained agent (exported params) on CPU under single-factor looks from several sources:

  bg_ours       our procedural skies (first K evaluation test seeds), our render model
  bg_photos     the original's sky photos as a 1x1 cube (all six faces), our render model
  floor_ours    our procedural floors (first K test seeds), our render model
  floor_orig    the ORIGINAL's floor photos rendered natively by MuJoCo with the original's
                MJCF/materials (texrepeat 3, texuniform: 2/3 m tiles; colorspace linear), but
                the ground at dm_control's size (cheetah: not widened), so only the floor
                texture differs from our training look; K photos evenly spaced in name order
  body_ours     our body colours (first K test seeds)

One episode per look, reset seed = look index; action repeat from the config (paper: 4);
3-frame stacks; deterministic policy.

usage: agent_probe2.py CFG_DIR AGENT_MSGPACK EVAL_JSON K OUT_JSON variant...
"""
import glob, xml.etree.ElementTree as ET
from native_probe import git

FLOORS = "/tmp/dmcr_floors"


def native_floor_model(domain, floor_png):
  root = ET.fromstring(git(f"dmc_remastered/assets/{domain}.xml").decode())
  mats = ET.fromstring(git("dmc_remastered/assets/materials.xml"))
  mats[0][0].attrib["builtin"] = "none"; mats[0][0].attrib["file"] = "floor.png"
  mats[0][0].attrib["colorspace"] = "linear"
  assets = {"./common/materials.xml": ET.tostring(mats),
            "./common/skybox.xml": git("dmc_remastered/assets/skybox.xml"),
            "./common/visual.xml": git("dmc_remastered/assets/visual.xml"),
            "floor.png": open(floor_png, "rb").read()}
  return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"), assets)


def run_frames(agent, domain, task, make_frame, n, repeat):
  envs = [suite.load(domain, task, task_kwargs={"random": i}) for i in range(n)]
  spec = envs[0].action_spec()
  for e in envs: e.reset()
  rets = np.zeros(n)
  frame = lambda i: make_frame(i, envs[i].physics.data.qpos)
  stacks = [[frame(i)] * STACK for i in range(n)]
  done = False
  while not done:
    obs = np.stack([np.concatenate(s, -1) for s in stacks])
    act = to_env_action(np.asarray(evaluate.greedy_action(agent, jax.numpy.asarray(obs))),
                        spec.minimum, spec.maximum)
    for i, e in enumerate(envs):
      for _ in range(repeat):
        t = e.step(act[i]); rets[i] += t.reward or 0.0
        if t.last(): done = True; break
      stacks[i] = stacks[i][1:] + [frame(i)]
  return rets


if __name__ == "__main__":
  cfg_dir, msgpack, ev, K, out = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5]
  variants = sys.argv[6:]
  cfg = loop.load_config(cfg_dir)
  domain, task = cfg.task.split("-", 1)
  repeat = cfg.action_repeat or 4
  agent = load_agent(cfg_dir, msgpack)
  base = T.load_bank(progress=False)
  rm0 = RM.build_render_model(domain, base)
  test = json.load(open(ev))["test_visual_seeds"][:K]
  res = json.load(open(out)) if os.path.exists(out) else {}
  for v in variants:
    t0 = time.time(); closers = []
    if v in ("bg_ours", "floor_ours", "body_ours", "train"):
      vary = {"bg_ours": "background", "floor_ours": "floor", "body_ours": "body", "train": "none"}[v]
      looks = RM.prepare(rm0, rm0.sample(test if v != "train" else [0] * K, vary))
      fr = RM.FrameRenderer(rm0, 84, 84); closers.append(fr)
      make = lambda i, q, fr=fr, looks=looks: fr.render(looks, q, index=i)
      info = {}
    elif v == "bg_photos":
      ph, files = photo_cubes(base.backgrounds.shape[2])
      ids = np.linspace(0, len(files) - 1, K).round().astype(int)
      rm = RM.build_render_model(domain, bank_with(base, ph, v))
      looks = looks_with_ids(rm, ids)
      fr = RM.FrameRenderer(rm, 84, 84); closers.append(fr)
      make = lambda i, q, fr=fr, looks=looks: fr.render(looks, q, index=i)
      info = {"files": [os.path.basename(files[i]) for i in ids]}
    elif v == "floor_orig":
      files = sorted(glob.glob(FLOORS + "/*.png"))
      ids = np.linspace(0, len(files) - 1, K).round().astype(int)
      models = [native_floor_model(domain, files[i]) for i in ids]
      rends = [mujoco.Renderer(m, 84, 84) for m in models]; closers += rends
      datas = [mujoco.MjData(m) for m in models]
      def make(i, q, models=models, rends=rends, datas=datas):
        d = datas[i]; d.qpos[:] = q; mujoco.mj_fwdPosition(models[i], d)
        rends[i].update_scene(d, camera=0); return rends[i].render().copy()
      info = {"files": [os.path.basename(files[i]) for i in ids]}
    r = run_frames(agent, domain, task, make, K, repeat)
    for c in closers: c.close()
    res[v] = {"returns": r.tolist(), "mean": float(r.mean()), "sem": float(r.std(ddof=1) / np.sqrt(K)),
              "wall_s": time.time() - t0, **info}
    print(f"{cfg.task} {v:12s} mean {r.mean():6.1f} +- {res[v]['sem']:5.1f} (sem, K={K})  "
          f"{np.round(r).astype(int).tolist()}  {time.time() - t0:.0f}s", flush=True)
    json.dump(res, open(out, "w"), indent=1)
