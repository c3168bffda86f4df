import os, sys
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from agent_probe import *          # sets MUJOCO_GL, JAX_PLATFORMS=cpu, single-threaded XLA
"""Runs a trained agent (exported params) on CPU in dm_control's own task: MuJoCo C physics,
frames from dm_control's own renderer (`physics.render(84, 84, camera_id=0)`), nothing of this
project's env, physics or render model in the loop. Its returns against `evaluate`'s train
return (same agent, our env) separate "our env differs from dm_control" from "the agent
learned less".

One episode per initial state (task random = episode index), action repeat from the config,
3-frame stacks (oldest first, reset = first frame repeated), deterministic policy.

usage: dmc_native_probe.py CFG_DIR AGENT_MSGPACK K OUT_JSON
"""
from agent_probe2 import run_frames

if __name__ == "__main__":
  cfg_dir, msgpack, K, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
  cfg = loop.load_config(cfg_dir)
  domain, task = cfg.task.split("-", 1)
  import dmcr_jax.env as E
  repeat = cfg.action_repeat or E.ACTION_REPEAT[cfg.task]
  agent = load_agent(cfg_dir, msgpack)
  t0 = time.time()
  renderers = {}
  envs_seen = []

  # run_frames builds the envs; the frame function renders the same task's physics natively.
  def make(i, q):
    if i not in renderers:
      renderers[i] = suite.load(domain, task, task_kwargs={"random": 10_000 + i}).physics
    p = renderers[i]
    p.data.qpos[:] = q; p.forward()
    return p.render(84, 84, camera_id=0)
  r = run_frames(agent, domain, task, make, K, repeat)
  res = {"task": cfg.task, "action_repeat": repeat, "returns": r.tolist(), "mean": float(r.mean()),
         "sem": float(r.std(ddof=1) / np.sqrt(K)), "wall_s": time.time() - t0}
  print(f"{cfg.task} dm_control native: mean {r.mean():6.1f} +- {res['sem']:5.1f} (sem, K={K}) "
        f"{np.round(r).astype(int).tolist()} {time.time() - t0:.0f}s", flush=True)
  json.dump(res, open(out, "w"), indent=1)
