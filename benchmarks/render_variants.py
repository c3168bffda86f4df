"""Where does a tiled render's time go? Frames/s of the worker loop with parts switched.

`TiledRenderer` renders each frame at the origin of MuJoCo's offscreen buffer and
blits it into a tile. This probe runs the same per-frame loop (apply a look, write
qpos, kinematics, `mjv_updateScene`, `mjr_render`, blit; one readback per buffer)
in P processes at once and switches one part at a time, to find what stops the
pool from scaling with processes on a GPU:

- `offscreen`: MuJoCo's offscreen buffer as large as the tile buffer (as the
  renderer sizes it) or as large as one frame;
- `samples`: MuJoCo's multisampling (4, the model's default) or none;
- `blit`: copy each frame into its tile, or not (pixels are then lost: timing only);
- `looks`: every frame a different visual seed ("all") or all frames seed 0;
- `rawgl`: the per-frame GL calls through PyOpenGL's checked wrappers or its raw
  bindings (`OpenGL.raw.GL`: no `glGetError` after every call).

    python -m dmcr_jax.benchmarks.render_variants --procs 1,16 --out benchmarks/results/render_variants_h100.jsonl
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import time

BASE = dict(quality="fastest", offscreen="tile", samples=4, blit=True, looks="all",
            rawgl=False)
VARIANTS = [
    {},
    {"offscreen": "frame"},
    {"samples": 0},
    {"blit": False},
    {"looks": "none"},
    {"rawgl": True},
    {"offscreen": "frame", "rawgl": True},
    {"quality": "fast"},
    {"quality": "fast", "offscreen": "frame", "rawgl": True},
]


def _worker(args):
  cfg, frames, size, seed = args
  os.environ["JAX_PLATFORMS"] = "cpu"  # the looks are drawn with JAX: keep it off the GPU
  os.environ.setdefault("MUJOCO_GL", "egl")
  os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
  import mujoco
  import numpy as np

  from dmcr_jax.visuals import render_model as rmod
  from dmcr_jax.visuals.tiled import QUALITY, apply_quality, prepare_kinematics

  rm = rmod.build_render_model("walker")
  m = rm.model
  d = mujoco.MjData(m)
  rng = np.random.default_rng(seed)
  seeds = np.arange(1, frames + 1) + seed * frames if cfg["looks"] == "all" else [0] * frames
  looks = rmod.prepare(rm, rm.sample(seeds, vary="all"))
  qpos = m.qpos0 + 0.2 * rng.standard_normal((frames, m.nq))
  cols = 2048 // size
  tiles = cols * cols
  bw = bh = cols * size
  apply_quality(m, cfg["quality"])
  _, shadows, reflections = QUALITY[cfg["quality"]]
  m.vis.quality.offsamples = cfg["samples"]
  if cfg["offscreen"] == "tile":
    m.vis.global_.offwidth, m.vis.global_.offheight = bw, bh
  else:
    m.vis.global_.offwidth, m.vis.global_.offheight = size, size
  gl = mujoco.GLContext(bw, bh)
  gl.make_current()
  con = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_150)
  from OpenGL import GL
  from OpenGL.raw.GL.VERSION import GL_3_0 as raw
  bind = raw.glBindFramebuffer if cfg["rawgl"] else GL.glBindFramebuffer
  blit = raw.glBlitFramebuffer if cfg["rawgl"] else GL.glBlitFramebuffer
  fbo, rbo = GL.glGenFramebuffers(1), GL.glGenRenderbuffers(1)
  GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rbo)
  GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, bw, bh)
  GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fbo)
  GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0,
                               GL.GL_RENDERBUFFER, rbo)
  scn = mujoco.MjvScene(m, maxgeom=10000)
  scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = shadows
  scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = reflections
  opt, pert, cam = mujoco.MjvOption(), mujoco.MjvPerturb(), mujoco.MjvCamera()
  cam.type, cam.fixedcamid = mujoco.mjtCamera.mjCAMERA_FIXED, 0
  buf = np.empty((bh, bw, 3), np.uint8)
  origin = mujoco.MjrRect(0, 0, size, size)

  def run(n):
    for start in range(0, n, tiles):
      count = min(tiles, n - start)
      for k in range(count):
        i = start + k
        rmod.apply(rm, looks, i, context=con)
        d.qpos[:] = qpos[i]
        prepare_kinematics(m, d)
        mujoco.mjv_updateScene(m, d, opt, pert, cam, mujoco.mjtCatBit.mjCAT_ALL, scn)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, con)
        mujoco.mjr_render(origin, scn, con)
        if cfg["blit"]:
          r, c = divmod(k, cols)
          bind(GL.GL_READ_FRAMEBUFFER, con.offFBO)
          bind(GL.GL_DRAW_FRAMEBUFFER, fbo)
          blit(0, 0, size, size, c * size, r * size, (c + 1) * size,
                               (r + 1) * size, GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST)
      GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, fbo)
      GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
      GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
      rows = -(-count // cols) * size
      GL.glReadPixels(0, 0, bw, rows, GL.GL_RGB, GL.GL_UNSIGNED_BYTE, buf[:rows])

  run(min(frames, 64))  # warm-up (texture uploads, shader compiles)
  t0 = time.perf_counter()
  run(frames)
  return frames, time.perf_counter() - t0


def measure(cfg: dict, procs: int, frames: int, size: int) -> dict:
  """Runs `procs` processes of `frames` frames each at once; total frames/s."""
  ctx = mp.get_context("spawn")
  with ctx.Pool(procs) as pool:
    res = pool.map(_worker, [(cfg, frames, size, s) for s in range(procs)])
  # Processes start together but not at the same instant: the slowest sets the pace.
  total = sum(n for n, _ in res)
  slowest = max(t for _, t in res)
  return dict(cfg, procs=procs, frames_per_proc=frames, size=size,
              frames_per_s=total / slowest,
              per_proc_frames_per_s=sum(n / t for n, t in res) / procs)


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--procs", default="1,16")
  p.add_argument("--frames", type=int, default=1024, help="frames per process")
  p.add_argument("--size", type=int, default=84)
  p.add_argument("--out", default=None)
  args = p.parse_args(argv)
  from dmcr_jax.benchmarks.rows import gpu_name
  device = gpu_name() or "none"
  rows = []
  for procs in [int(x) for x in args.procs.split(",")]:
    for v in VARIANTS:
      row = dict(bench="render_variants", device=device, cpus=os.cpu_count(),
                 gl=os.environ.get("MUJOCO_GL", "egl"), changed=",".join(
                     f"{k}={val}" for k, val in v.items()) or "baseline",
                 **measure(dict(BASE, **v), procs, args.frames, args.size))
      rows.append(row)
      print(json.dumps(row), flush=True)
      if args.out:
        with open(args.out, "a") as f:
          f.write(json.dumps(row) + "\n")
  print("| procs | changed | frames/s | per process |\n|---:|---|---:|---:|")
  for r in rows:
    print(f"| {r['procs']} | {r['changed']} | {r['frames_per_s']:,.0f} | "
          f"{r['per_proc_frames_per_s']:,.0f} |")


if __name__ == "__main__":
  main()
