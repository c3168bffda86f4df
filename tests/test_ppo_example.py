"""`examples/ppo_pixels.py`: GAE against a NumPy reference, a PPO update lowers the clipped
loss on its batch, the rollout's NEXT_STEP bookkeeping and learning on a toy env with the
jax_env contract, the protocol plan of a run, bad configs, and a real `PixelEnv` run of
the CLI (files written after every chunk, finite losses).

The example is imported by path, as a user running the file would load it.
"""

import csv
import dataclasses
import functools
import importlib.util
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _load():
  path = os.path.join(ROOT, "examples", "ppo_pixels.py")
  spec = importlib.util.spec_from_file_location("ppo_pixels_example", path)
  module = importlib.util.module_from_spec(spec)
  sys.modules[spec.name] = module      # dataclasses look their module up
  spec.loader.exec_module(module)
  return module


ppo = _load()
TINY = dict(channels=(4, 4), kernels=(3, 3), hidden=(16,))


def gae_reference(reward, value, done, last_value, gamma, lam):
  """GAE by a plain backward loop: bootstrap from the next value, cut after `done`."""
  t_max, n = reward.shape
  adv = np.zeros((t_max, n))
  for i in range(n):
    a = 0.0
    for t in reversed(range(t_max)):
      nxt = last_value[i] if t == t_max - 1 else value[t + 1, i]
      delta = reward[t, i] + gamma * nxt - value[t, i]
      a = delta + (0.0 if done[t, i] else gamma * lam * a)
      adv[t, i] = a
  return adv, adv + value


