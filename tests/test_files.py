"""`dmcr_jax._files.write_atomic`: a file is written whole or not at all."""

import os

import numpy as np
import pytest

from dmcr_jax._files import write_atomic


def test_a_failed_write_leaves_the_previous_file_and_no_temporary_one(tmp_path):
  path = tmp_path / "sub" / "a.npz"  # the folder is made
  write_atomic(path, lambda f: np.savez(f, x=np.arange(3)))
  def fail(f):
    f.write(b"partial")
    raise KeyboardInterrupt
  with pytest.raises(KeyboardInterrupt):
    write_atomic(path, fail)
  with np.load(path) as saved:
    np.testing.assert_array_equal(saved["x"], np.arange(3))
  assert os.listdir(tmp_path / "sub") == ["a.npz"]
