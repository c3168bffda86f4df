"""`dmcr_jax.augment.check`, `register` and import paths (`load`).

Every built-in passes the checker on real renders; for every property an
augmentation broken in exactly that way fails exactly that property (the
others pass or are skipped because they need it).
"""

import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.core import unsafe_am_i_under_a_jit_DO_NOT_USE as under_jit

from dmcr_jax import augment
from dmcr_jax import augment_check as ac
from examples.augmentations import hue_rotation

pytestmark = pytest.mark.xdist_group("augment_check")


def _failed(aug, **kw):
  return set(augment.check(aug, raise_error=False, **kw).failed)


def test_observations_are_real_renders_with_aligned_stacks():
  obs, next_obs = ac.observations(32)
  n = len(ac.CHECK_TASKS) * len(ac.CHECK_LOOKS)
  assert obs.shape == next_obs.shape == (n, 32, 32, 3 * ac.STACK)
  assert obs.dtype == np.uint8
  # o′ is o one step later: its first two frames are o's last two.
  np.testing.assert_array_equal(next_obs[..., :6], obs[..., 3:])
  assert not np.array_equal(next_obs[..., 6:], obs[..., 6:])
  # Different looks of one task differ; the pictures are not flat.
  assert not np.array_equal(obs[0], obs[1])
  assert obs.std() > 20


@pytest.mark.parametrize("name", augment.NAMES)
def test_every_builtin_passes(name):
  report = augment.check(name)
  assert report.ok and all(r.status == "pass" for r in report.results), str(report)


def test_the_example_passes_by_import_path_composed_with_drq():
  assert augment.check("examples.augmentations:hue_rotation+drq").ok


# --------------------------------------------------------------------------- #
# One broken augmentation per property: per-sample functions fn(key, image).
# --------------------------------------------------------------------------- #

_calls = itertools.count()


def _nondeterministic(key, x):
  return jnp.roll(x, next(_calls) % 5 + 1, axis=1)  # Python state, not the key


@jax.custom_batching.custom_vmap
def _first_sample(x):
  return x


@_first_sample.def_vmap
def _first_sample_rule(axis_size, in_batched, x):  # wrong: sample 0 for all
  return jnp.broadcast_to(x[:1], x.shape), in_batched[0]


