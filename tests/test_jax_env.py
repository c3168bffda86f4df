"""`make(..., renderer="jax")` and `dmcr-train --renderer jax`: the JAX env's physics equal
the pool env's, its frames are close to MuJoCo's, NEXT_STEP auto-reset and frame
stacks, determinism, few-shot looks made on the device, bad arguments, and the
device training loop (chunks, log, checkpoints, resume, the host loop's update count).

Everything is sized alike (pendulum, 2 envs, 16 px, frame skip 100, the few-shot
range levels(6)) so the env, `set_state` and the training loop share compilations.
"""

import csv
import os

import jax
import numpy as np
import pytest

import dmcr_jax
from dmcr_jax import env_base
from dmcr_jax import jax_env
from dmcr_jax.visuals.levels import levels
from dmcr_jax.train import loop, sac
from dmcr_jax.train.__main__ import parse

pytestmark = pytest.mark.xdist_group("jax_env")

# pendulum-swingup: 1,000 control steps per episode; frame skip 100 -> 10 agent steps.
TASK, SKIP, EPISODE, N, SIZE = "pendulum-swingup", 100, 10, 2, 16
RANGE = levels(6)
STEPS = 2 * EPISODE + 3
# Mean absolute difference of a 16 px frame against MuJoCo's (measured ≤ 3.2 on
# these frames; jax_render's docstring has the 84 px figures).
MAD_BOUND = 6.0
TINY = sac.SACConfig(batch_size=8, conv_channels=4, feature_dim=8, hidden_dim=16)


def _make(renderer, **kwargs):
  return dmcr_jax.make(TASK, num_envs=N, visual_seeds=RANGE, frame_skip=SKIP,
                       image_size=SIZE, seed=3, renderer=renderer, **kwargs)


@pytest.fixture(scope="module")
def envs():
  # The one-compilation check counts this module's envs only (other tests in the
  # same process, e.g. `dmcr-train --renderer jax` with the physics on the CPU, step
  # envs of other sizes through the same jitted function).
  jax_env.step.clear_cache()
  with _make("jax") as jenv, _make("pool", workers=1) as penv:
    yield jenv, penv


def _run(env, seed, actions):
  obs, info = env.reset(seed=seed)
  out = dict(obs=[obs], reward=[], truncated=[], info=[info])
  for a in actions:
    obs, reward, terminated, truncated, info = env.step(a)
    assert not terminated.any()
    out["obs"].append(np.asarray(obs))
    out["reward"].append(reward)
    out["truncated"].append(truncated)
    out["info"].append(info)
  return out


@pytest.fixture(scope="module")
def actions():
  rng = np.random.default_rng(0)
  return [rng.uniform(-1, 1, (N, 1)).astype(np.float32) for _ in range(STEPS)]


@pytest.fixture(scope="module")
def rollouts(envs, actions):
  jenv, penv = envs
  return _run(jenv, 11, actions), _run(penv, 11, actions)


@pytest.mark.slow
def test_rewards_states_and_info_equal_the_pool_env(rollouts):
  # Two programs step the same physics (the fused physics-and-frames step, the pool
  # env's physics alone): floats may differ in float32's last bits, nothing else.
  jax_run, pool_run = rollouts
  close = lambda a, b, msg="": np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6,
                                                           err_msg=msg)
  close(np.stack(jax_run["reward"]), np.stack(pool_run["reward"]))
  np.testing.assert_array_equal(np.stack(jax_run["truncated"]),
                                np.stack(pool_run["truncated"]))
  for a, b in zip(jax_run["info"], pool_run["info"]):
    assert a.keys() == b.keys()
    for k in a:
      if np.asarray(a[k]).dtype.kind == "f":
        close(a[k], b[k], k)
      else:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.slow
def test_frames_are_close_to_the_pool_env(rollouts):
  jax_run, pool_run = rollouts
  mads = [np.abs(a.astype(int) - b.astype(int)).mean(axis=(1, 2, 3))
          for a, b in zip(jax_run["obs"], pool_run["obs"])]
  assert np.max(mads) < MAD_BOUND, np.max(mads)
  # ... and the check can fail: another env's frame (another look) is far off.
  a, b = jax_run["obs"][0], pool_run["obs"][0]
  if not np.array_equal(jax_run["info"][0]["visual_seed"][[0]],
                        jax_run["info"][0]["visual_seed"][[1]]):
    assert np.abs(a[0].astype(int) - b[1].astype(int)).mean() > MAD_BOUND


