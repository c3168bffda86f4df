"""The single-env adapters pass gymnasium's checker and follow dm_env's protocol."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import dmcr_jax

pytestmark = pytest.mark.xdist_group("env")


def test_every_task_is_registered():
  for task in dmcr_jax.ALL_TASKS:
    assert f"dmcr/{task}-v0" in gymnasium.registry


@pytest.mark.slow
def test_gymnasium_env_checker_passes():
  env = gymnasium.make("dmcr/pendulum-swingup-v0", visual_seed=3, frame_skip=100,
                       image_size=32, workers=1, render_mode="rgb_array")
  try:
    check_env(env.unwrapped)
    obs, info = env.reset(seed=0)
    assert obs.shape == (32, 32, 9) and info["visual_seed"] == 3
    np.testing.assert_array_equal(env.render(), obs[..., -3:])
    steps, truncated = 0, False
    while not truncated:
      obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
      steps += 1
      assert not terminated and isinstance(reward, float)
    assert steps == 10
  finally:
    env.close()


@pytest.mark.slow
def test_vector_env_spaces_and_api():
  # Sized as test_env's memory test (same group): one physics compilation for both.
  with dmcr_jax.make("pendulum-swingup", num_envs=2, visual_seeds=dmcr_jax.TEST_SEEDS,
                     frame_skip=100, image_size=16, workers=1) as env:
    assert isinstance(env, gymnasium.vector.VectorEnv)
    assert env.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert dmcr_jax.TEST_SEEDS.contains_all(info["visual_seed"])
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs)
    assert reward.shape == terminated.shape == truncated.shape == (2,)
    assert info["state"].shape == (2, env.task.observation_size)


@pytest.mark.slow
def test_dm_env_protocol():
  env = dmcr_jax.DmEnv("pendulum-swingup", visual_seed=5, frame_skip=100, image_size=16,
                       workers=1)
  try:
    spec = env.observation_spec()["pixels"]
    ts = env.reset()
    assert ts.first() and ts.reward is None
    spec.validate(ts.observation["pixels"])
    env.action_spec().validate(np.zeros(1, np.float32))
    steps = 0
    while not ts.last():
      ts = env.step(np.zeros(1, np.float32))
      steps += 1
      assert ts.discount == 1.0
    assert steps == 10
    assert env.step(np.zeros(1, np.float32)).first()  # step after LAST starts anew
  finally:
    env.close()


@pytest.mark.slow
def test_gymnasium_vector_episode_statistics_wrapper_over_episode_ends():
  from gymnasium.wrappers.vector import RecordEpisodeStatistics
  env = RecordEpisodeStatistics(dmcr_jax.make("pendulum-swingup", num_envs=2, frame_skip=100,
                                              image_size=16, workers=1))
  try:
    obs, info = env.reset(seed=[0, 1])  # gymnasium's per-env seeds
    assert info["_episode_index"].all() and "episode" not in info
    ends = 0
    for t in range(1, 23):  # two episodes of 10 steps each, and a reset step between
      obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
      if truncated.any():
        ends += 1
        assert truncated.all() and info["_episode"].all()
        np.testing.assert_allclose(info["episode"]["r"], info["episode_return"], rtol=1e-6)
        assert list(info["episode"]["l"]) == [10, 10]
    assert ends == 2 and len(env.return_queue) == 4
  finally:
    env.close()


@pytest.mark.slow
def test_gymnasium_episode_statistics_wrapper_over_episode_ends():
  env = gymnasium.wrappers.RecordEpisodeStatistics(gymnasium.make(
      "dmcr/pendulum-swingup-v0", frame_skip=100, image_size=16, workers=1))
  try:
    env.reset(seed=0)
    ends = 0
    for _ in range(2):
      truncated = False
      while not truncated:
        _, _, _, truncated, info = env.step(env.action_space.sample())
      ends += 1
      assert info["episode"]["l"] == 10
      np.testing.assert_allclose(info["episode"]["r"], info["episode_return"], rtol=1e-6)
      assert not any(k.startswith("_") for k in info)
      env.reset()
    assert ends == 2
  finally:
    env.close()


def test_reset_takes_one_seed_per_env_and_refuses_bad_seeds():
  with dmcr_jax.make("pendulum-swingup", num_envs=2, frame_skip=100, image_size=16,
                     workers=1) as env:
    _, a = env.reset(seed=[3, 5])
    _, b = env.reset(seed=[5, 3])
    _, c = env.reset(seed=[3, 9])
    # Env i's initial state depends on seed[i] alone.
    np.testing.assert_array_equal(a["state"], b["state"][::-1])
    np.testing.assert_array_equal(a["state"][0], c["state"][0])
    assert not np.array_equal(a["state"][1], c["state"][1])
    for bad in (2**70, -1, [1, 2, 3], 1.5, [0, 2**32]):
      with pytest.raises(ValueError, match=r"seed must be an int in \[0, 2\*\*32\)|2 ints"):
        env.reset(seed=bad)
  with pytest.raises(ValueError, match="seed"):
    dmcr_jax.make("pendulum-swingup", seed=2**70)
