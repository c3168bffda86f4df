"""`dmcr_jax.models.names`: dm_control's suite models and name → id lookups."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from dm_control import suite
from mujoco import mjx

from dmcr_jax.models import names


def test_lookups_match_dm_control_on_mujoco_and_mjx_models():
  env = suite.load("walker", "walk", task_kwargs={"random": 0})
  env.reset()
  m = names.suite_model("walker")
  mx = mjx.put_model(m)
  named = env.physics.named
  for model in (m, mx):
    assert names.body_id(model, "torso") == env.physics.model.name2id("torso", "body")
    assert names.geom_id(model, "floor") == env.physics.model.name2id("floor", "geom")
    assert names.joint_id(model, "right_knee") == env.physics.model.name2id(
        "right_knee", "joint")
    assert names.qpos_adr(model, "right_knee") == named.data.qpos.axes.row.convert_key_item(
        "right_knee").start
    assert names.qvel_adr(model, "left_hip") == named.data.qvel.axes.row.convert_key_item(
        "left_hip").start
    assert names.find_id(model, mujoco.mjtObj.mjOBJ_BODY, "no_such_body") == -1
  # A sensor read equals dm_control's named read of the same data.
  got = names.sensor(env.physics.model.ptr, env.physics.data.ptr, "torso_subtreelinvel")
  np.testing.assert_array_equal(got, named.data.sensordata["torso_subtreelinvel"])
  idx = names.sensor_indices(mx, "torso_subtreelinvel")
  np.testing.assert_array_equal(env.physics.data.sensordata[idx], got)


def test_absent_names_and_fields_raise_naming_them():
  m = names.suite_model("cartpole")
  with pytest.raises(ValueError, match="No body named 'nope' in the model"):
    names.body_id(m, "nope")
  with pytest.raises(ValueError, match="No geom named 'nope'"):
    names.field_id(m, "geom_pos", "nope")
  with pytest.raises(ValueError, match="not one of an element kind"):
    names.field_id(m, "tendon_range", "x")
  assert names.field_id(m, "geom_rgba", "pole_1") == m.geom("pole_1").id


def test_suite_model_is_cached_and_compile_is_fresh():
  assert names.suite_model("cartpole") is names.suite_model("cartpole")
  fresh = names.compile_suite_model("cartpole")
  assert fresh is not names.suite_model("cartpole")
  assert fresh.nq == names.suite_model("cartpole").nq
