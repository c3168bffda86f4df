"""JAX ports of `dm_control.suite.utils.randomizers`.

`randomize_limited_and_rotational_joints` draws the same distribution as
dm_control's: limited hinges and slides uniform in their range, unlimited hinges
uniform in [-π, π], unlimited ball joints a uniform unit quaternion, free joints'
orientation `normalize(U(0,1)^4)` (dm_control's documented quirk) with position
untouched. Limited ball joints do not occur in the DMCR domains and raise.
Each joint draws from its own `fold_in(key, joint_id)` stream.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from dmcr_jax._mjx import mjx  # mujoco.mjx, quietly


def randomize_limited_and_rotational_joints(key: jax.Array, m: mjx.Model,
                                            qpos: jax.Array) -> jax.Array:
  """Returns `qpos` with every joint randomised as dm_control's randomizer does."""
  jnt_type = np.asarray(m.jnt_type)
  limited = np.asarray(m.jnt_limited).astype(bool)
  adr = np.asarray(m.jnt_qposadr)
  rng = jnp.asarray(m.jnt_range)
  for j in range(m.njnt):
    k = jax.random.fold_in(key, j)
    t, a = int(jnt_type[j]), int(adr[j])
    if t in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
      if limited[j]:
        qpos = qpos.at[a].set(jax.random.uniform(k, (), minval=rng[j, 0],
                                                 maxval=rng[j, 1]))
      elif t == mujoco.mjtJoint.mjJNT_HINGE:
        qpos = qpos.at[a].set(jax.random.uniform(k, (), minval=-jnp.pi,
                                                 maxval=jnp.pi))
    elif t == mujoco.mjtJoint.mjJNT_BALL:
      if limited[j]:
        raise NotImplementedError("Limited ball joints are not used in DMCR.")
      q = jax.random.normal(k, (4,))
      qpos = qpos.at[a:a + 4].set(q / jnp.linalg.norm(q))
    elif t == mujoco.mjtJoint.mjJNT_FREE:
      q = jax.random.uniform(k, (4,))
      qpos = qpos.at[a + 3:a + 7].set(q / jnp.linalg.norm(q))
  return qpos


def initialize_randomized_joints(key: jax.Array, m: mjx.Model,
                                 d: mjx.Data) -> tuple[mjx.Data, dict]:
  """A `TaskSpec.initialize` that only randomises the joints (walker's and
  hopper's `initialize_episode`): (data with `qpos` drawn, empty info)."""
  return d.replace(qpos=randomize_limited_and_rotational_joints(key, m, d.qpos)), {}
