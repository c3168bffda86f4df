"""RenderPool: bit-identical to the single-frame reference, robust to a killed worker."""

import os
import signal
import time

import numpy as np
import pytest

from dmcr_jax.visuals import render_model as rmod
from dmcr_jax.visuals.pool import WorkerError
from dmcr_jax.visuals.render_pool import RenderPool, check_egl_devices

pytestmark = pytest.mark.xdist_group("render_pool")


@pytest.fixture(scope="module")
def pool():
  with RenderPool("reacher-easy", max_batch=16, workers=2) as p:
    yield p


def _inputs(rm, n, seed=0):
  rng = np.random.default_rng(seed)
  looks = rm.sample(np.arange(n) * 13 + seed, vary="all")
  qpos = rm.model.qpos0 + rng.uniform(-1, 1, (n, rm.model.nq))
  target = np.concatenate([rng.uniform(-.2, .2, (n, 2)), np.full((n, 1), .01)], 1)
  size = np.zeros((n, 3))
  size[:, 0] = rng.uniform(.015, .05, n)
  return qpos, looks, {"geom_pos:target": target, "geom_size:target": size}


def _reference(rm, qpos, looks, variables):
  fr = rmod.FrameRenderer(rm)
  try:
    return np.stack([fr.render(looks, qpos[i], index=i,
                               model_variables={k: v[i] for k, v in variables.items()})
                     for i in range(len(qpos))])
  finally:
    fr.close()


def test_pixels_equal_reference_for_any_batch_size(pool):
  qpos, looks, var = _inputs(pool.rm, 9)
  ref = _reference(pool.rm, qpos, looks, var)
  assert ref.std() > 5  # a real picture, not a blank frame
  np.testing.assert_array_equal(pool.render(qpos, looks, var), ref)
  # A different batch size moves frames to other workers and tiles.
  np.testing.assert_array_equal(pool.render(qpos[:1], looks.take(0),
                                            {k: v[:1] for k, v in var.items()}), ref[:1])
  np.testing.assert_array_equal(
      pool.render(qpos[3:], looks.take(slice(3, None)), {k: v[3:] for k, v in var.items()}),
      ref[3:])


def test_worker_count_does_not_change_pixels(pool):
  qpos, looks, var = _inputs(pool.rm, 5, seed=1)
  with RenderPool("reacher-easy", max_batch=8, workers=1) as single:
    np.testing.assert_array_equal(single.render(qpos, looks, var),
                                  pool.render(qpos, looks, var))


def test_workers_render_without_loading_jax(pool):
  # A worker only applies prepared looks and renders: it never imports JAX, whose
  # import is a large part of a worker's start-up (every env with the pool renderer
  # starts its workers). Checked on the loaded shared libraries, after a render.
  qpos, looks, var = _inputs(pool.rm, 4, seed=3)
  pool.render(qpos, looks, var)
  for pid in pool.pids:
    with open(f"/proc/{pid}/maps") as f:
      libraries = f.read()
    assert "libmujoco" in libraries and "jaxlib" not in libraries, pid


def test_a_bank_texture_reaches_the_gl_context_when_a_look_first_draws_it():
  # What a pool worker does: its context starts with a 1×1 placeholder for each
  # bank texture and receives a texture before the first frame that draws it.
  import copy
  from dmcr_jax.visuals.render_pool import _WorkerRenderer
  from OpenGL import GL
  worker = _WorkerRenderer("cartpole", (), 16, 16, 0, "exact", None)
  rm, renderer = worker.rm, worker.renderer
  floor = rm.bank_textures[0] + 5

  def gl_width(tex):
    renderer._gl.make_current()
    GL.glBindTexture(GL.GL_TEXTURE_2D, int(renderer.context.texture[tex]))
    return GL.glGetTexLevelParameteriv(GL.GL_TEXTURE_2D, 0, GL.GL_TEXTURE_WIDTH)

  try:
    assert gl_width(floor) == 1 and rm.model.tex_width[floor] == 256  # the model is intact
    looks = rmod.prepare(rm, rm.sample(np.arange(1)))
    looks.floor_matid[:] = rm.floor_mat0 + 5
    qpos = rm.model.qpos0[None]
    inputs = {"qpos": qpos, **{"look." + k: v for k, v in vars(looks).items()}}
    out = np.empty((1, 16, 16, 3), np.uint8)
    worker(inputs, out)
    assert gl_width(floor) == 256
    reference = rmod.FrameRenderer(copy.copy(rm), 16, 16)
    try:
      np.testing.assert_array_equal(out[0], reference.render(looks, qpos[0]))
    finally:
      reference.close()
  finally:
    renderer.close()


