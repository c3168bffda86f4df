"""`dmcr_jax.benchmarks.parity_ids`: edge marking and the cross-machine counts, on small arrays."""

import numpy as np
import pytest

from dmcr_jax.benchmarks import parity_ids


def test_on_edge_marks_pixels_next_to_another_id():
  ids = np.zeros((1, 5, 5), np.int8)
  ids[0, 2, 2] = 3
  edge = parity_ids.on_edge(ids)
  expected = np.zeros((5, 5), bool)
  expected[1:4, 1:4] = True  # the changed pixel and its eight neighbours
  np.testing.assert_array_equal(edge[0], expected)


def test_compare_counts_each_side():
  ref = np.zeros((2, 4, 4), np.int8)
  ref[:, 1:3, 1:3] = 1
  a = {"walker_refbody": ref, "walker_jaxbody": ref.copy()}
  b = {"walker_refbody": ref.copy(), "walker_jaxbody": ref.copy()}
  b["walker_refbody"][0, 0, 0] = 1   # next to the square: an edge pixel
  b["walker_refbody"][1, 3, 3] = 5   # ... and so is this corner (diagonal neighbour)
  b["walker_jaxbody"][1, 0, 3] = 2
  (row,) = parity_ids.compare(a, b)
  assert row == dict(domain="walker", frames=2, pixels=32, mujoco_changed=2,
                     mujoco_changed_on_edges=2, mujoco_frames_changed=2,
                     ray_caster_changed=1, disagree_first=0, disagree_second=3)


def test_compare_rejects_a_missing_domain():
  ids = np.zeros((1, 2, 2), np.int8)
  with pytest.raises(ValueError, match="humanoid"):
    parity_ids.compare({"humanoid_refbody": ids, "humanoid_jaxbody": ids}, {})
