import os
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
"""Runs the trained cheetah-run SAC+AUG agent (seed 0, exported params) on CPU, on our render
model, under background-only looks drawn from four skybox banks:

  ours          our procedural skies (the evaluation's first K test visual seeds)
  ours_upper    the same skies, but only above the original's floor line: texels whose direction
                lies below the far edge of the original's 15 m-wide cheetah ground (seen from the
                camera) keep dm_control's default skybox, so exactly the pixels the original's
                background factor can change are changed
  photos        the original's landscape photos as MuJoCo loads a single square skybox file
                (the same image on all six faces), K photos evenly spaced in name order
  photos_upper  those photos, restricted as ours_upper

plus the training look. Physics: dm_control's cheetah-run (reset seed = episode index), action
repeat 4, 3-frame stacks (oldest first, reset = first frame repeated), deterministic policy
(tanh of the mean), 84x84 frames from render_model.FrameRenderer (the pool's reference).

usage: agent_probe.py CFG_DIR AGENT_MSGPACK EVAL_JSON K OUT_JSON [variants...]
"""
import glob, json, sys, time
import numpy as np
import jax, flax.serialization
from PIL import Image
from dm_control import suite
import mujoco
from dmcr_jax.visuals import render_model as RM, textures as T
from dmcr_jax.train import loop, evaluate
from dmcr_jax.train.step import to_env_action

SKIES = "/tmp/dmcr_skies"
REPEAT, STACK = 4, 3


def load_agent(cfg_dir, msgpack):
  cfg = loop.load_config(cfg_dir)
  import dmcr_jax
  task = dmcr_jax.load(cfg.task)
  agents = loop.init_agents(cfg, (84, 84, 9), task.action_size)
  agent = jax.tree.map(lambda x: x[0], agents)
  like = {"encoder": agent.params["encoder"], "actor": agent.params["actor"]}
  raw = flax.serialization.msgpack_restore(open(msgpack, "rb").read())
  got = flax.serialization.from_state_dict(like, {"encoder": raw["encoder"], "actor": raw["actor"]})
  return agent.replace(params={**agent.params, **got})


def default_sky_cube(rm, W):
  m = rm.model; t = rm.sky_tex
  adr, w, h, nc = m.tex_adr[t], m.tex_width[t], m.tex_height[t], m.tex_nchannel[t]
  faces = np.asarray(m.tex_data[adr:adr + w * h * nc]).reshape(6, w, w, nc)[..., :3]
  return np.stack([np.asarray(Image.fromarray(f).resize((W, W), Image.BOX)) for f in faces])


def photo_cubes(W):
  files = sorted(glob.glob(SKIES + "/*.png"))
  return np.stack([np.broadcast_to(np.asarray(Image.open(f).convert("RGB").resize((W, W), Image.BOX)),
                                   (6, W, W, 3)) for f in files]), files


def cut_sin(rm, states):
  """sin(elevation) of the original's ground far edge (y = +15) seen from camera 0."""
  m = rm.model; d = mujoco.MjData(m); s = []
  for q in states:
    d.qpos[:] = q; mujoco.mj_forward(m, d)
    cx, cy, cz = d.cam_xpos[0]
    dy = 15.0 - cy
    s.append(-cz / np.hypot(dy, cz))
  return float(np.mean(s)), float(np.min(s)), float(np.max(s))


def restrict(cubes, default, s_cut):
  z = T.cube_directions(cubes.shape[2])[..., 2]          # (6, W, W) sin(elevation)
  below = (z < s_cut)[None, ..., None]
  return np.where(below, default[None], cubes).astype(np.uint8)


def bank_with(base, bgs, name):
  n = T.NUM_BACKGROUNDS
  if bgs.shape[0] < n:   # pad (only ids < len are used)
    bgs = np.concatenate([bgs, np.repeat(bgs[:1], n - bgs.shape[0], 0)])
  return T.TextureBank(floors=base.floors, backgrounds=np.ascontiguousarray(bgs),
                       floor_names=base.floor_names,
                       background_names=tuple(f"{name}_{i}" for i in range(n)), source=name)