def test_gae_matches_numpy():
  rng = np.random.default_rng(0)
  t_max, n = 11, 5
  reward = rng.normal(size=(t_max, n)).astype(np.float32)
  value = rng.normal(size=(t_max, n)).astype(np.float32)
  done = rng.random((t_max, n)) < 0.25
  last = rng.normal(size=n).astype(np.float32)
  adv, target = ppo.gae(jnp.asarray(reward), jnp.asarray(value), jnp.asarray(done),
                        jnp.asarray(last), 0.97, 0.9)
  want_adv, want_target = gae_reference(reward, value, done, last, 0.97, 0.9)
  np.testing.assert_allclose(np.asarray(adv), want_adv, rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(np.asarray(target), want_target, rtol=1e-5, atol=1e-5)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _fixed_batch(cfg, net, params, key, b=64, size=8):
  """Random frames, actions drawn from the policy, random advantages; every eighth row invalid."""
  k_obs, k_act, k_adv = jax.random.split(key, 3)
  obs = jax.random.randint(k_obs, (b, size, size, 9), 0, 256).astype(jnp.uint8)
  mean, log_std, value = net.apply(params, obs)
  action = mean + jnp.exp(log_std) * jax.random.normal(k_act, mean.shape)
  adv = jax.random.normal(k_adv, (b,))
  return ppo.Batch(obs=obs, action=action, log_prob=ppo.log_prob(action, mean, log_std),
                   advantage=adv, target=value + adv, valid=jnp.arange(b) % 8 != 0)


def test_update_lowers_the_clipped_loss_on_its_batch():
  cfg = ppo.Config(epochs=4, minibatches=2, learning_rate=3e-3, anneal_lr=False, **TINY)
  net = ppo.network(cfg, 2)
  params = jax.jit(net.init)(jax.random.key(0), jnp.zeros((1, 8, 8, 9), jnp.uint8))
  batch = _fixed_batch(cfg, net, params, jax.random.key(1))
  tx = ppo.optimizer(cfg)
  loss = jax.jit(ppo.loss, static_argnums=(1, 3))
  before, aux0 = loss(params, net, batch, cfg)
  # At the acting params the ratio is 1: no clipping, KL 0.
  assert float(aux0["approx_kl"]) == pytest.approx(0.0, abs=1e-6)
  assert float(aux0["clip_frac"]) == 0.0
  new, _, info = jax.jit(ppo.update, static_argnums=(4, 5, 6))(
      params, tx.init(params), batch, jax.random.key(2), net, tx, cfg)
  after, aux1 = loss(new, net, batch, cfg)
  assert all(np.isfinite(float(v)) for v in info.values())
  assert float(after) < float(before)
  assert float(aux1["policy_loss"]) < float(aux0["policy_loss"])
  assert jax.tree.map(jnp.shape, new) == jax.tree.map(jnp.shape, params)


# A toy env with jax_env's contract (NEXT_STEP auto-reset, `physics.needs_reset` and
# `physics.episode_return`): reward 1 per step whose action is positive, episodes of
# LENGTH steps, blank frames.
LENGTH = 3


@dataclasses.dataclass(frozen=True)
class ToyTask:
  action_size: int = 1
  action_low: tuple = (-1.0,)
  action_high: tuple = (1.0,)


@struct.dataclass
class ToyPhysics:
  t: jax.Array
  needs_reset: jax.Array
  episode_return: jax.Array


@struct.dataclass
class ToyState:
  physics: ToyPhysics
  obs: jax.Array


@struct.dataclass
class ToyEnv:
  task: ToyTask = struct.field(pytree_node=False, default=ToyTask())
  num_envs: int = struct.field(pytree_node=False, default=4)
  height: int = struct.field(pytree_node=False, default=8)
  width: int = struct.field(pytree_node=False, default=8)
  frame_stack: int = struct.field(pytree_node=False, default=3)

  def reset(self, key):
    n = self.num_envs
    return ToyState(ToyPhysics(jnp.zeros(n, jnp.int32), jnp.zeros(n, bool), jnp.zeros(n)),
                    jnp.zeros((n, self.height, self.width, 3 * self.frame_stack), jnp.uint8))

  def step(self, state, actions):
    p = state.physics
    resetting = p.needs_reset
    reward = jnp.where(resetting, 0.0, (actions[:, 0] > 0).astype(jnp.float32))
    t = jnp.where(resetting, 0, p.t + 1)
    done = ~resetting & (t >= LENGTH)
    ret = jnp.where(resetting, 0.0, p.episode_return + reward)
    return ToyState(ToyPhysics(t, done, ret), state.obs), reward, done


def test_rollout_bookkeeping_and_learning_on_a_toy_env():
  cfg = ppo.Config(num_envs=16, unroll=8, epochs=4, minibatches=2, learning_rate=1e-2,
                   anneal_lr=False, entropy_coef=0.0, reward_scale=1.0, frame_skip=1,
                   **TINY)
  env = ToyEnv(num_envs=16)
  carry = ppo.init(env, jax.random.key(0), cfg)
  carry, m = ppo.run_chunk(env, carry, cfg=cfg, iterations=12)
  m = jax.device_get(m)
  # Each env ends an episode every LENGTH + 1 steps (the last one resets it): in
  # 8 steps, 2 episodes per env.
  np.testing.assert_array_equal(m["episodes"], 2 * env.num_envs)
  assert all(np.isfinite(v).all() for v in m.values())
  returns = m["return_sum"] / m["episodes"]
  assert ((0 <= returns) & (returns <= LENGTH)).all()
  # The policy learns to push (every positive action pays): from about half the
  # steps paying (the first policy's mean is near 0) to nearly all.
  assert returns[0] < 0.67 * LENGTH and returns[-3:].mean() > 0.9 * LENGTH


def test_train_stops_at_the_time_limit_after_a_whole_chunk():
  cfg = ppo.Config(num_envs=4, unroll=8, epochs=1, minibatches=2, chunk_iterations=2,
                   total_steps=4 * 8 * 2 * 3, frame_skip=1, **TINY)
  seen = []
  params, metrics = ppo.train(cfg, env=ToyEnv(), on_chunk=lambda row, p: seen.append(row))
  assert [r["agent_steps"] for r in seen] == [64, 128, 192] == [
      r["agent_steps"] for r in metrics["rows"]]
  assert not metrics["stopped_at_time_limit"] and metrics["agent_steps"] == 192
  _, metrics = ppo.train(cfg, env=ToyEnv(), time_limit=0.0)
  assert metrics["stopped_at_time_limit"] and len(metrics["rows"]) == 1
  assert metrics["agent_steps"] == 64 and metrics["compile_s"] > 0


def test_the_protocol_plan_uses_the_training_observations():
  cfg = ppo.Config(task="cartpole-balance", levels=7, image_size=24, frame_skip=50, **TINY)
  proto = ppo.protocol_plan(cfg, visual_seeds=2, dynamics_seeds=1, train_episodes=2,
                            conditions=("none", "all"))
  assert proto.config["image_size"] == [24, 24]
  assert proto.config["action_repeat"] == 50
  assert proto.config["train_look"] == ["levels:7"]
  net = ppo.network(cfg, 1)
  params = jax.jit(net.init)(jax.random.key(0), jnp.zeros((1, 24, 24, 9), jnp.uint8))
  obs = jnp.full((3, 24, 24, 9), 255, jnp.uint8)
  a = proto.policy(params, obs, jax.random.key(0))
  assert a.shape == (3, 1) and bool((jnp.abs(a) <= 1).all())


@pytest.mark.parametrize("change, match", [
    (dict(task="cartpole-swing"), "unknown task"),
    (dict(unroll=3, num_envs=3, minibatches=2), "divisible by minibatches"),
    (dict(levels=0), "levels must be an int"),
    (dict(vary="colour"), "colour"),
])
def test_bad_configs_are_refused(change, match):
  with pytest.raises(ValueError, match=match):
    ppo.check(ppo.Config(**change))


def test_the_cli_refuses_bad_evaluation_options_before_training(tmp_path):
  out = str(tmp_path / "never")
  with pytest.raises(SystemExit, match="conditions"):
    ppo.main(["--eval-conditions", "none,colour", "--out", out])
  with pytest.raises(SystemExit, match="exclude each other"):
    ppo.main(["--eval-only", "--no-eval", "--out", out])
  assert not os.path.exists(out)


@pytest.mark.slow
def test_cli_trains_on_the_pixel_env_and_writes_after_every_chunk(tmp_path):
  # pendulum-swingup (the fewest bodies to step and ray-cast: the fastest to compile)
  # at 16 px and frame skip 100: episodes of 10 agent steps, each env's ending at
  # vector steps 10 and 21, one in each chunk of 2 × 6 steps.
  out = str(tmp_path / "run")
  summary = ppo.main(["--task", "pendulum-swingup", "--num-envs", "4", "--image-size", "16",
                      "--frame-skip", "100", "--levels", "3", "--unroll", "6",
                      "--minibatches", "2", "--epochs", "2", "--total-steps", "96",
                      "--no-shadows", "--no-reflection", "--no-eval", "--out", out])
  with open(os.path.join(out, "returns.csv")) as f:
    rows = list(csv.DictReader(f))
  assert [int(r["agent_steps"]) for r in rows] == [48, 96]
  for r in rows:
    assert int(r["episodes"]) == 4
    assert 0 <= float(r["return_mean"]) <= 1000
    assert all(np.isfinite(float(r[k])) for k in ("loss", "value_loss", "entropy"))
  with open(os.path.join(out, "metrics.json")) as f:
    saved = json.load(f)
  assert saved["agent_steps"] == 96 and saved["compile_s"] > 0
  assert summary["rows"] == saved["rows"]
  assert os.path.getsize(os.path.join(out, "returns.png")) > 0
  with open(os.path.join(out, "summary.md")) as f:
    table = f.read().splitlines()
  assert len(table) == 4 and "pendulum-swingup" in table[2] and "| 96 |" in table[2]
  cfg = ppo.Config(task="pendulum-swingup", image_size=16, frame_skip=100)
  params = ppo.load_params(cfg, os.path.join(out, "params.msgpack"))
  template = jax.eval_shape(ppo.network(cfg, 1).init, jax.random.key(0),
                            jnp.zeros((1, 16, 16, 9), jnp.uint8))
  assert jax.tree.map(np.shape, params) == jax.tree.map(np.shape, template)
  assert all(np.isfinite(x).all() for x in jax.tree.leaves(params))
