"""One DMCR env behind the standard single-env APIs: gymnasium and dm_env.

- `GymEnv` is a `gymnasium.Env`; every task is registered with gymnasium as
  `dmcr/<task>-v0` (e.g. `gymnasium.make("dmcr/walker-walk-v0", visual_seed=3)`)
  when `dmcr_jax` is imported. Observations are uint8 (H, W, 3·frame_stack);
  episodes end with `truncated=True` at the time limit (no TimeLimit wrapper is
  needed). `render_mode="rgb_array"` makes `render()` return the latest frame.
- `DmEnv` is a `dm_env.Environment` in dm_control's pixel-wrapper style: the
  observation is `{"pixels": (H, W, 3·frame_stack) uint8}`, the last step of an
  episode is a truncation (`StepType.LAST`, discount 1.0), and `step` after it
  starts a new episode, as dm_env prescribes.

Both run a one-env `PixelVectorEnv` (`dmcr_jax.make`): the same physics, visual
seeds, frame skip and render pool. `visual_seed` takes an int or a `SeedRange`
(a new look every episode); other keywords go to `dmcr_jax.make`. `close()`
stops the env's workers at once; an env never closed (gymnasium code rarely
closes) is closed at interpreter exit, so the process still exits promptly.
"""

from __future__ import annotations

from typing import Any

import dm_env
import gymnasium
import numpy as np
from dm_env import specs

from dmcr_jax import _ENV_ID as ENV_ID  # "dmcr/{task}-v0"
from dmcr_jax.env_pool import PixelVectorEnv


def _first(info: dict) -> dict:
  """The one env's info (the vector env's "_<key>" masks dropped)."""
  return {k: v[0] for k, v in info.items() if not k.startswith("_")}


class GymEnv(gymnasium.Env):
  """One DMCR task with pixel observations as a `gymnasium.Env`.

  Args:
    task: a task name, e.g. "walker-walk".
    visual_seed: an int, or a `SeedRange` to draw every episode's look from.
    render_mode: None or "rgb_array".
    **make_kwargs: the other arguments of `dmcr_jax.make` (vary, frame_skip,
      frame_stack, image_size, camera, seed, workers, quality, gl).
  """

  metadata = {"render_modes": ["rgb_array"]}

  def __init__(self, task: str, visual_seed: Any = 0, render_mode: str | None = None,
               **make_kwargs):
    if render_mode not in (None, "rgb_array"):
      raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
    if "num_envs" in make_kwargs or "visual_seeds" in make_kwargs:
      raise ValueError("GymEnv is one env: use visual_seed=, not num_envs/visual_seeds")
    self._vec = PixelVectorEnv(task, num_envs=1, visual_seeds=visual_seed, **make_kwargs)
    self.render_mode = render_mode
    self.observation_space = self._vec.single_observation_space
    self.action_space = self._vec.single_action_space
    self.metadata = dict(self.metadata, render_fps=1.0 / (
        self._vec.task.control_timestep * self._vec.frame_skip))

  def reset(self, *, seed: int | None = None, options: dict | None = None):
    super().reset(seed=seed)
    obs, info = self._vec.reset(seed=seed, options=options)
    return obs[0], _first(info)

  def step(self, action):
    obs, reward, terminated, truncated, info = self._vec.step(np.asarray(action)[None])
    return (obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]),
            _first(info))

  def render(self):
    frames = self._vec.render()
    return None if frames is None else frames[0]

  def close(self):
    self._vec.close()

  @property
  def vector_env(self) -> PixelVectorEnv:
    return self._vec


class DmEnv(dm_env.Environment):
  """One DMCR task with pixel observations as a `dm_env.Environment`.

  Args:
    task: a task name, e.g. "walker-walk".
    visual_seed: an int, or a `SeedRange` to draw every episode's look from.
    **make_kwargs: the other arguments of `dmcr_jax.make`.
  """

  def __init__(self, task: str, visual_seed: Any = 0, **make_kwargs):
    self._vec = PixelVectorEnv(task, num_envs=1, visual_seeds=visual_seed, **make_kwargs)
    self._needs_reset = True

  def reset(self) -> dm_env.TimeStep:
    obs, _ = self._vec.reset()
    self._needs_reset = False
    return dm_env.restart({"pixels": obs[0]})

  def step(self, action) -> dm_env.TimeStep:
    if self._needs_reset:
      return self.reset()
    obs, reward, _, truncated, _ = self._vec.step(np.asarray(action)[None])
    observation = {"pixels": obs[0]}
    if truncated[0]:
      self._needs_reset = True
      return dm_env.truncation(float(reward[0]), observation)
    return dm_env.transition(float(reward[0]), observation)

  def observation_spec(self):
    space = self._vec.single_observation_space
    return {"pixels": specs.BoundedArray(space.shape, np.uint8, 0, 255, name="pixels")}

  def action_spec(self):
    space = self._vec.single_action_space
    return specs.BoundedArray(space.shape, np.float32, space.low, space.high, name="action")

  def close(self):
    self._vec.close()


def register_envs() -> None:
  """Registers `dmcr/<task>-v0` (`ENV_ID`) for every task with gymnasium
  (idempotent; `import dmcr_jax` does it)."""
  import dmcr_jax
  dmcr_jax._register_envs()