def looks_with_ids(rm, ids):
  p = rm.sample([1] * len(ids), "background")            # any seed; ids replaced below
  p = p.replace(background_id=jax.numpy.asarray(np.asarray(ids, np.int32))) if hasattr(p, "replace") \
      else type(p)(**{**{f: getattr(p, f) for f in p.__dataclass_fields__},
                      "background_id": jax.numpy.asarray(np.asarray(ids, np.int32))})
  return RM.prepare(rm, p)


def run(agent, rm, looks, n, first_seed=0):
  """One episode per look i (reset seed first_seed + i), all in lockstep; returns (n,) returns."""
  envs = [suite.load("cheetah", "run", task_kwargs={"random": first_seed + i}) for i in range(n)]
  spec = envs[0].action_spec()
  ts = [e.reset() for e in envs]
  rets = np.zeros(n)
  with RM.FrameRenderer(rm, 84, 84) as fr:
    frame = lambda i: fr.render(looks, envs[i].physics.data.qpos, index=i)
    stacks = [[frame(i)] * STACK for i in range(n)]
    done = False
    while not done:
      obs = np.stack([np.concatenate(s, -1) for s in stacks])
      act = np.asarray(evaluate.greedy_action(agent, jax.numpy.asarray(obs)))
      act = to_env_action(act, spec.minimum, spec.maximum)
      for i, e in enumerate(envs):
        for _ in range(REPEAT):
          t = e.step(act[i]); rets[i] += t.reward or 0.0
          if t.last(): done = True; break
        stacks[i] = stacks[i][1:] + [frame(i)]
  return rets


if __name__ == "__main__":
  cfg_dir, msgpack, ev, K, out = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5]
  variants = sys.argv[6:] or ["train", "ours", "ours_upper", "photos", "photos_upper"]
  agent = load_agent(cfg_dir, msgpack)
  base = T.load_bank(progress=False)
  rm0 = RM.build_render_model("cheetah", base)
  W = base.backgrounds.shape[2]
  dflt = default_sky_cube(rm0, W)
  from dmcr_jax.visuals.show import task_state
  sc = cut_sin(rm0, [task_state("cheetah", "run", k, 0)[0] for k in range(3)])
  print("original floor-edge sin(elev) mean/min/max", sc, "deg", np.degrees(np.arcsin(sc[0])), flush=True)
  test = json.load(open(ev))["test_visual_seeds"][:K]
  proc_ids = np.asarray(rm0.sample(test, "background").background_id)
  ph, files = photo_cubes(W)
  ph_ids = np.linspace(0, len(files) - 1, K).round().astype(int)
  res = {"cut_sin": sc, "K": K, "proc_ids": proc_ids.tolist(),
         "photo_files": [os.path.basename(files[i]) for i in ph_ids]}
  if os.path.exists(out):
    res = {**json.load(open(out)), **res}
  for v in variants:
    t0 = time.time()
    if v == "train":
      looks = RM.prepare(rm0, rm0.sample([0] * K, "none")); rm = rm0
    elif v.startswith("dfltcheck"):  # bank cube 0 = downsampled default sky, whole sphere
      rm = RM.build_render_model("cheetah", bank_with(base, dflt[None], "dfltcheck")); looks = looks_with_ids(rm, [0] * K)
    elif v.startswith("ours"):
      bgs = base.backgrounds if v == "ours" else restrict(base.backgrounds, dflt, sc[0])
      rm = rm0 if v == "ours" else RM.build_render_model("cheetah", bank_with(base, bgs, v))
      looks = looks_with_ids(rm, proc_ids)
    else:
      bgs = ph if v == "photos" else restrict(ph, dflt, sc[0])
      rm = RM.build_render_model("cheetah", bank_with(base, bgs, v))
      looks = looks_with_ids(rm, ph_ids)
    r = run(agent, rm, looks, K)
    res[v] = {"returns": r.tolist(), "mean": float(r.mean()), "sem": float(r.std(ddof=1) / np.sqrt(K)),
              "wall_s": time.time() - t0}
    print(f"{v:14s} mean {r.mean():6.1f} +- {res[v]['sem']:5.1f} (sem, K={K})  {np.round(r).astype(int).tolist()}  "
          f"{time.time() - t0:.0f}s", flush=True)
    json.dump(res, open(out, "w"), indent=1)
