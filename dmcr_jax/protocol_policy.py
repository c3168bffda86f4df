"""The protocol's policy contract: the policy inside the program, and its checks.

A `Policy` is ``policy(params, obs, key) -> actions``: uint8 (B, H, W, 3·stack)
frame stacks to float (B, A) actions in [−1, 1]. `policy_actions` runs it vmapped
over envs (each of K agents on its own envs) with per-env keys; `env_actions` maps its
actions onto the task's bounds; `check_policy` traces it abstractly before anything
compiles; `worst_action` and `check_actions` catch NaN or out-of-range actions;
`agent_count` checks params against a leading agent axis; `params_digest` keys a
progress file by the params.
"""

from __future__ import annotations

import hashlib
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.checks import positive_int

Policy = Callable[[Any, jax.Array, jax.Array], jax.Array]
"""``policy(params, obs, key) -> actions``: uint8 (B, H, W, 3·stack) → float (B, A)."""


def params_digest(params) -> str:
  """SHA-1 of a pytree's structure and leaf bytes (what a progress file is keyed by)."""
  h = hashlib.sha1(str(jax.tree.structure(params)).encode())
  for leaf in jax.tree.leaves(jax.device_get(params)):
    a = np.asarray(leaf)
    h.update(str((a.shape, a.dtype)).encode())
    h.update(np.ascontiguousarray(a).tobytes())
  return h.hexdigest()


POLICY_STREAM = 0x9E3779B9
"""`fold_in` constant of the policy keys' stream (apart from the dynamics keys)."""


def policy_actions(policy: Policy, params, obs: jax.Array, index: jax.Array,
                   t: jax.Array, key: jax.Array, agents: int | None) -> jax.Array:
  """Every env's action: the policy vmapped over envs, each agent on its own envs.

  Env e's action is ``policy(params_k, obs[e:e+1], fold_in(fold_in(key, index[e]),
  t))[0]``, so it depends on its own observation and key alone. The vmap over
  envs batches the policy's layers over them (a batch-1 convolution becomes one
  of the agent's B envs). The K agents are K separate calls in the program, each
  on its own params and rows (static slices), so each agent's layers keep their
  own unbatched weights (a vmap over agents would make grouped convolutions of K
  groups) and XLA may schedule the K calls together; the program grows with K.

  Args:
    policy: the `Policy`.
    params: its params (leading axis K when `agents` is K).
    obs: uint8 (K·B, H, W, C) observations, agent k's in rows [k·B, (k+1)·B).
    index: int32 (K·B,) each env's episode index within its segment.
    t: int32 scalar, the agent step.
    key: the pass's policy key.
    agents: K, or None (params without an agent axis).

  Returns:
    float (K·B, A) actions.
  """
  keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.fold_in(key, i), t))(index)
  one = lambda p, o, k: policy(p, o[None], k)[0]
  per_env = jax.vmap(one, in_axes=(None, 0, 0))
  if agents is None:
    return per_env(params, obs, keys)
  b = obs.shape[0] // agents
  rows = lambda x, a: x[a * b:(a + 1) * b]
  return jnp.concatenate([per_env(jax.tree.map(lambda x: x[a], params), rows(obs, a),
                                  rows(keys, a)) for a in range(agents)])


def worst_action(actions: jax.Array, agents: int) -> jax.Array:
  """float32 (K,) max |action| of each agent's envs; NaN where any action is NaN."""
  a = jnp.abs(actions.astype(jnp.float32)).reshape(agents, -1)
  return jnp.where(jnp.isnan(a).any(axis=1), jnp.nan, jnp.max(a, axis=1))


def env_actions(actions: jax.Array, low: np.ndarray, high: np.ndarray) -> jax.Array:
  """Policy actions in [−1, 1] → the task's bounds (float32), as `dmcr_jax.train.step`'s
  `to_env_action`."""
  low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
  return (low + (actions.astype(jnp.float32) + 1.0) * 0.5 * (high - low)).astype(jnp.float32)


