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


def test_vector_env_spaces_and_api():
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
