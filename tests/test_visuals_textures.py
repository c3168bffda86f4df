"""Texture banks: recorded hashes (same bytes everywhere), sizes, cache, user folders."""

import numpy as np
import pytest

from dmcr_jax.visuals import textures as T

# sha256 prefixes of generated textures (they must be the same on every machine).
RECORDED = {
    ("floor", 0): "b7048ca6e9b46dd1",
    ("floor", 7): "e2a43a7c8cd5b950",
    ("floor", 10): "d7b29ba8b59fe099",
    ("floor", 319): "8a8e0afe34565bcc",
    ("background", 0): "8c1aafc9e1c08f61",
    ("background", 119): "17d7b63d164ac497",
}


@pytest.mark.parametrize("kind, index", sorted(RECORDED))
def test_recorded_hashes(kind, index):
  img = (T.procedural_floor(index) if kind == "floor" else T.procedural_background(index))
  assert T.texture_hash(img) == RECORDED[(kind, index)]


def test_bank_sizes_and_kinds():
  assert T.NUM_FLOORS >= 300 and T.NUM_BACKGROUNDS >= 100
  kinds = {T.floor_name(i).rsplit("_", 1)[0] for i in range(T.NUM_FLOORS)}
  assert kinds == set(T.FLOOR_KINDS) and len(kinds) >= 11
  for k in ("grass", "soil", "sand", "gravel", "rock", "ice", "concrete", "brick",
            "tiles", "moss", "leaves"):
    assert k in kinds
  f = T.procedural_floor(3)
  b = T.procedural_background(3)
  assert f.shape == (T.FLOOR_SIZE, T.FLOOR_SIZE, 3) and f.dtype == np.uint8
  assert b.shape == (6, T.BACKGROUND_SIZE, T.BACKGROUND_SIZE, 3) and b.dtype == np.uint8


def test_textures_differ_and_are_not_flat():
  floors = [T.procedural_floor(i) for i in range(16)]       # one of each kind
  hashes = {T.texture_hash(f) for f in floors}
  assert len(hashes) == 16
  for f in floors:
    assert f.astype(float).std() > 3            # has structure
  means = np.array([f.reshape(-1, 3).mean(0) for f in floors])
  assert means.std(0).min() > 10                # kinds look different


def test_floors_tile_seamlessly():
  for i in (0, 3, 7, 14):                       # grass, gravel, brick, cobblestone
    f = T.procedural_floor(i).astype(float)
    inner = np.abs(np.diff(f, axis=1)).mean()
    seam = np.abs(f[:, 0] - f[:, -1]).mean()
    assert seam < 2.5 * inner + 2


def test_cube_directions_cover_the_sphere():
  d = T.cube_directions(8)
  np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-6)
  # face order +X −X +Y −Y +Z −Z of cube coordinates (x, z, −y) of the world
  centre = d[:, 3:5, 3:5].mean(axis=(1, 2))
  expect = [(1, 0, 0), (-1, 0, 0), (0, 0, 1), (0, 0, -1), (0, -1, 0), (0, 1, 0)]
  np.testing.assert_allclose(centre / np.linalg.norm(centre, axis=-1, keepdims=True),
                             expect, atol=0.05)


def test_bad_indices():
  with pytest.raises(ValueError):
    T.procedural_floor(T.NUM_FLOORS)
  with pytest.raises(ValueError):
    T.procedural_background(-1)


def test_cache_build_and_reload(tmp_path, monkeypatch):
  """The bank is built once (in worker processes), saved, and reloaded."""
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
  monkeypatch.setattr(T, "NUM_FLOORS", 3)
  monkeypatch.setattr(T, "NUM_BACKGROUNDS", 2)
  monkeypatch.setattr(T, "_BANK_CACHE", {})
  assert T.cache_dir() == tmp_path / "dmcr_jax"
  bank = T.load_bank(progress=False)
  assert bank.floors.shape[0] == 3 and bank.backgrounds.shape[0] == 2
  for i in range(3):
    np.testing.assert_array_equal(bank.floors[i], T.procedural_floor(i))
  np.testing.assert_array_equal(bank.backgrounds[1], T.procedural_background(1))
  files = sorted(p.name for p in (tmp_path / "dmcr_jax" / T.VERSION).iterdir())
  assert files == ["backgrounds.npy", "floors.npy"]

  def fail(*a, **k):
    raise AssertionError("rebuilt although cached")
  monkeypatch.setattr(T, "_BANK_CACHE", {})
  monkeypatch.setattr(T, "build_procedural", fail)
  again = T.load_bank(progress=False)
  np.testing.assert_array_equal(again.floors, bank.floors)
  assert T.load_bank(progress=False) is again          # in-process cache



def test_progress_to_a_log_file_is_one_line(monkeypatch, capsys):
  """With stderr not a terminal (a log file), the build says so in one line, not in
  a progress bar's carriage-return redraws."""
  monkeypatch.setattr(T, "NUM_FLOORS", 2)
  monkeypatch.setattr(T, "NUM_BACKGROUNDS", 1)
  T.build_procedural(workers=1, progress=True)
  err = capsys.readouterr().err
  assert "\r" not in err and err.count("building texture bank") == 1, err
  T.build_procedural(workers=1, progress=False)
  assert capsys.readouterr().err == ""

def _write_images(folder, names, seed):
  import imageio.v3 as iio
  folder.mkdir()
  rng = np.random.default_rng(seed)
  for k, name in enumerate(names):
    img = np.full((40 + 8 * k, 60, 3), 30 * k, np.uint8)
    img[..., 1] = rng.integers(0, 255, img.shape[:2])
    iio.imwrite(folder / name, img)


def test_user_folders_sorted_by_name(tmp_path, monkeypatch):
  monkeypatch.setattr(T, "_BANK_CACHE", {})
  _write_images(tmp_path / "floors", ["c.png", "a.png", "b.jpg"], 0)
  _write_images(tmp_path / "skies", ["z.png", "m.png"], 1)
  (tmp_path / "floors" / "notes.txt").write_text("not an image")
  bank = T.load_bank(tmp_path / "floors", tmp_path / "skies", progress=False)
  assert bank.floor_names == ("a.png", "b.jpg", "c.png")
  assert bank.background_names == ("m.png", "z.png")
  assert bank.floors.shape == (3, T.FLOOR_SIZE, T.FLOOR_SIZE, 3)
  assert bank.backgrounds.shape == (2, 6, T.BACKGROUND_SIZE, T.BACKGROUND_SIZE, 3)
  # "a.png" was written second (k=1): its red channel is 30.
  assert abs(int(bank.floors[0][..., 0].mean()) - 30) <= 1
  with pytest.raises(ValueError, match="No images"):
    T.load_bank(tmp_path / "floors" / "..", None)


def test_the_visual_seeds_page_states_the_bank_sizes():
  # It said 300 floors and 100 backgrounds.
  import os
  from dmcr_jax.visuals import textures
  page = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs",
                      "visual_seeds.md")
  with open(page) as f:
    text = " ".join(f.read().split())
  assert (f"The texture banks ({textures.NUM_FLOORS} floors in {len(textures.FLOOR_KINDS)} "
          f"kinds, {textures.NUM_BACKGROUNDS} backgrounds") in text
