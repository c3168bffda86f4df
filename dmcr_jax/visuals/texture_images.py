"""Textures from a user's image files: listing, reading and resampling.

Folders are read in file-name order (so a seed means the same image on every
machine); a floor image is centre-cropped and resized to a square, a landscape
photo is wrapped around a skybox's horizon.
"""

from __future__ import annotations

import pathlib

import numpy as np

from dmcr_jax.visuals.texture_backgrounds import _azimuth, _dirs
from dmcr_jax.visuals.texture_noise import F32, _lerp, _to_uint8
from dmcr_jax.visuals.texture_spec import BACKGROUND_SIZE, FLOOR_SIZE, IMAGE_SUFFIXES


# ---------------------------------------------------------------------------
# User image folders
# ---------------------------------------------------------------------------


def _list_images(folder) -> list[pathlib.Path]:
  folder = pathlib.Path(folder).expanduser()
  if not folder.is_dir():
    raise ValueError(f"Not a folder: {folder}")
  files = sorted((f for f in folder.iterdir()
                  if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES),
                 key=lambda f: f.name)
  if not files:
    raise ValueError(f"No images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
  return files


def _read_rgb(path) -> np.ndarray:
  import imageio.v3 as iio
  img = np.asarray(iio.imread(path))
  if img.ndim == 2:
    img = np.repeat(img[..., None], 3, axis=-1)
  if img.ndim == 4:          # animated: first frame
    img = img[0]
  img = img[..., :3]
  if img.dtype != np.uint8:
    scale = 255.0 / float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else 255.0
    img = np.clip(img.astype(np.float64) * scale + 0.5, 0, 255).astype(np.uint8)
  return img


def _bilinear(img: np.ndarray, u, v) -> np.ndarray:
  """Samples img (H, W, 3) uint8 at normalised coords u (x), v (y) in [0, 1]."""
  h, w = img.shape[:2]
  fx = np.clip(u * F32(w) - F32(0.5), F32(0), F32(w - 1))
  fy = np.clip(v * F32(h) - F32(0.5), F32(0), F32(h - 1))
  x0, y0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
  x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
  tx, ty = (fx - x0.astype(F32))[..., None], (fy - y0.astype(F32))[..., None]
  im = img.astype(F32) * F32(1.0 / 255)
  top = _lerp(im[y0, x0], im[y0, x1], tx)
  bot = _lerp(im[y1, x0], im[y1, x1], tx)
  return _lerp(top, bot, ty)


def floor_from_image(img: np.ndarray, size: int = FLOOR_SIZE) -> np.ndarray:
  """Resizes a user's floor image to a square texture (centre crop, bilinear)."""
  h, w = img.shape[:2]
  side = min(h, w)
  y0, x0 = (h - side) // 2, (w - side) // 2
  img = img[y0:y0 + side, x0:x0 + side]
  c = (np.arange(size, dtype=F32) + F32(0.5)) * F32(1.0 / size)
  vv, uu = np.meshgrid(c, c, indexing="ij")
  return _to_uint8(_bilinear(img, uu, vv))


def background_from_image(img: np.ndarray, size: int = BACKGROUND_SIZE) -> np.ndarray:
  """Wraps a user's landscape photo around the horizon of a skybox cube.

  The photo covers a quarter turn of azimuth and is mirror-repeated around the
  horizon (no seams); vertically it spans sin(elevation) ∈ [−0.5, 0.5], and
  above/below it its top/bottom rows are extended.
  """
  d = _dirs(size)
  az = _azimuth(d[..., 0], d[..., 1])             # [0, 4)
  seg = np.floor(az)
  frac = az - seg
  u = np.where((seg.astype(np.int64) % 2) == 0, frac, F32(1) - frac)
  v = np.clip(F32(0.5) - d[..., 2], F32(0), F32(1))
  return _to_uint8(_bilinear(img, u, v))