def agent_count(params, agents) -> int | None:
  """`agents` checked against the params' leading axes (None: no agent axis)."""
  if agents is None:
    return None
  k = positive_int("agents", agents)
  leaves = jax.tree.leaves(params)
  if not leaves:
    raise ValueError("params has no arrays: with agents=K every leaf carries a leading "
                     "axis of K agents")
  bad = sorted({tuple(np.shape(x)) for x in leaves if np.ndim(x) == 0 or np.shape(x)[0] != k})
  if bad:
    raise ValueError(f"agents={k}: every params leaf must have a leading axis of {k} "
                     f"agents; got leaves of shape {', '.join(map(str, bad[:3]))}")
  return k


_TRACER_ERRORS = tuple(getattr(jax.errors, name) for name in (
    "ConcretizationTypeError", "TracerArrayConversionError", "TracerBoolConversionError",
    "TracerIntegerConversionError", "UnexpectedTracerError") if hasattr(jax.errors, name))


def check_policy(policy: Policy, params, obs_shape: tuple[int, ...], action_size: int,
                 agents: int | None) -> None:
  """Traces `policy` abstractly (`jax.eval_shape`, nothing compiled or run) on one
  agent's params, a uint8 batch of 2 observations and a key; ValueError unless it
  is a pure JAX function returning float (2, action_size).

  Args:
    policy: the `Policy`.
    params: its params (leading axis K when `agents` is K).
    obs_shape: (H, W, 3·frame_stack).
    action_size: A.
    agents: K or None.
  """
  if not callable(policy):
    raise ValueError(f"policy must be a function policy(params, obs, key) -> actions, got "
                     f"{type(policy).__name__}")
  spec = lambda x: jax.ShapeDtypeStruct(np.shape(x)[1 if agents else 0:], jnp.result_type(x))
  one = jax.tree.map(spec, params)
  obs = jax.ShapeDtypeStruct((2,) + tuple(obs_shape), jnp.uint8)
  key = jax.eval_shape(lambda: jax.random.key(0))
  try:
    out = jax.eval_shape(policy, one, obs, key)
  except _TRACER_ERRORS as e:
    first = str(e).strip().splitlines()[0]
    raise ValueError("policy must be a pure JAX function of (params, obs, key): tracing "
                     f"it on abstract arrays failed ({type(e).__name__}: {first})") from e
  except Exception as e:  # noqa: BLE001 - any failure of the user's code, named
    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
    raise ValueError(f"policy(params, obs, key) failed when traced on obs uint8 "
                     f"{obs.shape} and one agent's params ({type(e).__name__}: {first})"
                     ) from e
  want = (2, action_size)
  if not isinstance(out, jax.ShapeDtypeStruct) or tuple(out.shape) != want:
    got = out.shape if isinstance(out, jax.ShapeDtypeStruct) else type(out).__name__
    raise ValueError(f"policy must return actions of shape (batch, action_size) = {want} "
                     f"for a batch of 2 observations {tuple(obs.shape)}, got {got}")
  if not jnp.issubdtype(out.dtype, jnp.floating):
    raise ValueError(f"policy must return float actions in [-1, 1], got dtype {out.dtype}")


def check_actions(worst: np.ndarray) -> None:
  """ValueError naming the agents whose actions were NaN or outside [−1, 1]
  (`worst`: each agent's `worst_action`)."""
  nan = np.flatnonzero(np.isnan(worst))
  out = np.flatnonzero(worst > 1.0)
  if len(nan) or len(out):
    parts = []
    if len(nan):
      parts.append(f"NaN actions (agents {nan.tolist()})")
    if len(out):
      parts.append(f"actions outside [-1, 1] (agents {out.tolist()}, largest |action| "
                   f"{float(np.nanmax(worst[out])):.4g})")
    raise ValueError(f"policy returned {' and '.join(parts)}: a policy must return "
                     "finite actions in [-1, 1] (they are not clipped); squash them, "
                     "e.g. with jnp.tanh")
