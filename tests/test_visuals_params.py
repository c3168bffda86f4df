"""Visual seeds → VisualParams: seed 0, toggles, independence, ranges, bad inputs."""

import hashlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax import visuals as V
from dmcr_jax.models import names
from dmcr_jax.visuals import params as P
from dmcr_jax.visuals import ranges as R

N = 256                       # one batch size for most tests: one compilation
SEEDS = np.arange(1, N + 1)
FIELDS = ("cam_pos", "cam_rot", "light_pos", "light_dir", "headlight_ambient",
          "headlight_diffuse", "headlight_specular", "body_rgba", "effector_rgba",
          "target_rgba", "floor_id", "background_id", "floor_reflectance",
          "light_diffuse", "light_specular")
# The fields RECORDED_WALKER_HASH covers (those before finger's light colour).
RECORDED_FIELDS = FIELDS[:13]
FACTOR_FIELDS = {f: [k for k, v in P._FIELD_FACTOR.items() if v == f] for f in V.FACTORS}


def as_np(params):
  return {k: np.asarray(getattr(params, k)) for k in FIELDS + ("varied", "seed")}


@pytest.mark.parametrize("domain", V.DOMAINS)
def test_seed_zero_is_dm_control_default(domain):
  p = V.sample(domain, [0] * N, "all")
  dflt = V.defaults(domain)
  assert not np.asarray(p.varied).any()
  for k in FIELDS:
    np.testing.assert_array_equal(np.asarray(getattr(p, k))[0], dflt[k], err_msg=k)
  # The defaults are dm_control's model values.
  m = names.suite_model(domain)
  r = R.DOMAIN_RANGES[domain]
  np.testing.assert_array_equal(
      dflt["cam_pos"], m.cam_pos[names.obj_id(m, P.mujoco.mjtObj.mjOBJ_CAMERA, r.camera)]
      .astype(np.float32))
  np.testing.assert_array_equal(dflt["headlight_ambient"], np.float32([.4, .4, .4]))
  assert dflt["floor_id"] == -1 and dflt["background_id"] == -1


def test_vary_none_is_default_for_every_seed():
  p = as_np(V.sample("walker", SEEDS, "none"))
  d0 = as_np(V.sample("walker", [0] * N, "all"))
  for k in FIELDS + ("varied",):
    np.testing.assert_array_equal(p[k], d0[k], err_msg=k)


@pytest.mark.parametrize("factor", V.FACTORS)
def test_toggle_isolation(factor):
  """Switching one factor off changes only its own fields (to the defaults)."""
  domain = "cheetah" if factor != "target" else "reacher"
  full = as_np(V.sample(domain, SEEDS, "all"))
  rest = [f for f in V.FACTORS if f != factor]
  without = as_np(V.sample(domain, SEEDS, rest))
  only = as_np(V.sample(domain, SEEDS, [factor]))
  dflt = V.defaults(domain)
  for k in FIELDS:
    if k in FACTOR_FIELDS[factor]:
      np.testing.assert_array_equal(without[k], np.broadcast_to(dflt[k], without[k].shape))
      np.testing.assert_array_equal(only[k], full[k], err_msg=k)
    else:
      np.testing.assert_array_equal(without[k], full[k], err_msg=k)
  assert full["varied"][:, V.FACTORS.index(factor)].all()


def test_factors_not_in_table5_are_ignored():
  # Reflectance and target do not apply to cartpole; background not to fish.
  for domain, factor in (("cartpole", "reflectance"), ("cartpole", "target"),
                         ("fish", "background"), ("humanoid", "background"),
                         ("reacher", "background"), ("walker", "target")):
    assert factor not in V.APPLICABLE[domain]
    p = as_np(V.sample(domain, SEEDS, "all"))
    assert not p["varied"][:, V.FACTORS.index(factor)].any()
    for k in FACTOR_FIELDS[factor]:
      np.testing.assert_array_equal(p[k], np.broadcast_to(V.defaults(domain)[k], p[k].shape))


def test_independence_between_factors():
  """|correlation| < 0.05 between draws of different factors over 10,000 seeds."""
  p = V.sample("cheetah", np.arange(1, 10_001), "all")
  cols = {
      "camera": np.asarray(p.cam_pos)[:, 0], "camera_z": np.asarray(p.cam_pos)[:, 2],
      "light": np.asarray(p.light_pos)[:, 0],
      "headlight": np.asarray(p.headlight_ambient)[:, 0],
      "body": np.asarray(p.body_rgba)[:, 0], "effector": np.asarray(p.effector_rgba)[:, 1],
      "floor": np.asarray(p.floor_id).astype(float),
      "background": np.asarray(p.background_id).astype(float),
      "reflectance": np.asarray(p.floor_reflectance),
  }
  factor_of = {"camera": "camera", "camera_z": "camera", "light": "light",
               "headlight": "light", "body": "body", "effector": "body",
               "floor": "floor", "background": "background",
               "reflectance": "reflectance"}
  t = V.sample("reacher", np.arange(1, 10_001), "all")
  cols["target"] = np.asarray(t.target_rgba)[:, 0]
  cols["reacher_floor"] = np.asarray(t.floor_id).astype(float)
  factor_of["target"], factor_of["reacher_floor"] = "target", "floor"
  names = list(cols)
  corr = np.corrcoef(np.stack([cols[n] for n in names]))
  for i, a in enumerate(names):
    for j, b in enumerate(names):
      if factor_of[a] != factor_of[b]:
        assert abs(corr[i, j]) < 0.05, (a, b, corr[i, j])
  # And the draws are spread over their ranges.
  assert len(np.unique(cols["floor"])) == V.NUM_FLOORS
  assert len(np.unique(cols["background"])) == V.NUM_BACKGROUNDS


