"""The batched pixel env: physics equal to the models', NEXT_STEP auto-reset, frame
stacks, determinism, few-shot seed ranges, bad input, memory over 5,000 steps."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dmcr_jax
from dmcr_jax import physics_env
from dmcr_jax.visuals import render_model as rmod
from dmcr_jax.visuals.levels import (TEST_SEEDS, TRAIN_SEEDS, EnvRanges, SeedBounds, SeedRange,
                                     levels)

pytestmark = pytest.mark.xdist_group("env")

# pendulum-swingup: 1,000 control steps per episode; frame skip 100 -> 10 agent steps.
TASK, SKIP, EPISODE = "pendulum-swingup", 100, 10
SEEDS = [0, 5, 7]


@pytest.fixture(scope="module")
def env():
  with dmcr_jax.make(TASK, num_envs=3, visual_seeds=SEEDS, frame_skip=SKIP, image_size=32,
                     workers=2, seed=3) as e:
    yield e


@pytest.fixture(scope="module")
def one_step(env):
  """`Task.step` for a single env, jitted once for the tests that compare with it."""
  return jax.jit(env.task.step)


def _actions(rng, env, n=None):
  return rng.uniform(-1, 1, (n or env.num_envs, env.task.action_size)).astype(np.float32)


@pytest.mark.slow
def test_rewards_and_states_equal_the_model(env, one_step):
  task = env.task
  env.reset(seed=11)
  state = env.state.task
  # skip_step is `frame_skip` plain Task.steps with the rewards summed.
  s = s0 = jax.tree.map(lambda x: x[0], state)
  total = 0.0
  for _ in range(SKIP):
    s = one_step(s, jnp.ones(1))
    total += float(s.reward)
  s_skip, r_skip = jax.jit(lambda s: physics_env.skip_step(task, s, jnp.ones(1), SKIP))(s0)
  np.testing.assert_allclose(float(r_skip), total, rtol=1e-5)
  np.testing.assert_allclose(np.asarray(s_skip.obs), np.asarray(s.obs), atol=1e-5)
  # The env's rewards and state features are the vmapped model's (to float32's last
  # bits, grown over the episode: the env's jitted step is another XLA program).
  step = jax.jit(jax.vmap(lambda s, a: physics_env.skip_step(task, s, a, SKIP)))
  rng = np.random.default_rng(0)
  for _ in range(EPISODE):
    a = _actions(rng, env)
    _, reward, _, _, info = env.step(a)
    state, want = step(state, jnp.asarray(a))
    np.testing.assert_allclose(reward, np.asarray(want), rtol=1e-5, atol=2e-5)
    np.testing.assert_allclose(info["state"], np.asarray(state.obs), rtol=1e-5, atol=2e-5)


def test_autoreset_and_frame_stack_at_episode_boundaries(env):
  rng = np.random.default_rng(1)
  obs, info = env.reset(seed=4)
  assert obs.shape == (3, 32, 32, 9) and obs.dtype == np.uint8
  np.testing.assert_array_equal(obs[..., 0:3], obs[..., 6:9])  # first frame, repeated
  assert list(info["episode_index"]) == [0, 0, 0] and list(info["episode_step"]) == [0, 0, 0]
  total = np.zeros(3)
  for t in range(1, 2 * EPISODE + 3):
    prev = obs
    obs, reward, terminated, truncated, info = env.step(_actions(rng, env))
    assert not terminated.any()
    frame = env.render()
    np.testing.assert_array_equal(obs[..., -3:], frame)
    if t in (EPISODE + 1, 2 * EPISODE + 2):  # the step after a truncation resets
      assert not truncated.any() and (reward == 0).all()
      assert (info["episode_step"] == 0).all() and (info["episode_return"] == 0).all()
      for k in range(3):
        np.testing.assert_array_equal(obs[..., 3 * k:3 * k + 3], frame)
      total[:] = 0
    else:
      truncated_now = t in (EPISODE, 2 * EPISODE + 1)
      assert truncated.all() == truncated_now and truncated.any() == truncated_now
      np.testing.assert_array_equal(obs[..., :-3], prev[..., 3:])
      total += reward
      np.testing.assert_allclose(info["episode_return"], total, rtol=1e-5)
    assert list(info["episode_index"]) == [t // (EPISODE + 1)] * 3
  assert list(info["visual_seed"]) == SEEDS


def test_pixels_are_the_reference_render_of_the_state(env):
  env.reset(seed=5)
  obs, *_ = env.step(_actions(np.random.default_rng(2), env))
  rm = rmod.build_render_model("pendulum")
  looks = rmod.prepare(rm, rm.sample(SEEDS, vary="all"))
  qpos = np.asarray(env.state.task.data.qpos, np.float64)
  with rmod.FrameRenderer(rm, 32, 32) as fr:
    for i in range(3):
      np.testing.assert_array_equal(obs[i, ..., -3:], fr.render(looks, qpos[i], index=i))
  assert not np.array_equal(obs[0], obs[1])  # different looks


def test_same_seed_same_pixels(env):
  def run(seed):
    rng = np.random.default_rng(9)
    frames = [env.reset(seed=seed)[0]]
    frames += [env.step(_actions(rng, env))[0] for _ in range(EPISODE + 3)]
    return np.stack(frames)

  a, b = run(21), run(21)
  np.testing.assert_array_equal(a, b)
  assert not np.array_equal(a, run(22))
  # reset() without a seed continues the key stream: a new episode.
  env.reset(seed=21)
  assert not np.array_equal(env.reset()[0], a[0])


def test_step_async_then_step_wait_is_step(env):
  # The training loop dispatches its updates between the two halves; together
  # they must give exactly `step`, and be called in order.
  rng = np.random.default_rng(4)
  actions = [_actions(rng, env) for _ in range(3)]
  first = env.reset(seed=5)[0].copy()
  plain = [env.step(a) for a in actions]
  env.reset(seed=5)
  with pytest.raises(RuntimeError, match="without a pending"):
    env.step_wait()
  for a, want in zip(actions, plain):
    env.step_async(a)
    with pytest.raises(RuntimeError, match="twice"):
      env.step_async(a)
    got = env.step_wait()
    for g, w in zip(got[:4], want[:4]):
      np.testing.assert_array_equal(g, w)
  # The pool env's step_submit (frames handed out, not waited for) in between.
  env.reset(seed=5)
  with pytest.raises(RuntimeError, match="without a pending"):
    env.step_submit()
  for a, want in zip(actions, plain):
    env.step_async(a)
    env.step_submit()
    with pytest.raises(RuntimeError, match="without a pending"):
      env.step_submit()
    got = env.step_wait()
    for g, w in zip(got[:4], want[:4]):
      np.testing.assert_array_equal(g, w)
  env.step_async(actions[0])
  env.step_submit()
  np.testing.assert_array_equal(env.reset(seed=5)[0], first)  # the frames in flight dropped


def test_set_looks_gives_each_env_its_own_factors(env):
  # Every condition's envs in one batch: env i shows its seed under varies[i], as
  # set_visuals(seeds, vary=varies[i]) shows it.
  rng = np.random.default_rng(6)
  actions = [_actions(rng, env) for _ in range(2)]
  seeds, varies = [11, 12, 2**30 + 3], ["floor,light", "none", "all"]

  def run():
    return np.stack([env.reset(seed=8)[0]] + [env.step(a)[0] for a in actions])

  env.set_looks(seeds, varies)
  got = run()
  for i, vary in enumerate(varies):
    env.set_visuals(seeds, vary=vary)
    np.testing.assert_array_equal(got[:, i], run()[:, i])
  with pytest.raises(ValueError, match="3 varies"):
    env.set_looks(seeds, varies[:2])
  with pytest.raises(ValueError, match="wheels"):
    env.set_looks(seeds, ["floor", "none", "wheels"])
  env.set_visuals(SEEDS, vary="all")  # as the fixture built it


def test_set_visuals_and_set_state_act_like_a_fresh_env(env):
  # New looks on the running env give the pixels a fresh env with those seeds gives.
  rng = np.random.default_rng(4)
  actions = [_actions(rng, env) for _ in range(3)]
  env.set_visuals([11, 12, 2**30 + 3], vary="floor,light")
  with pytest.raises(RuntimeError, match="reset"):
    env.step(actions[0])
  got = [env.reset(seed=8)[0]] + [env.step(a)[0] for a in actions]
  with dmcr_jax.make(TASK, num_envs=3, visual_seeds=[11, 12, 2**30 + 3], vary="floor,light",
                     frame_skip=SKIP, image_size=32, workers=2, seed=3) as fresh:
    want = [fresh.reset(seed=8)[0]] + [fresh.step(a)[0] for a in actions]
  np.testing.assert_array_equal(np.stack(got), np.stack(want))
  # set_state: env 0's state in every env → the same pixels where the looks agree.
  env.set_visuals(5, vary="all")
  env.reset(seed=1)
  first = jax.tree.map(lambda x: jnp.broadcast_to(x[:1], x.shape), env.state)
  obs, info = env.set_state(first)
  assert (obs == obs[:1]).all() and (info["episode_step"] == info["episode_step"][0]).all()
  with pytest.raises(ValueError, match="shaped like"):
    env.set_state(jax.tree.map(lambda x: x[:2], env.state))
  env.set_visuals(SEEDS, vary="all")  # as the fixture built it


def test_bad_input_is_rejected_and_the_env_keeps_working(env):
  obs, _ = env.reset(seed=8)
  good = np.zeros((3, 1), np.float32)
  for bad, match in [(np.zeros((2, 1)), r"shape \(3, 1\)"), (np.zeros(3), r"shape \(3, 1\)"),
                     (np.array([[0.], [np.nan], [0.]]), r"finite; envs \[1\]"),
                     (np.array([[np.inf], [0.], [0.]]), r"finite; envs \[0\]")]:
    with pytest.raises(ValueError, match=match):
      env.step(bad)
  obs1, _, _, _, info = env.step(good)
  assert list(info["episode_step"]) == [1, 1, 1]  # the rejected calls did not step
  env.reset(seed=8)
  np.testing.assert_array_equal(env.step(good)[0], obs1)
  with pytest.raises(ValueError, match="no options"):
    env.reset(options={"x": 1})


@pytest.mark.parametrize("kwargs, match", [
    (dict(num_envs=0), "num_envs must be a positive int"),
    (dict(num_envs=-2), "num_envs must be a positive int"),
    (dict(num_envs=3, visual_seeds=[1, 2]), "got 2 seeds for 3 envs"),
    (dict(visual_seeds=-1), r"\[0, 2\*\*31 - 1\]"),
    (dict(visual_seeds=1.5), "must be integers"),
    (dict(visual_seeds=SeedRange(2**30 - 5, 2**30 + 5)), "straddles"),
    (dict(vary="floor,sky"), "Unknown visual factor"),
    (dict(frame_skip=0), "frame_skip must be a positive int"),
    (dict(frame_stack=0), "frame_stack must be a positive int"),
    (dict(image_size=(32, 0)), "image width must be a positive int"),
    (dict(quality="ultra"), "valid: exact, fast, fastest"),
    (dict(gl="vulkan"), "valid: egl, osmesa"),
    # Checked before any worker starts (camera 99 failed inside a render worker;
    # the others were accepted silently).
    (dict(camera=99), r"camera must be an id in \[0, 2\) or a name .*fixed, lookat"),
    (dict(camera="top"), "camera must be an id"),
    (dict(vary=""), "vary is empty"),
    (dict(vary="target,floor"), "target do\\(es\\) not apply to pendulum"),
    (dict(workers=0), "workers must be a positive int"),
    (dict(seed=2**70), r"seed must be an int in \[0, 2\*\*32\)"),
    (dict(render_pool="mine"), "render_pool must be a RenderPool"),
])
def test_make_rejects_bad_arguments(kwargs, match):
  with pytest.raises((ValueError, TypeError), match=match):
    dmcr_jax.make(TASK, **kwargs)


def test_a_shared_render_pool_must_draw_the_env_s_sizes(env):
  with pytest.raises(ValueError, match="this env needs"):
    dmcr_jax.make(TASK, num_envs=3, image_size=16, frame_skip=SKIP, render_pool=env._pool)


def test_make_rejects_unknown_task():
  with pytest.raises(ValueError, match="Valid tasks: ball_in_cup-catch"):
    dmcr_jax.make("walker-fly")


def test_seed_ranges_are_disjoint_and_sampled_inside():
  assert not TRAIN_SEEDS.overlaps(TEST_SEEDS)
  assert TRAIN_SEEDS.stop == TEST_SEEDS.start and TEST_SEEDS.stop == 2**31 - 1
  r = levels(1000)
  assert (r.start, r.stop, len(r)) == (0, 1000, 1000) and not r.overlaps(TEST_SEEDS)
  draws = np.asarray(jax.jit(lambda k: r.sample(k, (20000,)))(jax.random.key(0)))
  assert draws.min() >= 0 and draws.max() < 1000 and len(np.unique(draws)) > 990
  assert TEST_SEEDS.contains_all(TEST_SEEDS.first(100))
  assert not any(TRAIN_SEEDS.contains_all([s]) for s in TEST_SEEDS.first(100))
  with pytest.raises(ValueError, match="overlaps the held-out test range"):
    levels(10, start=2**30 - 5)
  with pytest.raises(ValueError, match="start < stop"):
    SeedRange(5, 5)


def test_seed_bounds_draw_what_the_static_ranges_draw():
  """Ranges passed as traced `SeedBounds` (the pool env's physics) draw, key for key,
  the seeds their static `SeedRange`/`EnvRanges` draw; one compilation serves all."""
  ranges = [levels(1), levels(7, start=3), TRAIN_SEEDS, TEST_SEEDS]
  per_env = EnvRanges(tuple(ranges))
  keys = jax.random.split(jax.random.key(5), 64)
  traces = []

  def draw(bounds, keys):
    traces.append(1)
    return jax.vmap(lambda k: jax.vmap(lambda i: bounds.sample(k, i))(jnp.arange(4)))(keys)

  draw = jax.jit(draw)
  for r in ranges:
    got = np.asarray(draw(SeedBounds.of(r, 4), keys))
    want = np.asarray(jax.vmap(r.sample)(keys))
    np.testing.assert_array_equal(got, np.repeat(want[:, None], 4, axis=1))
  got = np.asarray(draw(SeedBounds.of(per_env, 4), keys))
  want = np.asarray(jax.vmap(lambda k: jnp.stack([per_env.sample(k, i) for i in range(4)]))(keys))
  np.testing.assert_array_equal(got, want)
  assert len(traces) == 1
  # Fixed seeds stay an int32 array; ranges become bounds of one range per env.
  assert physics_env.seed_argument([3, 4], 2).dtype == np.int32
  np.testing.assert_array_equal(physics_env.seed_argument(levels(5), 3).stop, [5, 5, 5])
  with pytest.raises(ValueError, match="2 ranges for 3 envs"):
    SeedBounds.of(EnvRanges((levels(1), levels(2))), 3)


@pytest.mark.slow
def test_few_shot_draws_a_new_look_each_episode_inside_the_range():
  # Two envs with seeds drawn from a range, as the memory test's: one physics
  # compilation for both; 16 draws, 2 envs × 8 episodes.
  with dmcr_jax.make(TASK, num_envs=2, visual_seeds=levels(50, start=100), frame_skip=SKIP,
                     image_size=16, workers=1, seed=0) as env:
    obs, info = env.reset()
    seen = [info["visual_seed"]]
    for _ in range(7 * (EPISODE + 1)):
      obs, _, _, _, info = env.step(np.zeros((2, 1), np.float32))
      if (info["episode_step"] == 0).all():
        seen.append(info["visual_seed"])
  seen = np.stack(seen)
  assert seen.shape == (8, 2)
  assert ((seen >= 100) & (seen < 150)).all()
  assert len(np.unique(seen)) > 8  # new draws per env and per episode


def _rss_mib(pids) -> float:
  total = 0
  for pid in pids:
    with open(f"/proc/{pid}/status") as f:
      total += next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))
  return total / 1024


def _draw_every_bank_texture(pool) -> None:
  """Renders each floor and sky of the bank once in `pool`'s workers, which
  upload a bank texture into their GL context the first time a look draws it."""
  rm, n = pool.rm, pool.max_batch
  looks = rmod.prepare(rm, rm.sample(np.arange(n)))
  qpos = np.tile(rm.model.qpos0, (n, 1))
  for k in range(0, max(rm.bank.num_floors, rm.bank.num_backgrounds), n):
    looks.floor_matid = rm.floor_mat0 + (k + np.arange(n)) % rm.bank.num_floors
    looks.skybox_tex = rm.bg_tex0 + (k + np.arange(n)) % rm.bank.num_backgrounds
    pool.render(qpos, looks)


@pytest.mark.slow
def test_memory_does_not_grow_over_200_episodes():
  # A new held-out look every episode (10 steps and the reset step); sized as
  # test_adapters' episode statistics test (same group), whose physics compilation
  # this reuses. Over the 2,000 measured steps (about 180 episodes) the bound
  # catches a leak of 4 KiB a step (less than one step's frames) or of 45 KiB an
  # episode. The bank's textures, which the workers receive as looks first draw
  # them (at most the bank, not a leak), are all drawn during the warm-up.
  with dmcr_jax.make(TASK, num_envs=2, visual_seeds=TEST_SEEDS, frame_skip=SKIP,
                     image_size=16, workers=1, quality="fastest") as env:
    env.reset(seed=0)
    a = np.zeros((2, 1), np.float32)
    pids = [os.getpid()] + env._pool.pids
    _draw_every_bank_texture(env._pool)
    for _ in range(300):  # warm up: compile, allocator pools
      env.step(a)
    before = _rss_mib(pids)
    for _ in range(2000):
      _, _, _, _, info = env.step(a)
    after = _rss_mib(pids)
  assert info["episode_index"].min() >= 200  # 200 episodes went by (with resets)
  assert after - before < 8, f"RSS grew from {before:.1f} to {after:.1f} MiB"


def test_frame_skip_that_does_not_divide_the_episode_ends_it_on_time(env, one_step):
  task = env.task
  env.reset(seed=0)
  s = jax.tree.map(lambda x: x[0], env.state.task).replace(step_count=jnp.int32(900))
  ref, total = s, 0.0
  for _ in range(100):  # only 100 control steps are left of the episode
    ref = one_step(ref, jnp.ones(1))
    total += float(ref.reward)
  out, reward = jax.jit(lambda s: physics_env.skip_step(task, s, jnp.ones(1), 300))(s)
  assert int(out.step_count) == 1000 and bool(out.done)
  np.testing.assert_allclose(float(reward), total, rtol=1e-5)
  np.testing.assert_allclose(np.asarray(out.obs), np.asarray(ref.obs), atol=1e-5)


def test_views_of_shared_memory_stay_valid_until_the_step_after_next():
  # Sized like the module's env (3 envs, fixed seeds, SKIP): its physics compilation is reused.
  with dmcr_jax.make(TASK, num_envs=3, visual_seeds=[1, 2, 3], frame_skip=SKIP, image_size=16,
                     workers=1, copy_obs=False) as env:
    a = np.zeros((3, 1), np.float32)
    o0, _ = env.reset(seed=0)
    c0 = o0.copy()
    o1 = env.step(a)[0]
    np.testing.assert_array_equal(o0, c0)  # (o_t, o_t+1) can be stored together
    np.testing.assert_array_equal(o1[..., :-3], c0[..., 3:])
    o2 = env.step(a)[0]
    assert np.shares_memory(o0, o2) and not np.shares_memory(o1, o2)
