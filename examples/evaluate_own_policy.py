"""Your own policy through the paper's zero-shot protocol (`dmcr_jax.protocol`).

A policy is a pure JAX function ``policy(params, obs, key) -> actions`` on a uint8
batch of frame stacks (B, H, W, 3·stack), returning float actions (B, A) in
[−1, 1]. Here: a small flax network (randomly initialised; load your trained
params instead), K of them at once with ``--agents K``, or a scripted policy.

    python -m examples.evaluate_own_policy --tiny                # CPU, about a minute
    python -m examples.evaluate_own_policy --task walker-walk    # the full protocol (GPU)
    python -m examples.evaluate_own_policy --tiny --policy random --agents 1

See docs/protocol.md.
"""

import argparse

import flax.linen as nn
import jax
import jax.numpy as jnp

import dmcr_jax
from dmcr_jax import protocol


class ConvPolicy(nn.Module):
  """obs uint8 (B, H, W, C) → tanh actions (B, A): two convolutions and a dense layer."""
  action_size: int

  @nn.compact
  def __call__(self, obs):
    x = obs.astype(jnp.float32) / 255.0
    x = nn.relu(nn.Conv(16, (3, 3), strides=2)(x))
    x = nn.relu(nn.Conv(16, (3, 3), strides=2)(x))
    return jnp.tanh(nn.Dense(self.action_size)(x.reshape(x.shape[0], -1)))


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--task", default="cartpole-balance")
  p.add_argument("--policy", default="flax", choices=("flax", "random"))
  p.add_argument("--agents", type=int, default=2, help="flax networks evaluated in one pass")
  p.add_argument("--tiny", action="store_true", help="CPU sizes: 2 looks, 16 px, short episodes")
  p.add_argument("--out", default="eval_own_policy")
  a = p.parse_args(argv)
  tiny = dict(visual_seeds=2, dynamics_seeds=1, train_episodes=2, conditions=("none", "all"),
              image_size=16, action_repeat=100) if a.tiny else {}
  size = tiny.get("image_size", 84)
  action_size = dmcr_jax.load(a.task).action_size

  if a.policy == "flax":
    net = ConvPolicy(action_size)
    keys = jax.random.split(jax.random.key(0), a.agents)             # K networks
    params = jax.vmap(lambda k: net.init(k, jnp.zeros((1, size, size, 9), jnp.uint8)))(keys)
    policy = lambda params, obs, key: net.apply(params, obs)
    agents = a.agents
  else:  # scripted: uniform random actions from the protocol's per-env keys
    params, agents = None, None
    policy = lambda params, obs, key: jax.random.uniform(
        key, (obs.shape[0], action_size), minval=-1.0, maxval=1.0)

  result = protocol.evaluate(a.task, policy, params, agents=agents, progress=True, **tiny)
  print(result.markdown())
  result.write(a.out)
  print(f"wrote {a.out}/eval.json, eval.md and eval.png")
  return result


if __name__ == "__main__":
  main()