def test_killed_worker_is_replaced(pool):
  qpos, looks, var = _inputs(pool.rm, 6, seed=2)
  want = pool.render(qpos, looks, var)
  victim = pool.pids[1]
  os.kill(victim, signal.SIGKILL)
  time.sleep(0.2)
  before = pool.restarts
  np.testing.assert_array_equal(pool.render(qpos, looks, var), want)
  assert pool.restarts == before + 1 and victim not in pool.pids


def test_bad_inputs(pool):
  qpos, looks, var = _inputs(pool.rm, 3)
  with pytest.raises(ValueError, match="qpos must have shape"):
    pool.render(qpos[:, :1], looks, var)
  with pytest.raises(ValueError, match=r"batch size must be in \[1, 16\]"):
    pool.render(np.zeros((17, pool.nq)), looks, var)
  with pytest.raises(ValueError, match="got 3 looks for 2 envs"):
    pool.render(qpos[:2], looks, {k: v[:2] for k, v in var.items()})
  with pytest.raises(ValueError, match="geom_pos:target"):
    pool.render(qpos, looks, {})
  with pytest.raises(ValueError, match="osmesa"):
    RenderPool("reacher-easy", max_batch=1, gl="vulkan")
  with pytest.raises(ValueError, match="exact"):
    RenderPool("reacher-easy", max_batch=1, quality="ultra")
  with pytest.raises(ValueError, match="walker-walk"):
    RenderPool("walker-fly", max_batch=1)
  with pytest.raises(ValueError, match="EGL device indices"):
    RenderPool("reacher-easy", max_batch=1, egl_devices=[-1])
  with pytest.raises(ValueError, match="gl='egl'"):
    check_egl_devices((0,), "osmesa")
  # The pool still works after bad calls.
  assert pool.render(qpos, looks, var).shape == (3, 84, 84, 3)



def test_egl_devices_reach_each_workers_gl_setup():
  # MuJoCo's EGL setup reads MUJOCO_EGL_DEVICE_ID in the worker: an index past the
  # machine's EGL devices fails there, naming the variable (no machine has 1000).
  with pytest.raises(WorkerError, match="MUJOCO_EGL_DEVICE_ID"):
    RenderPool("reacher-easy", max_batch=2, workers=1, gl="egl", egl_devices=[999])

def test_close_leaves_nothing_behind():
  p = RenderPool("reacher-easy", max_batch=2, workers=2)
  pids = p.pids
  names = [s.name for s in p._pool._segments]
  p.close()
  for pid in pids:
    with pytest.raises(ProcessLookupError):
      os.kill(pid, 0)
  assert not any(os.path.exists(f"/dev/shm/{n}") for n in names)


@pytest.mark.slow
def test_frame_stacks_built_in_the_workers_survive_a_killed_worker(pool):
  with RenderPool("reacher-easy", max_batch=8, workers=2, frame_stack=3) as stacked:
    calls = [_inputs(pool.rm, 5, seed=s) for s in (3, 4, 5, 6)]
    frames = [pool.render(*c) for c in calls]
    restart = [None, np.zeros(5, bool), np.array([0, 1, 0, 0, 1], bool), np.zeros(5, bool)]
    want = np.concatenate([frames[0]] * 3, axis=-1)
    for t, (c, f, r) in enumerate(zip(calls, frames, restart)):
      if t == 3:  # a worker dies between calls: its slice is re-rendered from `prev`
        os.kill(stacked.pids[0], signal.SIGKILL)
        time.sleep(0.2)
      got = stacked.render(*c, restart=r)
      if t:
        want = np.concatenate([want[..., 3:], f], axis=-1)
        want[r] = np.concatenate([f[r]] * 3, axis=-1)
      np.testing.assert_array_equal(got, want)
    assert stacked.restarts == 1


