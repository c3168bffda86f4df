"""The pool env's look cache (`env_looks.static_looks`): kept as it is while no env's
seed or factors change, and otherwise equal to the looks made afresh, env by env."""

import dataclasses

import numpy as np
import pytest

from dmcr_jax.env_looks import static_looks, vary_key
from dmcr_jax.visuals import render_model as rmod
from tests.banks import procedural_bank


@pytest.fixture(scope="module")
def rm():
  """walker's render model with a small bank (3 floors, 3 skies)."""
  bank = procedural_bank((0, 7, 10), (0, 1, 2), "env-looks-test-bank")
  return rmod.build_render_model("walker", bank)


def _reference(rm, seeds, varies) -> dict:
  """Each env's look made alone from its seed and factors."""
  rows = [rmod.prepare(rm, rm.sample([s], vary=v)) for s, v in zip(seeds, varies)]
  return {f.name: np.concatenate([getattr(r, f.name) for r in rows])
          for f in dataclasses.fields(rmod.Looks)}


def _assert_looks(looks, want):
  for name, value in want.items():
    np.testing.assert_array_equal(getattr(looks, name), value, err_msg=name)


def test_cached_looks_follow_each_env_s_seed_and_factors(rm):
  varies = tuple(vary_key(v) for v in ("all", "none", ["floor", "camera"], "all"))
  seeds = np.array([0, 5, 9, 2**30 + 3], np.int32)
  first = static_looks(rm, seeds, varies)
  _assert_looks(first.looks, _reference(rm, seeds, varies))
  assert static_looks(rm, seeds.copy(), varies, first) is first      # nothing changed
  # one env's seed and another's factors change: those rows are made again
  seeds2, varies2 = seeds.copy(), ("all", "none", "all", "all")
  seeds2[0] = 7
  second = static_looks(rm, seeds2, varies2, first)
  _assert_looks(second.looks, _reference(rm, seeds2, varies2))
  _assert_looks(first.looks, _reference(rm, seeds, varies))         # the old one unchanged
  np.testing.assert_array_equal(np.asarray(second.params.seed), seeds2)
