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


def test_suite_compile_quiet_drops_only_the_settotalmass_deprecation(caplog):
  """dm_control's cheetah sets `settotalmass`, which the pinned MuJoCo reports as
  deprecated on every compile: through dm_control's absl callback (from_xml_string)
  and as a Python warning (MjSpec.compile). Our compiles drop it; nothing else."""
  import warnings
  xml, assets = names.suite_xml("cheetah")  # imports dm_control: its callback is set
  def messages(caught):
    return [str(w.message) for w in caught] + [r.getMessage() for r in caplog.records]
  with warnings.catch_warnings(record=True) as caught, caplog.at_level("WARNING"):
    warnings.simplefilter("always")
    mujoco.MjModel.from_xml_string(xml, assets)
    mujoco.MjSpec.from_string(xml, include=assets).compile()
  loud = [m for m in messages(caught) if "settotalmass" in m]
  assert len(loud) == 2, messages(caught)  # the reference: MuJoCo does warn, twice
  caplog.clear()
  with warnings.catch_warnings(record=True) as caught, caplog.at_level("WARNING"):
    warnings.simplefilter("always")
    names.compile_suite_model("cheetah")
    with names.suite_compile_quiet():
      mujoco.MjSpec.from_string(xml, include=assets).compile()
      warnings.warn("another warning")
  assert [m for m in messages(caught) if "settotalmass" in m] == []
  assert "another warning" in messages(caught)