def test_row_views_share_the_workers_and_keep_their_own_stacks(pool):
  # Two envs' rows drawn by one pool's workers (`RenderPool.rows`), both calls in
  # flight together and collected in either order: each view's stacks continue its
  # own previous frames, not the other view's call.
  with RenderPool("reacher-easy", max_batch=6, workers=2, frame_stack=2) as stacked:
    views, want = [stacked.rows(0, 3), stacked.rows(3, 6)], [None, None]
    for t in range(3):
      for v, view in enumerate(views):
        c = _inputs(pool.rm, 3, seed=10 * v + t)
        f = pool.render(*c)
        view.submit(*c, restart=None if t == 0 else np.zeros(3, bool))
        with pytest.raises(RuntimeError, match="twice"):
          view.pool.submit(*_inputs(pool.rm, 6, seed=1))   # rows of a call in flight
        want[v] = np.concatenate([f, f] if t == 0 else [want[v][..., 3:], f], axis=-1)
      for v in ((1, 0), (0, 1))[t % 2]:
        np.testing.assert_array_equal(views[v].collect(), want[v])
    with pytest.raises(ValueError, match="inside"):
      stacked.rows(4, 7)


def test_shift_stacks_is_the_strided_shift():
  from dmcr_jax.visuals.render_pool import shift_stacks
  rng = np.random.default_rng(0)
  for shape in [(5, 4, 3, 9), (2, 3, 3, 6), (1, 1, 1, 12)]:
    prev = rng.integers(0, 256, shape, np.uint8)
    out = rng.integers(0, 256, shape, np.uint8)
    shift_stacks(out, prev)
    np.testing.assert_array_equal(out[..., :-3], prev[..., 3:])
  with pytest.raises(AttributeError):  # never a silent copy of a strided view
    shift_stacks(np.zeros((4, 2, 2, 9), np.uint8)[::2], np.zeros((2, 2, 2, 9), np.uint8))


def test_gl_default_and_osmesa_check(monkeypatch):
  from dmcr_jax.visuals import render_pool as rp
  monkeypatch.delenv("MUJOCO_GL", raising=False)
  assert rp.default_gl() == "egl"  # with or without a GPU (Mesa's EGL renders on a CPU)
  monkeypatch.setenv("MUJOCO_GL", "osmesa")
  assert rp.default_gl() == "osmesa"
  monkeypatch.setenv("MUJOCO_GL", "glfw")
  assert rp.default_gl() == "egl"
  monkeypatch.setattr(rp.ctypes.util, "find_library", lambda name: None)
  with pytest.raises(ValueError, match="libosmesa6"):
    RenderPool("reacher-easy", max_batch=1, gl="osmesa")


OSMESA_SCRIPT = r"""
import os, sys
import numpy as np
from dmcr_jax.visuals.pool import WorkerError
from dmcr_jax.visuals.render_pool import RenderPool, check_egl_devices

frames = {}
for gl in ("osmesa", "egl"):
  with RenderPool("cartpole-balance", max_batch=2, height=24, width=24, workers=1,
                  gl=gl) as pool:
    looks = pool.rm.sample([0, 7], vary="all")
    frames[gl] = pool.render(np.tile(pool.rm.model.qpos0, (2, 1)), looks)
    maps = open(f"/proc/{pool.pids[0]}/maps").read()
    print(gl, "libOSMesa" in maps, "libEGL" in maps)
print("equal", bool(np.array_equal(frames["osmesa"], frames["egl"])),
      "std", float(frames["osmesa"].std()))
"""


@pytest.mark.slow
@pytest.mark.skipif(__import__("ctypes.util").util.find_library("OSMesa") is None,
                    reason="the OSMesa library is not installed (Debian: libosmesa6)")
def test_osmesa_renders_in_a_plain_shell():
  # make(..., gl="osmesa") failed ("'EGLPlatform' object has no attribute 'OSMesa'")
  # unless MUJOCO_GL=osmesa was exported: run it where neither variable is set.
  import subprocess
  import sys
  env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  out = subprocess.run([sys.executable, "-c", OSMESA_SCRIPT], capture_output=True,
                       text=True, timeout=180, cwd=root, env=dict(env, JAX_PLATFORMS="cpu"))
  assert out.returncode == 0, out.stderr[-3000:]
  lines = out.stdout.split("\n")
  # Each worker loaded its own backend's library, not the other's.
  assert "osmesa True False" in lines and "egl False True" in lines, out.stdout
  # The same Mesa rasteriser behind both: the same pixels, and a real picture.
  last = lines[-2].split()
  assert last[:2] == ["equal", "True"] and float(last[3]) > 5, out.stdout
