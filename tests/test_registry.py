"""Registry, reward helper and action handling (fast, no physics compile beyond cartpole)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from dm_control.utils import rewards as dm_rewards

import dmcr_jax
from dmcr_jax import models
from dmcr_jax.models.rewards import SIGMOIDS, tolerance


def test_all_tasks_listed():
  assert len(dmcr_jax.ALL_TASKS) == 22
  assert "walker-walk" in dmcr_jax.ALL_TASKS
  assert len(dmcr_jax.DOMAIN_TASKS) == 10


@pytest.mark.parametrize("bad", ["walker-fly", "walker", "", None, "Walker-Walk"])
def test_unknown_task_lists_valid(bad):
  with pytest.raises(ValueError, match="walker-walk"):
    models.load(bad)


@pytest.mark.parametrize("sigmoid", SIGMOIDS)
@pytest.mark.parametrize("bounds,margin,vam", [((0., 0.), 1., .1), ((-1., 2.), .5, .3),
                                               ((0., np.inf), 2., .05), ((1., 1.), 0., .1)])
def test_tolerance_matches_dm_control(sigmoid, bounds, margin, vam):
  if sigmoid in ("gaussian", "hyperbolic", "long_tail", "reciprocal", "tanh_squared") and vam == 0:
    return
  x = np.random.RandomState(0).uniform(-5, 5, 1000)
  want = dm_rewards.tolerance(x, bounds=bounds, margin=margin, sigmoid=sigmoid,
                              value_at_margin=vam)
  got = jax.jit(lambda v: tolerance(v, bounds, margin, sigmoid, vam))(x.astype(np.float32))
  np.testing.assert_allclose(np.asarray(got), want, atol=2e-6)


def test_tolerance_bad_arguments():
  with pytest.raises(ValueError):
    tolerance(0., bounds=(1., 0.))
  with pytest.raises(ValueError):
    tolerance(0., margin=-1.)
  with pytest.raises(ValueError, match="gaussian"):
    tolerance(3., margin=1., sigmoid="nope")


@pytest.mark.slow
def test_actions_clipped_and_non_finite_handled():
  task = models.load("cartpole-balance")
  s0 = jax.jit(task.reset)(jax.random.key(0))  # eager MJX runs op by op: far slower
  step = jax.jit(task.step)
  big = step(s0, jnp.array([5.0]))
  one = step(s0, jnp.array([1.0]))
  np.testing.assert_array_equal(np.asarray(big.obs), np.asarray(one.obs))
  for bad in (np.nan, np.inf, -np.inf):
    s = step(s0, jnp.array([bad]))
    assert np.all(np.isfinite(np.asarray(s.obs)))
  nan = step(s0, jnp.array([np.nan]))
  zero = step(s0, jnp.array([0.0]))
  np.testing.assert_array_equal(np.asarray(nan.obs), np.asarray(zero.obs))
