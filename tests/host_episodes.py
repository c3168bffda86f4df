"""The zero-shot protocol's episodes stepped from the host: the reference the
protocol's batched passes are checked against (tests/test_protocol*.py)."""

import numpy as np


def host_episode_returns(env, act, resets) -> np.ndarray:
  """One episode of every env of `env` (a `dmcr_jax.make` vector env), reset with
  `resets`, its actions `act(obs)` in [−1, 1] mapped onto the action bounds, a host
  round trip every step; the episode returns, float64 (N,)."""
  obs, _ = env.reset(seed=resets)
  low, high = env.single_action_space.low, env.single_action_space.high
  for _ in range(env.episode_length):
    a = np.asarray(act(obs))
    obs, _, _, truncated, info = env.step((low + (a + 1.0) * 0.5 * (high - low)).astype(np.float32))
  assert truncated.all()
  return np.asarray(info["episode_return"], np.float64)