def _per_frame_draw(key, x):
  frames = [jnp.roll(x[..., 3 * f:3 * f + 3],
                     jax.random.randint(jax.random.fold_in(key, f), (), 1, 8), axis=1)
            for f in range(x.shape[-1] // 3)]
  return jnp.concatenate(frames, axis=-1)


BROKEN = {
    "runs": lambda key, x: x.reshape(-1, 7),
    "uint8": lambda key, x: x.astype(jnp.float32),
    "shape": lambda key, x: x[1:],
    "nan": lambda key, x: (x * jnp.where(x > 100, 1.0, jnp.nan)).astype(jnp.uint8),
    "range": lambda key, x: (x.astype(jnp.int32) + 100).astype(jnp.uint8),
    "deterministic": _nondeterministic,
    "jit": lambda key, x: x[:, ::-1] if under_jit() else x,
    "vmap": lambda key, x: _first_sample(x),
    "frames": _per_frame_draw,
    "alignment": lambda key, x: x.reshape(*x.shape[:2], -1, 3)[:, :, ::-1].reshape(x.shape),
}


@pytest.mark.parametrize("prop", sorted(BROKEN))
def test_a_broken_augmentation_fails_exactly_its_property(prop):
  report = augment.check(BROKEN[prop], raise_error=False)
  assert report.failed == (prop,), str(report)
  assert prop in str(report)


def test_uint8_overflow_fails_range():
  assert _failed(lambda key, x: x + jnp.uint8(100)) == {"range"}


def test_o_and_next_o_with_different_draws_fail_pair():
  drq = augment.get("drq")

  def unshared(key, images):  # a batch augmentation: each array its own draw
    leaves, tree = jax.tree.flatten(images)
    return jax.tree.unflatten(tree, [drq(jax.random.fold_in(key, i), x)
                                     for i, x in enumerate(leaves)])

  assert _failed(unshared, batched=True) == {"pair"}
  assert _failed(lambda key, images: drq(key, images), batched=True) == set()


def test_check_raises_naming_the_failures():
  with pytest.raises(ac.AugmentationCheckError, match="fails uint8") as e:
    augment.check(BROKEN["uint8"])
  assert e.value.report.failed == ("uint8",)
  skipped = [r.name for r in augment.check(BROKEN["runs"], raise_error=False).results
             if r.status == "skip"]
  assert skipped == [p for p, _ in ac.PROPERTIES if p != "runs"]


# --------------------------------------------------------------------------- #
# register / load / get.
# --------------------------------------------------------------------------- #


@pytest.fixture
def registered():
  yield augment.register("hue", hue_rotation)
  augment.unregister("hue")


def test_register_makes_get_and_compositions_accept_the_name(registered):
  from dmcr_jax.train import sac
  key = jax.random.key(3)
  obs = np.random.default_rng(0).integers(0, 256, (4, 16, 16, 9), dtype=np.uint8)
  assert augment.get("hue") is registered and "hue" in augment.registered()
  out = augment.get("hue")(key, obs)
  for i in range(4):  # sample i draws from fold_in(key, i), the built-ins' rule
    np.testing.assert_array_equal(out[i], hue_rotation(jax.random.fold_in(key, i), obs[i]))
  composed = augment.get("hue+drq")
  np.testing.assert_array_equal(
      composed(key, obs),
      augment.get("drq")(jax.random.fold_in(key, 1),
                         augment.get("hue")(jax.random.fold_in(key, 0), obs)))
  assert sac.SACConfig(aug="drq,hue+drq").aug_names == ("drq", "hue+drq")
  assert augment.check("hue").ok


def test_register_refuses_bad_names_and_non_functions():
  for bad in ("drq", "a+b", "a,b", "m:f", "", "2x"):
    with pytest.raises(ValueError):
      augment.register(bad, hue_rotation)
  with pytest.raises(TypeError, match="fn\\(key, image\\)"):
    augment.register("thing", 3)
  with pytest.raises(ValueError, match="registered: |valid names"):
    augment.get("not_there")


def test_import_paths_load_and_explain_failures():
  aug = augment.get("examples.augmentations:hue_rotation")
  assert aug.name == "examples.augmentations:hue_rotation"
  with pytest.raises(ValueError, match="cannot import module 'no_such_pkg.mod'.*"
                                       "current directory"):
    augment.get("no_such_pkg.mod:fn+drq")
  with pytest.raises(ValueError, match="has no attribute 'nope'; its functions: "
                                       "hue_rotation"):
    augment.get("examples.augmentations:nope")
  with pytest.raises(ValueError, match="not callable|fn\\(key, image\\)"):
    augment.get("examples.augmentations:jnp.pi")


def test_benchmark_times_an_imported_augmentation_beside_the_builtins(tmp_path):
  from dmcr_jax.benchmarks import augment as bench
  out = tmp_path / "augment.jsonl"
  bench.main(["--batch", "4", "--size", "16", "--names", "none,drq", "--aug",
              "examples.augmentations:hue_rotation", "--min-time", "0", "--min-reps",
              "1", "--max-reps", "2", "--out", str(out)])
  rows = [json.loads(line) for line in out.read_text().splitlines()]
  assert [r["name"] for r in rows] == ["none", "drq", "examples.augmentations:hue_rotation"]
  assert all(r["median_ms"] > 0 and r["pair_median_ms"] > 0 for r in rows)
  assert "`examples.augmentations:hue_rotation`" in (tmp_path / "augment.md").read_text()
  with pytest.raises(SystemExit):
    bench.main(["--names", "none", "--aug", "no_such_module:fn", "--out", str(out)])