@pytest.mark.parametrize("domain", V.DOMAINS)
def test_values_in_ranges(domain):
  p = as_np(V.sample(domain, SEEDS, "all"))
  r = R.DOMAIN_RANGES[domain]
  for i in range(3):
    lo, hi = r.cam_pos[i]
    assert (p["cam_pos"][:, i] >= np.float32(lo)).all()
    assert (p["cam_pos"][:, i] <= np.float32(hi) + 1e-2 * (hi - lo) + 1e-6).all()
  for k in ("body_rgba", "effector_rgba"):
    assert (p[k][:, :3] >= 0).all() and (p[k][:, :3] < 1).all()
    assert (p[k][:, 3] >= .75).all() and (p[k][:, 3] <= 1).all()
  for k in ("headlight_ambient", "headlight_diffuse", "headlight_specular"):
    assert (p[k] >= 0).all() and (p[k] <= 1).all()
  assert (p["headlight_ambient"] >= .05).all() and (p["headlight_ambient"] <= .85).all()
  if "floor" in V.APPLICABLE[domain]:
    assert (p["floor_id"] >= 0).all() and (p["floor_id"] < V.NUM_FLOORS).all()
  if "reflectance" in V.APPLICABLE[domain]:
    assert (p["floor_reflectance"] >= 0).all() and (p["floor_reflectance"] < .5).all()
  if r.light_pos is None:   # walker, hopper: only the headlight varies
    np.testing.assert_array_equal(p["light_pos"], np.broadcast_to(
        V.defaults(domain)["light_pos"], p["light_pos"].shape))
  assert np.isfinite(np.concatenate([p[k].reshape(N, -1).astype(float)
                                     for k in FIELDS], 1)).all()


def test_deterministic_and_recorded():
  """Same seeds, same bytes; and the bytes are the benchmark's (recorded)."""
  seeds = np.concatenate([[1, 2, 3, 1000, 2**31 - 1], SEEDS[5:]])
  a = V.sample("walker", seeds.tolist(), "all")
  b = V.sample("walker", seeds.astype(np.int64), "all")
  h = hashlib.sha256()
  for k in FIELDS + ("varied", "seed"):
    np.testing.assert_array_equal(np.asarray(getattr(a, k)), np.asarray(getattr(b, k)))
  for k in RECORDED_FIELDS + ("varied", "seed"):
    h.update(np.ascontiguousarray(np.asarray(getattr(a, k))[:5]).tobytes())
  assert h.hexdigest()[:16] == RECORDED_WALKER_HASH
  # A seed's look does not depend on the batch it is in (nor on its position).
  c = V.sample("walker", np.roll(seeds, 7), "all")
  for k in FIELDS:
    np.testing.assert_array_equal(np.roll(np.asarray(getattr(a, k)), 7, axis=0),
                                  np.asarray(getattr(c, k)))


RECORDED_WALKER_HASH = "f46949a59fc56dcd"   # VisualParams bytes of 5 walker seeds


def test_jittable_and_traced_seeds():
  seeds = jnp.asarray(SEEDS, jnp.int32)
  eager = V.sample("finger", seeds, "all")
  jitted = jax.jit(lambda s: V.sample("finger", s, "all"))(seeds)
  for k in FIELDS:
    np.testing.assert_array_equal(np.asarray(getattr(eager, k)), np.asarray(getattr(jitted, k)))
  assert jitted.domain == "finger" and len(jitted) == N
  one = eager.take(3)
  assert len(one) == 1 and int(one.seed[0]) == 4


def test_vary_parsing():
  assert V.parse_vary("all") == frozenset(V.FACTORS)
  assert V.parse_vary("none") == frozenset() == V.parse_vary(None) == V.parse_vary([])
  assert V.parse_vary(" Floor, background ") == {"floor", "background"}
  assert V.parse_vary(("camera",)) == {"camera"}
  assert V.active_factors("fish", "all") == V.APPLICABLE["fish"]
  assert V.active_factors("walker-walk", "target,floor") == {"floor"}


@pytest.mark.parametrize("vary", ["floors", "camera,colour", ["light", "sky"], "all,none"])
def test_unknown_factor_raises_listing_valid(vary):
  with pytest.raises(ValueError) as e:
    V.sample("walker", [1], vary)
  for f in V.FACTORS:
    assert f in str(e.value)


@pytest.mark.parametrize("seeds, err", [
    ([-1], ValueError), ([2**31], ValueError), (np.array([2**40]), ValueError),
    ([1.0, 2.0], TypeError), (np.array([0.5]), TypeError), (True, TypeError),
    (["3"], TypeError), ([[1, 2], [3, 4]], ValueError), (jnp.array([1.5]), TypeError),
])
def test_bad_seeds_raise(seeds, err):
  with pytest.raises(err, match="seed"):
    V.sample("walker", seeds)


def test_bad_domain_and_bank_sizes():
  with pytest.raises(ValueError, match="walker"):
    V.sample("walkr", [1])
  with pytest.raises(ValueError, match="num_floors"):
    V.sample("walker", [1], num_floors=0)
  with pytest.raises(ValueError, match="num_backgrounds"):
    V.sample("walker", [1], num_backgrounds=2.5)
  with pytest.raises(TypeError):
    V.sample("walker", [1], vary=3)


def test_bank_size_is_respected():
  p = V.sample("walker", SEEDS, "floor,background", num_floors=3, num_backgrounds=2)
  assert set(np.asarray(p.floor_id)) == {0, 1, 2}
  assert set(np.asarray(p.background_id)) == {0, 1}
