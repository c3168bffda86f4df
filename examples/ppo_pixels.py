"""PPO from pixels, one jitted call per chunk of updates, on the pure pixel env (jax_env).

A single-file learner of your own, written in the manner of purejaxrl: the envs
(`jax_env.PixelEnv`: MJX physics, the JAX ray caster, frame stacks), the
rollouts and the updates are pure functions, and a chunk of PPO iterations is
one `lax.scan` in one XLA program. An iteration collects `unroll` agent steps of
all `num_envs` envs (a `lax.scan` over env steps, the policy inside), computes
GAE advantages, then runs `epochs` × `minibatches` clipped-objective updates (a
`lax.scan` over epochs of a `lax.scan` over shuffled minibatches). Every env
draws its own look from `levels(N)` at each reset (the paper's few-shot
training range), made on the device from its visual seed. Observations stay
uint8 (N, H, W, 3·frame_stack) and are divided by 255 inside the network.

Auto-reset is gymnasium's NEXT_STEP (`jax_env`): the step that ends an episode
(`truncated`, the time limit; DMC tasks never terminate) returns its last frame
and reward, and the env's next step ignores its action and returns the new
episode's first frame with reward 0. So the value of a truncated episode's last
frame is the next stored value (a time limit is bootstrapped, not treated as a
terminal), the advantage recursion stops at `truncated`, and the steps whose
action was ignored are masked out of every loss.

After training, the greedy policy (the Gaussian's mean, clipped to [−1, 1]) is
evaluated with the paper's zero-shot protocol (`dmcr_jax.protocol.evaluate`;
a reduced one by default, flags choose). The CLI writes, in `--out`, after every
chunk: `returns.csv` (one row per chunk: agent steps, wall seconds, the mean
return of the episodes that ended in it, losses), `returns.png`, `metrics.json`
and `params.msgpack` (flax serialization), so a run stopped at any point leaves
its results; at the end `eval.json`, `eval.md` and `eval.png` of the protocol.

    python examples/ppo_pixels.py --task cartpole-balance --num-envs 2048 --out runs/ppo_cartpole
    python examples/ppo_pixels.py --task cartpole-balance --num-envs 16 --image-size 32 \\
        --unroll 16 --minibatches 4 --epochs 4 --total-steps 20000 --out /tmp/ppo_cpu

See docs/own_learner.md.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
import os
import time
from typing import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization, struct

import dmcr_jax
from dmcr_jax import jax_env, protocol
from dmcr_jax.env import default_frame_skip
from dmcr_jax.visuals.factors import check_vary

LOG_2PI_E = float(np.log(2 * np.pi * np.e))

ANCHOR = dict(
    source="MuJoCo Playground, learning/notebooks/vision.ipynb and "
           "config/dm_control_suite_params.py (brax_vision_ppo_config)",
    task="CartpoleBalance (vision): 64×64 pixels, grey, 3 frames, no textures or shadows, "
         "250-step episodes at ctrl_dt 0.02 s, Playground's additive vision reward",
    env_steps=5_000_000, num_envs=1024, device="RTX 4090", train_minutes=7)
"""The anchor this example is compared with (its published settings and wall time)."""


@dataclasses.dataclass(frozen=True)
class Config:
  """A PPO run (static: hashable, so it is a static argument of the jitted chunk).

  The learning defaults are MuJoCo Playground's vision PPO for CartpoleBalance
  (`brax_vision_ppo_config`: 40,960 transitions per iteration in 8 minibatches,
  8 epochs, Adam at 1e-3, gradients clipped at norm 1, clip ε 0.3, γ 0.99, its
  CNN of 16 and 32 channels with max pooling and MLPs of 128 and 64), here with
  2,048 envs × 20 steps in one rollout.

  Attributes:
    task: one of `dmcr_jax.ALL_TASKS`.
    num_envs: N envs stepped as one batch.
    levels: each env draws its look from `dmcr_jax.levels(levels)` at every
      reset (1: dm_control's look only).
    vary: the factors the visual seeds change ("all" or a comma list).
    image_size: H = W of the frames, pixels.
    frame_stack: frames per observation.
    frame_skip: control steps per agent step (None: the paper's action repeat).
    total_steps: agent steps (vector steps × N) to train for; rounded up to
      whole chunks.
    unroll: agent steps per env per iteration (the rollout's length T).
    epochs, minibatches: passes over an iteration's T·N transitions, and the
      minibatches each pass is shuffled into (T·N must divide evenly).
    learning_rate: Adam's step size (annealed linearly to 0 if `anneal_lr`).
    max_grad_norm: global gradient-norm clip.
    gamma, gae_lambda: discount and GAE λ per agent step.
    clip_eps: PPO's ratio clip ε.
    entropy_coef, value_coef: weights of the entropy bonus and the value loss.
    reward_scale: the losses see each agent step's reward divided by the frame
      skip and multiplied by this (a DMC control step pays at most 1, so at most
      0.1 per step by default and values at most 10 at γ 0.99, the scale of
      Playground's vision reward); returns are reported unscaled.
    channels, kernels: the encoder's conv layers (stride 2, ELU, 2×2 max pool each).
    hidden: the policy and value MLPs' widths (on one shared encoder).
    init_log_std: the Gaussian policy's initial log standard deviation.
    chunk_iterations: iterations per jitted call (None: enough that every env
      ends an episode in each chunk).
    shadows, reflection: the ray caster's options.
    seed: the run's PRNG seed.
  """
  task: str = "cartpole-balance"
  num_envs: int = 2048
  levels: int = 10
  vary: str = "all"
  image_size: int = 84
  frame_stack: int = 3
  frame_skip: int | None = None
  total_steps: int = 5_000_000
  unroll: int = 20
  epochs: int = 8
  minibatches: int = 8
  learning_rate: float = 1e-3
  anneal_lr: bool = True
  max_grad_norm: float = 1.0
  gamma: float = 0.99
  gae_lambda: float = 0.95
  clip_eps: float = 0.3
  entropy_coef: float = 0.01
  value_coef: float = 0.5
  reward_scale: float = 0.1
  channels: tuple[int, ...] = (16, 32)
  kernels: tuple[int, ...] = (5, 3)
  hidden: tuple[int, ...] = (128, 64)
  init_log_std: float = -0.5
  chunk_iterations: int | None = None
  shadows: bool = True
  reflection: bool = True
  seed: int = 0

  @property
  def skip(self) -> int:
    """Control steps per agent step."""
    return default_frame_skip(self.task) if self.frame_skip is None else self.frame_skip

  @property
  def episode_steps(self) -> int:
    """Agent steps per episode (the time limit over the frame skip, rounded up)."""
    return -(-_time_limit(self.task) // self.skip)

  @property
  def iteration_steps(self) -> int:
    """Agent steps per iteration, T·N."""
    return self.unroll * self.num_envs

  @property
  def chunk(self) -> int:
    """Iterations per jitted call."""
    if self.chunk_iterations is not None:
      return self.chunk_iterations
    return -(-(self.episode_steps + 1) // self.unroll)

  @property
  def num_chunks(self) -> int:
    """Chunks to reach `total_steps`."""
    return max(1, -(-self.total_steps // (self.iteration_steps * self.chunk)))

  @property
  def num_updates(self) -> int:
    """Gradient steps of the whole run (the learning-rate schedule's length)."""
    return self.num_chunks * self.chunk * self.epochs * self.minibatches


@functools.cache
def _time_limit(task: str) -> int:
  """Control steps per episode of `task`."""
  return dmcr_jax.load(task).time_limit


def check(cfg: Config) -> Config:
  """`cfg`, or a ValueError naming the bad field and its valid values (before anything builds)."""
  if cfg.task not in dmcr_jax.ALL_TASKS:
    raise ValueError(f"unknown task {cfg.task!r}; valid: {', '.join(dmcr_jax.ALL_TASKS)}")
  for name in ("num_envs", "levels", "image_size", "frame_stack", "total_steps", "unroll",
               "epochs", "minibatches"):
    v = getattr(cfg, name)
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
      raise ValueError(f"{name} must be an int ≥ 1, got {v!r}")
  for name in ("frame_skip", "chunk_iterations"):
    v = getattr(cfg, name)
    if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
      raise ValueError(f"{name} must be None or an int ≥ 1, got {v!r}")
  check_vary(cfg.task.split("-", 1)[0], cfg.vary)
  if cfg.iteration_steps % cfg.minibatches:
    raise ValueError(f"unroll × num_envs ({cfg.iteration_steps}) must be divisible by "
                     f"minibatches ({cfg.minibatches})")
  if len(cfg.channels) != len(cfg.kernels) or not cfg.channels:
    raise ValueError(f"channels {cfg.channels} and kernels {cfg.kernels} must be "
                     "non-empty tuples of one length")
  if not 0 < cfg.gamma <= 1 or not 0 <= cfg.gae_lambda <= 1:
    raise ValueError(f"gamma must be in (0, 1] and gae_lambda in [0, 1], got "
                     f"{cfg.gamma}, {cfg.gae_lambda}")
  return cfg


# ----------------------------------------------------------------------------- network


class ActorCritic(nn.Module):
  """uint8 frame stacks (B, H, W, C) → (action mean (B, A), log std (B, A), value (B,)).

  A conv encoder (per layer: a stride-2 convolution, ELU, a 2×2 max pool; input
  divided by 255) shared by two MLP heads (ELU), orthogonal initialisation, and a
  state-independent log standard deviation.
  """
  action_size: int
  channels: tuple[int, ...] = (16, 32)
  kernels: tuple[int, ...] = (5, 3)
  hidden: tuple[int, ...] = (128, 64)
  init_log_std: float = -0.5

  @nn.compact
  def __call__(self, obs: jax.Array):
    ortho = nn.initializers.orthogonal
    x = obs.astype(jnp.float32) / 255.0
    for c, k in zip(self.channels, self.kernels):
      x = nn.Conv(c, (k, k), strides=2, kernel_init=ortho(np.sqrt(2)))(x)
      x = nn.max_pool(nn.elu(x), (2, 2), strides=(2, 2), padding="SAME")
    x = x.reshape(x.shape[0], -1)

    def head(out: int, scale: float, name: str) -> jax.Array:
      h = x
      for i, width in enumerate(self.hidden):
        h = nn.elu(nn.Dense(width, kernel_init=ortho(np.sqrt(2)), name=f"{name}_{i}")(h))
      return nn.Dense(out, kernel_init=ortho(scale), name=f"{name}_out")(h)

    mean = head(self.action_size, 0.01, "policy")
    value = head(1, 1.0, "value")[:, 0]
    log_std = self.param("log_std", nn.initializers.constant(self.init_log_std),
                         (self.action_size,))
    return mean, jnp.broadcast_to(log_std, mean.shape), value


def network(cfg: Config, action_size: int) -> ActorCritic:
  """The `ActorCritic` of `cfg` for `action_size` actions."""
  return ActorCritic(action_size, tuple(cfg.channels), tuple(cfg.kernels), tuple(cfg.hidden),
                     cfg.init_log_std)


def log_prob(action: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
  """Log density (B,) of a diagonal Gaussian at `action` (B, A)."""
  z = (action - mean) * jnp.exp(-log_std)
  return jnp.sum(-0.5 * z * z - log_std - 0.5 * np.log(2 * np.pi), axis=-1)


def entropy(log_std: jax.Array) -> jax.Array:
  """Entropy (B,) of a diagonal Gaussian with log standard deviations (B, A)."""
  return jnp.sum(log_std + 0.5 * LOG_2PI_E, axis=-1)


def optimizer(cfg: Config) -> optax.GradientTransformation:
  """Adam after a global-norm clip; the step size annealed linearly over the run."""
  lr = (optax.linear_schedule(cfg.learning_rate, 0.0, cfg.num_updates)
        if cfg.anneal_lr else cfg.learning_rate)
  return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(lr, eps=1e-5))


# ----------------------------------------------------------------------------- PPO pieces


@struct.dataclass
class Batch:
  """Transitions, any leading shape (T, N) or (B,).

  Attributes:
    obs: uint8 frame stacks the actions were taken on.
    action: float32 (…, A) Gaussian samples (before the clip to [−1, 1]).
    log_prob: float32 their log densities under the acting policy.
    advantage: float32 GAE advantages.
    target: float32 value targets (advantage + value).
    valid: bool, the env used the action (False on the step that resets an env).
  """
  obs: jax.Array
  action: jax.Array
  log_prob: jax.Array
  advantage: jax.Array
  target: jax.Array
  valid: jax.Array


def gae(reward: jax.Array, value: jax.Array, done: jax.Array, last_value: jax.Array,
        gamma: float, lam: float) -> tuple[jax.Array, jax.Array]:
  """Generalised advantage estimates (Schulman et al. 2016, eq. 16) of a rollout.

  With NEXT_STEP auto-reset and no terminal states, step t's next value is always
  `value[t + 1]` (or `last_value`): after a truncated step that is the value of
  the episode's last frame. The recursion A_t = δ_t + γλ(1 − done_t) A_{t+1}
  stops at `done` so that the next (reset) step's advantage never leaks back.

  Args:
    reward: float (T, N) rewards.
    value: float (T, N) values of the observations acted on.
    done: bool (T, N), step t ended an episode (its next frame is the last).
    last_value: float (N,) value of the observation after the rollout.
    gamma, lam: discount and λ.

  Returns:
    (advantages, value targets), each float32 (T, N).
  """
  next_value = jnp.concatenate([value[1:], last_value[None]], axis=0)
  delta = reward + gamma * next_value - value
  cont = gamma * lam * (1.0 - done.astype(jnp.float32))

  def back(a, x):
    d, c = x
    a = d + c * a
    return a, a

  _, adv = jax.lax.scan(back, jnp.zeros_like(last_value), (delta, cont), reverse=True)
  return adv, adv + value


def loss(params, net: ActorCritic, batch: Batch, cfg: Config) -> tuple[jax.Array, dict]:
  """PPO's loss on a minibatch (Schulman et al. 2017, eq. 7 and 9), over its valid rows.

  Clipped surrogate on per-minibatch normalised advantages, plus `value_coef` ×
  half the squared value error, minus `entropy_coef` × the entropy.

  Returns:
    (total loss, dict of policy_loss, value_loss, entropy, approx_kl, clip_frac).
  """
  mean, log_std, value = net.apply(params, batch.obs)
  w = batch.valid.astype(jnp.float32)
  n = jnp.maximum(w.sum(), 1.0)
  avg = lambda x: jnp.sum(w * x) / n
  adv = batch.advantage
  mu = avg(adv)
  adv = (adv - mu) / (jnp.sqrt(avg((adv - mu) ** 2)) + 1e-8)
  log_ratio = log_prob(batch.action, mean, log_std) - batch.log_prob
  ratio = jnp.exp(log_ratio)
  surrogate = jnp.minimum(ratio * adv,
                          jnp.clip(ratio, 1.0 - cfg.clip_eps, 1.0 + cfg.clip_eps) * adv)
  policy_loss = -avg(surrogate)
  value_loss = 0.5 * avg((value - batch.target) ** 2)
  ent = avg(entropy(log_std))
  total = policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * ent
  return total, dict(policy_loss=policy_loss, value_loss=value_loss, entropy=ent,
                     approx_kl=avg(ratio - 1.0 - log_ratio),
                     clip_frac=avg((jnp.abs(ratio - 1.0) > cfg.clip_eps).astype(jnp.float32)))


def update(params, opt_state, batch: Batch, key: jax.Array, net: ActorCritic,
           tx: optax.GradientTransformation, cfg: Config):
  """`cfg.epochs` passes of `cfg.minibatches` shuffled minibatch steps over a flat batch.

  Args:
    params, opt_state: the network's params and the optimizer's state.
    batch: a `Batch` with leading shape (B,).
    key: shuffles the minibatches of every epoch.
    net, tx, cfg: the network, optimizer and config.

  Returns:
    (params, opt_state, mean of `loss`'s dict over every step, plus "loss").
  """
  b = batch.valid.shape[0]

  def step(carry, mb):
    p, s = carry
    (total, aux), grads = jax.value_and_grad(loss, has_aux=True)(p, net, mb, cfg)
    updates, s = tx.update(grads, s, p)
    return (optax.apply_updates(p, updates), s), dict(aux, loss=total)

  def epoch(carry, k):
    perm = jax.random.permutation(k, b)
    mbs = jax.tree.map(lambda x: x[perm].reshape((cfg.minibatches, -1) + x.shape[1:]), batch)
    return jax.lax.scan(step, carry, mbs)

  (params, opt_state), info = jax.lax.scan(epoch, (params, opt_state),
                                           jax.random.split(key, cfg.epochs))
  return params, opt_state, jax.tree.map(jnp.mean, info)


# ----------------------------------------------------------------------------- the run


@struct.dataclass
class Carry:
  """What one chunk hands the next (donated between chunks).

  Attributes:
    params: the `ActorCritic` params.
    opt_state: the optimizer's state.
    env: the `jax_env.PixelState` of the N envs.
    key: the run's PRNG key.
  """
  params: dict
  opt_state: optax.OptState
  env: jax_env.PixelState
  key: jax.Array


def init(env: jax_env.PixelEnv, key: jax.Array, cfg: Config) -> Carry:
  """The first `Carry`: fresh params and optimizer state, every env reset."""
  k_net, k_env, key = jax.random.split(key, 3)
  net = network(cfg, env.task.action_size)
  obs = jnp.zeros((1, env.height, env.width, 3 * env.frame_stack), jnp.uint8)
  params = net.init(k_net, obs)
  return Carry(params=params, opt_state=optimizer(cfg).init(params), env=env.reset(k_env),
               key=key)


def iteration(env: jax_env.PixelEnv, carry: Carry, cfg: Config):
  """One PPO iteration: a rollout of `cfg.unroll` steps of all envs, GAE, the updates.

  Returns:
    (next `Carry`, metrics: float32 scalars `return_sum` and `episodes` of the
    episodes that ended in the rollout (unscaled returns), and `update`'s means).
  """
  net, tx = network(cfg, env.task.action_size), optimizer(cfg)
  low, high = env.task.action_low, env.task.action_high

  def env_step(c, _):
    state, key = c
    key, k = jax.random.split(key)
    mean, log_std, value = net.apply(carry.params, state.obs)
    action = mean + jnp.exp(log_std) * jax.random.normal(k, mean.shape)
    valid = ~state.physics.needs_reset
    nxt, reward, done = env.step(state, protocol.env_actions(jnp.clip(action, -1, 1), low, high))
    ended = jnp.where(done, nxt.physics.episode_return, 0.0)
    out = dict(obs=state.obs, action=action, log_prob=log_prob(action, mean, log_std),
               value=value, reward=reward * (cfg.reward_scale / cfg.skip), done=done,
               valid=valid, ended=ended)
    return (nxt, key), out

  key, k_roll, k_upd = jax.random.split(carry.key, 3)
  (state, _), r = jax.lax.scan(env_step, (carry.env, k_roll), None, length=cfg.unroll)
  _, _, last_value = net.apply(carry.params, state.obs)
  adv, target = gae(r["reward"], r["value"], r["done"], last_value, cfg.gamma, cfg.gae_lambda)
  flat = lambda x: x.reshape((-1,) + x.shape[2:])
  batch = Batch(obs=flat(r["obs"]), action=flat(r["action"]), log_prob=flat(r["log_prob"]),
                advantage=flat(adv), target=flat(target), valid=flat(r["valid"]))
  params, opt_state, info = update(carry.params, carry.opt_state, batch, k_upd, net, tx, cfg)
  info.update(return_sum=r["ended"].sum(), episodes=r["done"].sum().astype(jnp.float32))
  return Carry(params=params, opt_state=opt_state, env=state, key=key), info


@functools.partial(jax.jit, static_argnames=("cfg", "iterations"), donate_argnums=(1,))
def run_chunk(env: jax_env.PixelEnv, carry: Carry, *, cfg: Config, iterations: int):
  """`iterations` PPO iterations as one XLA program (`lax.scan` of `iteration`).

  Args:
    env: the `PixelEnv` (an argument, not a closure: its texture bank is large).
    carry: the `Carry` (donated).
    cfg: the static `Config`.
    iterations: iterations in the chunk (static).

  Returns:
    (next `Carry`, metrics of every iteration, leading axis `iterations`).
  """
  return jax.lax.scan(lambda c, _: iteration(env, c, cfg), carry, None, length=iterations)


def make_env(cfg: Config) -> jax_env.PixelEnv:
  """The training `PixelEnv` of `cfg`: N envs drawing their looks from `levels(cfg.levels)`."""
  return jax_env.make_env(dmcr_jax.load(cfg.task), cfg.num_envs, dmcr_jax.levels(cfg.levels),
                          cfg.vary, cfg.skip, cfg.frame_stack, cfg.image_size, cfg.image_size,
                          shadows=cfg.shadows, reflection=cfg.reflection)


def chunk_row(m: dict, chunk: int, cfg: Config, wall_s: float, chunk_s: float) -> dict:
  """One chunk's metrics (host NumPy, leading axis iterations) as a flat row."""
  episodes = float(np.sum(m["episodes"]))
  steps = (chunk + 1) * cfg.chunk * cfg.iteration_steps
  row = dict(chunk=chunk, agent_steps=steps, control_steps=steps * cfg.skip,
             wall_s=round(wall_s, 3), steps_per_s=round(cfg.chunk * cfg.iteration_steps
                                                        / chunk_s, 1),
             episodes=int(episodes),
             return_mean=float(np.sum(m["return_sum"]) / episodes) if episodes else float("nan"))
  for k in ("loss", "policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac"):
    row[k] = float(np.mean(m[k]))
  return row


def train(cfg: Config, *, env: jax_env.PixelEnv | None = None,
          time_limit: float | None = None,
          on_chunk: Callable[[dict, dict], None] | None = None) -> tuple[dict, dict]:
  """Trains a PPO agent: one compiled `run_chunk` called `cfg.num_chunks` times.

  Args:
    cfg: the `Config` (checked first).
    env: the envs to train on (default `make_env(cfg)`); any `PixelEnv` of
      `cfg.num_envs` envs, e.g. one with a range of looks per env (`EnvRanges`).
    time_limit: stop after the chunk past which the next one would end beyond
      this many seconds since the call (env building and compiling included);
      None: run every chunk.
    on_chunk: called after every chunk with (row, params) (e.g. to write files).

  Returns:
    (params, metrics): metrics hold `rows` (one `chunk_row` per chunk), the
    agent steps trained, `build_s`, `compile_s`, `train_s` (chunks only),
    `wall_s`, `device` and whether the time limit stopped it.
  """
  check(cfg)
  t0 = time.perf_counter()
  env = make_env(cfg) if env is None else env
  if env.num_envs != cfg.num_envs:
    raise ValueError(f"env has {env.num_envs} envs, cfg.num_envs is {cfg.num_envs}")
  carry = jax.jit(init, static_argnames="cfg")(env, jax.random.key(cfg.seed), cfg=cfg)
  jax.block_until_ready(carry)
  build_s = time.perf_counter() - t0
  compiled = run_chunk.lower(env, carry, cfg=cfg, iterations=cfg.chunk).compile()
  compile_s = time.perf_counter() - t0 - build_s
  rows, stopped, train_s = [], False, 0.0
  for c in range(cfg.num_chunks):
    tc = time.perf_counter()
    carry, m = compiled(env, carry)
    m = jax.device_get(m)
    chunk_s = time.perf_counter() - tc
    train_s += chunk_s
    rows.append(chunk_row(m, c, cfg, time.perf_counter() - t0, chunk_s))
    if on_chunk is not None:
      on_chunk(rows[-1], carry.params)
    if (time_limit is not None and c + 1 < cfg.num_chunks
        and time.perf_counter() - t0 + chunk_s > time_limit):
      stopped = True
      break
  steps = len(rows) * cfg.chunk * cfg.iteration_steps
  return carry.params, dict(rows=rows, agent_steps=steps, control_steps=steps * cfg.skip,
                            build_s=build_s, compile_s=compile_s, train_s=train_s,
                            wall_s=time.perf_counter() - t0, device=jax.devices()[0].device_kind,
                            stopped_at_time_limit=stopped)


@functools.lru_cache(maxsize=8)
def greedy_policy(action_size: int, channels: tuple, kernels: tuple, hidden: tuple
                  ) -> Callable:
  """The protocol policy ``policy(params, obs, key) -> actions`` of an `ActorCritic`:
  its Gaussian's mean clipped to [−1, 1] (one function object per network shape, so
  the protocol compiles it once)."""
  net = ActorCritic(action_size, channels, kernels, hidden)

  def policy(params, obs, key):
    del key
    return jnp.clip(net.apply(params, obs)[0], -1.0, 1.0)
  return policy


def load_params(cfg: Config, path: str) -> dict:
  """The params of `cfg`'s network saved at `path` (`flax.serialization.to_bytes`)."""
  net = network(cfg, dmcr_jax.load(cfg.task).action_size)
  obs = jnp.zeros((1, cfg.image_size, cfg.image_size, 3 * cfg.frame_stack), jnp.uint8)
  template = jax.eval_shape(net.init, jax.random.key(0), obs)
  with open(path, "rb") as f:
    return serialization.from_bytes(jax.tree.map(lambda x: np.zeros(x.shape, x.dtype),
                                                 template), f.read())


def protocol_plan(cfg: Config, **options) -> protocol.Protocol:
  """The zero-shot protocol (`dmcr_jax.protocol.prepare`) of the run's greedy policy.

  The observations (size, stack, action repeat) and the render options are the
  training env's; the training look is the range trained on (`levels(cfg.levels)`).
  Call the result with the trained params for its `protocol.Results`.

  Args:
    cfg: the run's `Config`.
    **options: `protocol.prepare` options (visual_seeds, dynamics_seeds,
      train_episodes, conditions, max_envs, seed).

  Returns:
    The `protocol.Protocol` (planned on the host; nothing compiled).
  """
  a = dmcr_jax.load(cfg.task).action_size
  policy = greedy_policy(a, tuple(cfg.channels), tuple(cfg.kernels), tuple(cfg.hidden))
  return protocol.prepare(cfg.task, policy, train_look=dmcr_jax.levels(cfg.levels),
                          train_vary=cfg.vary, image_size=cfg.image_size,
                          frame_stack=cfg.frame_stack, action_repeat=cfg.skip,
                          shadows=cfg.shadows, reflection=cfg.reflection, **options)


# ----------------------------------------------------------------------------- CLI


def plot(rows: list[dict], path: str, title: str) -> None:
  """Return against agent steps (PNG)."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, ax = plt.subplots(figsize=(5, 3.2))
  ax.plot([r["agent_steps"] for r in rows], [r["return_mean"] for r in rows], marker=".")
  ax.set_xlabel("agent steps")
  ax.set_ylabel("episode return")
  ax.set_title(title, fontsize=9)
  ax.grid(alpha=0.3)
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def markdown(summary: dict) -> str:
  """The run beside the anchor (`ANCHOR`), a markdown table (`summary.md`)."""
  c, rows = summary["config"], summary.get("rows") or [{}]
  ev = summary.get("eval", {})
  fmt = lambda x: "–" if x is None or x != x else f"{x:,.1f}"
  steps_to = lambda target: next((r["agent_steps"] for r in rows
                                  if r.get("return_mean", 0) >= target), None)
  a = summary["anchor"]
  lines = [
      "| run | device | pixels | envs | looks | agent steps | compile s | train s | wall s "
      "| last return | agent steps to return ≥ 900 | protocol train / none / all |",
      "|---|---|---|---:|---|---:|---:|---:|---:|---:|---:|---|",
      f"| PPO (examples/ppo_pixels.py), {c['task']} | {summary.get('device', '?')} "
      f"| {c['image_size']}×{c['image_size']} RGB, shadows {'on' if c['shadows'] else 'off'} "
      f"| {c['num_envs']:,} | levels:{c['levels']} | {summary.get('agent_steps', 0):,} "
      f"| {fmt(summary.get('compile_s'))} | {fmt(summary.get('train_s'))} "
      f"| {fmt(summary.get('wall_s'))} | {fmt(rows[-1].get('return_mean'))} "
      f"| {'–' if steps_to(900) is None else f'{steps_to(900):,}'} | "
      + " / ".join(fmt(x) for x in (ev.get("train"),
                                    ev.get("conditions", {}).get("none", {}).get("mean"),
                                    ev.get("conditions", {}).get("all", {}).get("mean")))
      + " |",
      f"| anchor: MuJoCo Playground vision PPO, CartpoleBalance | {a['device']} "
      f"| 64×64 grey, no textures or shadows | {a['num_envs']:,} | one | "
      f"{a['env_steps']:,} env steps | – | about {a['train_minutes']} min | – | – | – | – |"]
  return "\n".join(lines) + "\n"


def parse(argv=None) -> tuple[Config, argparse.Namespace]:
  """The CLI's `Config` and its other options."""
  d = Config()
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--task", default=d.task)
  p.add_argument("--num-envs", type=int, default=d.num_envs)
  p.add_argument("--levels", type=int, default=d.levels,
                 help="each env draws its look from levels(N) at every reset")
  p.add_argument("--vary", default=d.vary)
  p.add_argument("--image-size", type=int, default=d.image_size)
  p.add_argument("--frame-stack", type=int, default=d.frame_stack)
  p.add_argument("--frame-skip", type=int, default=None, help="default: the paper's")
  p.add_argument("--total-steps", type=int, default=d.total_steps, help="agent steps")
  p.add_argument("--unroll", type=int, default=d.unroll)
  p.add_argument("--epochs", type=int, default=d.epochs)
  p.add_argument("--minibatches", type=int, default=d.minibatches)
  p.add_argument("--lr", type=float, default=d.learning_rate)
  p.add_argument("--entropy-coef", type=float, default=d.entropy_coef)
  p.add_argument("--clip-eps", type=float, default=d.clip_eps)
  p.add_argument("--gamma", type=float, default=d.gamma)
  p.add_argument("--reward-scale", type=float, default=d.reward_scale,
                 help="the losses' reward per agent step: reward / frame skip × this")
  p.add_argument("--chunk-iterations", type=int, default=None,
                 help="iterations per jitted call (default: one episode's worth)")
  p.add_argument("--no-shadows", action="store_true")
  p.add_argument("--no-reflection", action="store_true")
  p.add_argument("--seed", type=int, default=d.seed)
  p.add_argument("--time-limit", type=float, default=None,
                 help="seconds; stop training cleanly before a chunk would pass it")
  p.add_argument("--out", default="runs/ppo_pixels")
  p.add_argument("--eval-visual-seeds", type=int, default=20)
  p.add_argument("--eval-dynamics-seeds", type=int, default=1)
  p.add_argument("--eval-train-episodes", type=int, default=20)
  p.add_argument("--eval-conditions", default="none,all",
                 help="comma list, or 'every' (all that apply to the task)")
  p.add_argument("--eval-max-envs", type=int, default=None)
  p.add_argument("--no-eval", action="store_true")
  p.add_argument("--eval-only", action="store_true",
                 help="evaluate --out's params.msgpack (same network and observation flags)")
  a = p.parse_args(argv)
  cfg = Config(task=a.task, num_envs=a.num_envs, levels=a.levels, vary=a.vary,
               image_size=a.image_size, frame_stack=a.frame_stack, frame_skip=a.frame_skip,
               total_steps=a.total_steps, unroll=a.unroll, epochs=a.epochs,
               minibatches=a.minibatches, learning_rate=a.lr, entropy_coef=a.entropy_coef,
               clip_eps=a.clip_eps, gamma=a.gamma, reward_scale=a.reward_scale,
               chunk_iterations=a.chunk_iterations, shadows=not a.no_shadows,
               reflection=not a.no_reflection, seed=a.seed)
  return check(cfg), a


EVAL_KEYS = ("task", "levels", "vary", "image_size", "frame_stack", "frame_skip", "channels",
             "kernels", "hidden", "shadows", "reflection")
"""The config fields an `--eval-only` run must share with the run it evaluates."""


def main(argv=None) -> dict:
  """Trains, writes the curve and checkpoint after every chunk, then runs the protocol."""
  try:
    cfg, a = parse(argv)
    if a.eval_only and a.no_eval:
      raise ValueError("--eval-only and --no-eval exclude each other")
    conditions = None if a.eval_conditions == "every" else tuple(a.eval_conditions.split(","))
    # Planned (and its options checked) before training; compiled after it.
    proto = None if a.no_eval else protocol_plan(
        cfg, visual_seeds=a.eval_visual_seeds, dynamics_seeds=a.eval_dynamics_seeds,
        train_episodes=a.eval_train_episodes, conditions=conditions,
        max_envs=a.eval_max_envs)
  except ValueError as e:
    raise SystemExit(f"ppo_pixels: {e}") from None
  os.makedirs(a.out, exist_ok=True)
  csv_path, rows = os.path.join(a.out, "returns.csv"), []
  title = f"PPO {cfg.task}, {cfg.num_envs} envs, levels:{cfg.levels}, {cfg.image_size} px"
  summary = dict(config=dataclasses.asdict(cfg), anchor=ANCHOR)

  def write_summary(**extra):
    summary.update(extra)
    with open(os.path.join(a.out, "metrics.json"), "w") as f:
      json.dump(summary, f, indent=1, default=float)

  def on_chunk(row, params):
    rows.append(row)
    with open(csv_path, "a" if len(rows) > 1 else "w", newline="") as f:
      w = csv.DictWriter(f, fieldnames=list(row))
      if len(rows) == 1:
        w.writeheader()
      w.writerow(row)
    with open(os.path.join(a.out, "params.msgpack"), "wb") as f:
      f.write(serialization.to_bytes(jax.device_get(params)))
    plot(rows, os.path.join(a.out, "returns.png"), title)
    write_summary(rows=rows)
    print(f"chunk {row['chunk'] + 1}/{cfg.num_chunks}  steps {row['agent_steps']:,}  "
          f"return {row['return_mean']:.1f}  ({row['episodes']} episodes)  "
          f"{row['steps_per_s']:,.0f} steps/s  wall {row['wall_s']:.1f} s", flush=True)

  if a.eval_only:
    with open(os.path.join(a.out, "metrics.json")) as f:
      saved = json.load(f)
    mine = json.loads(json.dumps(summary["config"]))
    differ = [k for k in EVAL_KEYS if saved["config"][k] != mine[k]]
    if differ:
      raise SystemExit(f"--eval-only: {', '.join(differ)} differ from the run in {a.out}; "
                       "pass the run's flags")
    summary.update(saved)
    params = load_params(cfg, os.path.join(a.out, "params.msgpack"))
  else:
    print(f"{title}: {cfg.num_chunks} chunks of {cfg.chunk} iterations × "
          f"{cfg.iteration_steps:,} agent steps", flush=True)
    params, metrics = train(cfg, time_limit=a.time_limit, on_chunk=on_chunk)
    print(f"trained {metrics['agent_steps']:,} agent steps in {metrics['wall_s']:.1f} s "
          f"(build {metrics['build_s']:.1f} s, compile {metrics['compile_s']:.1f} s, "
          f"chunks {metrics['train_s']:.1f} s) on {metrics['device']}", flush=True)
    write_summary(**metrics)
  if proto is not None:
    t0 = time.perf_counter()
    result = proto(params, progress=True,
                   progress_file=os.path.join(a.out, "eval_progress.npz"))
    result.write(a.out)
    print(result.markdown())
    write_summary(eval=dict(
        train=float(result.train_mean[0]), wall_s=time.perf_counter() - t0,
        compile_s=result.compile_s, agent_steps=result.agent_steps,
        conditions={c: dict(mean=float(result.mean(c)[0]), e_g=float(result.e_g(c)[0]))
                    for c in result.conditions}))
  with open(os.path.join(a.out, "summary.md"), "w") as f:
    f.write(markdown(summary))
  print(markdown(summary))
  print(f"wrote {a.out}/metrics.json, summary.md, returns.csv, returns.png, params.msgpack"
        + ("" if proto is None else ", eval.json, eval.md, eval.png"))
  return summary


if __name__ == "__main__":
  main()