@pytest.mark.slow
def test_autoreset_and_frame_stacks_at_episode_boundaries(rollouts, envs):
  obs, info = rollouts[0]["obs"], rollouts[0]["info"]
  assert obs[0].shape == (N, SIZE, SIZE, 9) and obs[0].dtype == np.uint8
  np.testing.assert_array_equal(obs[0][..., 0:3], obs[0][..., 6:9])
  total = np.zeros(N)
  for t in range(1, STEPS + 1):
    reward, truncated = rollouts[0]["reward"][t - 1], rollouts[0]["truncated"][t - 1]
    frame = obs[t][..., -3:]
    if t in (EPISODE + 1, 2 * EPISODE + 2):      # the step after a truncation resets
      assert not truncated.any() and (reward == 0).all()
      assert (info[t]["episode_step"] == 0).all() and (info[t]["episode_return"] == 0).all()
      for k in range(3):
        np.testing.assert_array_equal(obs[t][..., 3 * k:3 * k + 3], frame)
      total[:] = 0
    else:
      assert truncated.all() == (t in (EPISODE, 2 * EPISODE + 1)) == truncated.any()
      np.testing.assert_array_equal(obs[t][..., :-3], obs[t - 1][..., 3:])
      total += reward
      np.testing.assert_allclose(info[t]["episode_return"], total, rtol=1e-5)
    assert list(info[t]["episode_index"]) == [t // (EPISODE + 1)] * N
  np.testing.assert_array_equal(envs[0].render(), obs[-1][..., -3:])


@pytest.mark.slow
def test_few_shot_looks_are_drawn_in_range_and_made_on_the_device(rollouts, envs):
  jenv = envs[0]
  seeds = np.stack([i["visual_seed"] for i in rollouts[0]["info"]])
  assert RANGE.contains_all(seeds)
  assert len(np.unique(seeds[[0, EPISODE + 1, 2 * EPISODE + 2]])) > 1   # new draws
  assert (seeds[1:EPISODE + 1] == seeds[0]).all()                  # fixed in an episode
  # The state's looks are the looks of the env's current seeds, made on the device:
  # the host's float64 path to float32 rounding (integer fields equal).
  rm, scene = jax_env.scene_of("pendulum")
  want = jax_env.host_looks(scene, rm, seeds[-1], "all")
  for a, b in zip(jax.tree.leaves(jenv.pixel_state.look), jax.tree.leaves(want)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-6)


@pytest.mark.slow
def test_same_seed_same_pixels_and_one_compilation(rollouts, envs, actions):
  jenv = envs[0]
  again = _run(jenv, 11, actions[:EPISODE + 2])
  np.testing.assert_array_equal(np.stack(again["obs"]), np.stack(rollouts[0]["obs"][:EPISODE + 3]))
  other = _run(jenv, 12, actions[:1])
  assert not np.array_equal(other["obs"][0], again["obs"][0])
  assert jax_env.step._cache_size() == 1       # every step reused one compilation


@pytest.mark.slow
def test_render_inputs_alone_draw_what_the_whole_physics_draws(envs, actions):
  # What the env moves to the render device when the physics runs on another
  # (`render_inputs`) gives the fused step's frames, stacks and looks, also for
  # envs that reset (a new look drawn from the range).
  jenv = envs[0]
  jenv.reset(seed=5)
  env, state = jenv.functional, jenv.pixel_state
  # Inputs committed to the device, as the env passes them: the env's compilation
  # of `step` is reused (an uncommitted argument compiles the same program again).
  on_device = lambda x: jax.device_put(x, jax.devices()[0])
  after = jax_env.step(env, state, on_device(actions[0]))[0]
  inputs = jax_env.render_inputs(after.physics, env.drawn_variables)
  for resetting in (state.physics.needs_reset, on_device(np.array([True, False]))):
    want = jax_env.observe(env, state, after.physics, resetting)
    got = jax_env.observe_inputs(env, state.replace(physics=None), inputs, resetting)
    assert got.physics is None
    np.testing.assert_array_equal(np.asarray(got.obs), np.asarray(want.obs))
    for a, b in zip(jax.tree.leaves(got.look), jax.tree.leaves(want.look)):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  np.testing.assert_array_equal(np.asarray(want.obs[1]), np.asarray(after.obs[1]))


@pytest.mark.slow
def test_set_state_restarts_the_stacks_from_that_state(envs):
  jenv = envs[0]
  jenv.reset(seed=5)
  obs, _, _, _, _ = jenv.step(np.zeros((N, 1), np.float32))
  state = jenv.state
  restarted, info = jenv.set_state(state)
  assert (info["episode_step"] == 1).all()
  for k in range(3):
    np.testing.assert_array_equal(restarted[..., 3 * k:3 * k + 3], obs[..., -3:])
  with pytest.raises(ValueError, match="shaped like"):
    jenv.set_state(jax.tree.map(lambda x: x[:1], state))


@pytest.mark.slow
def test_first_compile_is_announced_once_and_a_closed_env_refuses_to_step(
    envs, monkeypatch, capfd):
  # Sized as `envs`, so nothing compiles again; both renderers.
  monkeypatch.setattr(env_base, "_ANNOUNCED", set())
  for renderer, what in (("jax", "physics and ray-cast renderer"), ("pool", "physics")):
    for again in (False, True):
      env = _make(renderer, **({"workers": 1} if renderer == "pool" else {}))
      env.reset(seed=1)
      env.step(np.zeros((N, 1), np.float32))
      env.close()
      env.close()   # idempotent
      for call in (lambda: env.step(np.zeros((N, 1), np.float32)), env.reset,
                   lambda: env.set_visuals(0)):
        with pytest.raises(RuntimeError, match=f"this {type(env).__name__} is closed"):
          call()
      lines = [ln for ln in capfd.readouterr().err.splitlines() if "compiling" in ln]
      if again:   # an env of a shape already announced
        assert lines == []
      else:
        assert len(lines) == 1, lines
        assert lines[0].startswith(f"dmcr_jax: compiling {TASK}'s {what} for {N} envs on cpu")


@pytest.mark.parametrize("kwargs, match", [
    (dict(renderer="opengl"), "Unknown renderer 'opengl'; valid: pool, jax"),
    (dict(renderer="jax", quality="fast"), "quality apply only to renderer='pool'"),
    (dict(renderer="jax", workers=2, gl="egl"), "gl, workers apply only to renderer='pool'"),
    (dict(shadows=False), "shadows apply only to renderer='jax'"),
    (dict(renderer="jax", num_envs=2, visual_seeds=[levels(2), 0]),
     "mixes SeedRanges and fixed seeds"),
    (dict(render_kernel=True), "render_kernel apply only to renderer='jax'"),
    (dict(renderer="jax", egl_devices=[1]), "egl_devices apply only to renderer='pool'"),
    (dict(egl_devices=[-1]), "EGL device indices"),
    pytest.param(dict(renderer="jax", render_kernel=True), "fused render kernel needs a GPU",
                 marks=pytest.mark.skipif(jax.default_backend() == "gpu", reason="a GPU")),
])
def test_make_rejects_bad_renderer_arguments(kwargs, match):
  with pytest.raises(ValueError, match=match):
    dmcr_jax.make(TASK, **kwargs)


@pytest.mark.parametrize("argv, match", [
    (["--renderer", "gl"], "Unknown renderer 'gl'; valid: pool, jax"),
    (["--renderer", "jax", "--quality", "fast"], "apply only to renderer 'pool'"),
    (["--renderer", "jax", "--chunk-steps", "0"], "chunk_steps must be a positive int"),
    (["--renderer", "jax", "--egl-devices", "1"], "apply only to renderer 'pool'"),
    (["--egl-devices", "1,a"], "want EGL device indices"),
])
def test_train_rejects_bad_renderer_arguments(argv, match, capsys):
  with pytest.raises(SystemExit):
    parse(argv)
  assert match in capsys.readouterr().err


def _host_loop_updates(start, steps, n, warmup, utd):
  """Critic updates the host loop (dmcr_jax.train.loop) makes from `start` to `steps`
  (every buffer can be sampled from the first update on)."""
  owed, updates, step = 0.0, 0, start
  while step < steps:
    before, step = step, step + n
    if step > warmup:
      owed += utd * (step - max(before, warmup))
      pairs = int(owed // 2)
      updates += 2 * pairs
      owed -= 2 * pairs
  return updates


@pytest.mark.slow
def test_device_training_runs_chunks_logs_checkpoints_and_resumes(tmp_path):
  # The demo's training run (test_demo: one agent of 2 envs, a 24-transition buffer,
  # 8 warm-up steps, chunks of 12 vector steps), so both compile one chunk program.
  out = str(tmp_path / "run")
  base = dict(task=TASK, action_repeat=SKIP, image_size=SIZE, num_envs=N, seeds=(0,),
              visual_seeds=f"levels:{len(RANGE)}", buffer_capacity=24, warmup_steps=8,
              log_every=5, renderer="jax", chunk_steps=12, out_dir=out, sac=TINY)
  chunk = 12 * N                                          # transitions per agent a chunk
  cfg = loop.TrainConfig(steps=2 * chunk, checkpoint_every=chunk, **base)
  summary = loop.train(cfg, progress=False)
  assert summary["steps"] == 2 * chunk and not summary["interrupted"]
  ckpt = os.path.join(out, "checkpoints")
  assert sorted(int(d) for d in os.listdir(ckpt) if d.isdigit()) == [chunk, 2 * chunk]
  _, agents, step = loop.load_run(out)
  assert step == 2 * chunk
  np.testing.assert_array_equal(np.asarray(agents.step),
                                [_host_loop_updates(0, 2 * chunk, N, 8, 1.0)])
  # Resume: agents, step and key restored; new episodes, empty buffers.
  cfg2 = loop.TrainConfig(steps=3 * chunk, checkpoint_every=0, **base)
  summary = loop.train(cfg2, resume=True, progress=False)
  assert summary["steps"] == 3 * chunk
  _, agents2, step = loop.load_run(out)
  assert step == 3 * chunk and (np.asarray(agents2.step) > np.asarray(agents.step)).all()
  with open(os.path.join(out, "log.csv")) as f:
    rows = list(csv.DictReader(f))
  # Episodes of 10 vector steps (N transitions each) end at vector steps 10 and 21,
  # then (resumed at 24) at 34: one row per env.
  assert [(int(r["step"]), int(r["agent"])) for r in rows] == [
      (s * N, 0) for s in (10, 21, 34) for _ in range(N)]
  assert rows[0]["critic_loss"] and np.isfinite(float(rows[-1]["critic_loss"]))
  assert all(np.isfinite(float(r["episode_return"])) for r in rows)
  assert os.path.exists(os.path.join(out, "learning_curve.png"))
