"""dm_control reference data for the parity tests.

Runs dm_control's own suite tasks with random actions and records, after each
control step, the physics state (qpos, qvel, act, ctrl, sensordata, warm start),
the task variables (via `Task.info_from_physics`), dm_control's flattened
observation and its reward.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from dm_control import suite

from dmcr_jax import models


@dataclasses.dataclass
class Records:
  qpos: np.ndarray
  qvel: np.ndarray
  act: np.ndarray
  ctrl: np.ndarray
  sensordata: np.ndarray
  qacc_warmstart: np.ndarray
  info: dict
  obs: np.ndarray
  reward: np.ndarray

  def take(self, index) -> "Records":
    """The records at `index` (a slice or index array) of the leading axis."""
    return Records(**{f.name: ({k: v[index] for k, v in getattr(self, f.name).items()}
                               if f.name == "info" else getattr(self, f.name)[index])
                      for f in dataclasses.fields(self)})


def load_env(name: str, seed: int):
  domain, task = models.split_name(name)
  return suite.load(domain, task, task_kwargs={"random": seed})


def flat_obs(obs) -> np.ndarray:
  return np.concatenate([np.ravel(np.asarray(v, np.float64)) for v in obs.values()])


def snapshot(physics, task) -> dict:
  d = physics.data
  return dict(qpos=d.qpos.copy(), qvel=d.qvel.copy(), act=d.act.copy(),
              ctrl=d.ctrl.copy(), sensordata=d.sensordata.copy(),
              qacc_warmstart=d.qacc_warmstart.copy(),
              info={k: np.asarray(v) for k, v in task.info_from_physics(physics).items()})


def stack(snaps: list[dict], obs: list, rewards: list) -> Records:
  fields = {k: np.stack([s[k] for s in snaps]) for k in
            ("qpos", "qvel", "act", "ctrl", "sensordata", "qacc_warmstart")}
  info = {k: np.stack([s["info"][k] for s in snaps]) for k in snaps[0]["info"]}
  return Records(**fields, info=info, obs=np.stack(obs), reward=np.asarray(rewards))


def random_rollout_states(name: str, n_states: int = 200, episodes: int = 2,
                          seed: int = 0) -> Records:
  """`n_states` states spread evenly over `episodes` random-action episodes."""
  task = models.load(name)
  env = load_env(name, seed)
  spec = env.action_spec()
  rng = np.random.RandomState(seed)
  per_episode = n_states // episodes
  stride = max(1, task.time_limit // per_episode)
  snaps, obs, rewards = [], [], []
  for _ in range(episodes):
    env.reset()
    for t in range(per_episode * stride):
      ts = env.step(rng.uniform(spec.minimum, spec.maximum))
      if t % stride == stride - 1:
        snaps.append(snapshot(env.physics, task))
        obs.append(flat_obs(ts.observation))
        rewards.append(ts.reward)
  return stack(snaps, obs, rewards)


def trajectories(name: str, actions: np.ndarray, seeds) -> tuple[Records, list[Records]]:
  """Initial states for `seeds` and dm_control's states after each action.

  Args:
    actions: (T, B, A) actions; B must equal len(seeds).
  Returns:
    (initial Records over B, [Records over B after step t for t < T]).
  """
  task = models.load(name)
  envs = [load_env(name, s) for s in seeds]
  init = []
  for env in envs:
    env.reset()
    init.append(snapshot(env.physics, task))
  init = stack(init, [np.zeros(task.observation_size)] * len(envs), [0.0] * len(envs))
  steps = []
  for a in actions:
    snaps, obs, rewards = [], [], []
    for env, ab in zip(envs, a):
      ts = env.step(ab)
      snaps.append(snapshot(env.physics, task))
      obs.append(flat_obs(ts.observation))
      rewards.append(ts.reward)
    steps.append(stack(snaps, obs, rewards))
  return init, steps
