"""Procedural texture banks (floors and skyboxes), their disk cache, and user folders.

The original DMCR shipped 383 floor photos and 116 landscape photos that we
cannot redistribute. This module generates a replacement bank procedurally and
deterministically: `NUM_FLOORS` tileable 256×256 floor textures in 16 kinds
(grass, soil, sand, gravel, rock, ice, concrete, brick, tiles, moss, leaves,
lichen, snow, mud, cobblestone, frozen ground) and `NUM_BACKGROUNDS` skybox cube
maps (6 faces of 192×192: sky gradients, sun, clouds, stars, mountain ridges,
tree lines, fields, dunes, snow and water with reflections).

Determinism: texture `i` is a pure function of `(VERSION, i)`. Per-texture
parameters come from NumPy's PCG64 raw stream (`PCG64(seed).random_raw`, whose
output is fixed by its specification), pixel noise from an integer hash
(uint32 multiply/xor/shift), and all pixel arithmetic uses only float32 `+ - * /`,
`sqrt`, `floor`, `min`/`max` and comparisons: operations that IEEE 754 rounds
exactly, so the bytes are the same on every machine (tests check hashes). No
transcendental functions, reductions or library interpolation touch pixels.

The bank is built once (with a progress bar) and
cached as `.npy` files under `$XDG_CACHE_HOME/dmcr_jax` (or `~/.cache/dmcr_jax`)
in a folder named by `VERSION`. `load_bank(floor_dir=..., background_dir=...)`
uses a user's image folders instead (files sorted by name, so a seed means the
same image on every machine).

Cube-map layout: `backgrounds[b]` has shape (6, W, W, 3), the faces of an OpenGL
cube map in the order +X, −X, +Y, −Y, +Z, −Z, as MuJoCo uploads a cube texture
whose height is 6× its width. MuJoCo's skybox looks a world direction (x, y, z)
up at cube coordinates (x, z, −y), so world "up" is the +Y face.

Where things live: the bank's sizes and counts in `texture_spec`, the noise and
hash primitives in `texture_noise`, the floors in `texture_floors`, the skyboxes in
`texture_backgrounds`, user image files in `texture_images`; this module holds the
bank itself (`TextureBank`, its cache and build, `load_bank`) and re-exports the
others' public names.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pathlib
import tempfile
from typing import Sequence

import numpy as np

from dmcr_jax._files import write_atomic

# The other modules' names, used here and re-exported for callers (the library's
# own modules import them from their homes).
from dmcr_jax.visuals.texture_backgrounds import (background_name, cube_directions,
                                                  procedural_background)
from dmcr_jax.visuals.texture_floors import floor_name, procedural_floor
from dmcr_jax.visuals.texture_images import (_list_images, _read_rgb, background_from_image,
                                             floor_from_image)
from dmcr_jax.visuals.texture_noise import F32, U32, fbm, value_noise, worley
from dmcr_jax.visuals.texture_spec import (BACKGROUND_SIZE, FLOOR_KINDS, FLOOR_SIZE,
                                           FLOORS_PER_KIND, IMAGE_SUFFIXES, NUM_BACKGROUNDS,
                                           NUM_FLOORS, VERSION)


# ---------------------------------------------------------------------------
# The bank, its cache, and the build
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class TextureBank:
  """Floor textures and skybox cube maps for the render model.

  Attributes:
    floors: uint8 (F, S, S, 3) tileable floor textures.
    backgrounds: uint8 (B, 6, W, W, 3) cube faces (+X, −X, +Y, −Y, +Z, −Z).
    floor_names, background_names: a name per texture (kind or file name).
    source: "procedural/<VERSION>" or the user folders it was read from.
  """
  floors: np.ndarray
  backgrounds: np.ndarray
  floor_names: tuple[str, ...]
  background_names: tuple[str, ...]
  source: str

  @property
  def num_floors(self) -> int:
    return int(self.floors.shape[0])

  @property
  def num_backgrounds(self) -> int:
    return int(self.backgrounds.shape[0])

  @property
  def key(self) -> str:
    """A short content key (source and sizes), used to cache render models."""
    return f"{self.source}|{self.floors.shape}|{self.backgrounds.shape}"

  def subset(self, floors: Sequence[int], backgrounds: Sequence[int]) -> "TextureBank":
    """A smaller bank with the given floor and background ids (for tests/tools)."""
    fl, bg = list(floors), list(backgrounds)
    return TextureBank(
        floors=self.floors[fl], backgrounds=self.backgrounds[bg],
        floor_names=tuple(self.floor_names[i] for i in fl),
        background_names=tuple(self.background_names[i] for i in bg),
        source=f"{self.source}[floors={fl},backgrounds={bg}]")


def cache_dir() -> pathlib.Path:
  """The cache folder: $XDG_CACHE_HOME/dmcr_jax, else ~/.cache/dmcr_jax."""
  base = os.environ.get("XDG_CACHE_HOME") or os.path.join(
      os.path.expanduser("~"), ".cache")
  return pathlib.Path(base) / "dmcr_jax"


def _bank_paths() -> tuple[pathlib.Path, pathlib.Path]:
  d = cache_dir() / VERSION
  return d / "floors.npy", d / "backgrounds.npy"


def _jobs(num_floors: int, num_backgrounds: int) -> list[tuple[str, int]]:
  # Backgrounds first (slowest), then floors, so workers finish together.
  return [("background", i) for i in range(num_backgrounds)] + [
      ("floor", i) for i in range(num_floors)]


def _make(kind: str, index: int) -> np.ndarray:
  return procedural_floor(index) if kind == "floor" else procedural_background(index)


def _worker_main(worker: int, workers: int, out_dir: str, num_floors: int,
                 num_backgrounds: int) -> None:
  """Subprocess entry point: generates jobs[worker::workers] into out_dir."""
  import sys
  for kind, i in _jobs(num_floors, num_backgrounds)[worker::workers]:
    np.save(os.path.join(out_dir, f"{kind}_{i}.npy"), _make(kind, i))
    sys.stdout.write("1\n")
    sys.stdout.flush()


def build_procedural(workers: int | None = None, progress: bool = True
                     ) -> tuple[np.ndarray, np.ndarray]:
  """Generates the whole procedural bank (no cache).

  Work is spread over plain `python -c` subprocesses (not multiprocessing, so
  it is safe to call from scripts without a `__main__` guard and from processes
  that run JAX threads).

  Args:
    workers: processes to use (default: the CPU count; 1 runs in-process).
    progress: show a tqdm progress bar (one line instead when stderr is not a
      terminal).

  Returns:
    (floors (NUM_FLOORS, S, S, 3), backgrounds (NUM_BACKGROUNDS, 6, W, W, 3)).
  """
  import subprocess
  import sys
  import threading
  from tqdm.auto import tqdm
  nf, nb = NUM_FLOORS, NUM_BACKGROUNDS
  jobs = _jobs(nf, nb)
  workers = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
  floors = np.empty((nf, FLOOR_SIZE, FLOOR_SIZE, 3), np.uint8)
  bgs = np.empty((nb, 6, BACKGROUND_SIZE, BACKGROUND_SIZE, 3), np.uint8)
  desc = "dmcr_jax: building texture bank (once)"
  bar_on = progress and sys.stderr.isatty()
  if progress and not bar_on:  # to a log file: one line instead of a bar's redraws
    print(f"{desc} …", file=sys.stderr, flush=True)
  bar = tqdm(total=len(jobs), desc=desc, disable=not bar_on, unit="tex")
  try:
    if workers == 1:
      for kind, i in jobs:
        (floors if kind == "floor" else bgs)[i] = _make(kind, i)
        bar.update()
      return floors, bgs
    with tempfile.TemporaryDirectory(prefix="dmcr_textures_") as tmp:
      # Load this file directly (not the package, which imports JAX): fast start.
      code = ("import importlib.util, sys; "
              "spec = importlib.util.spec_from_file_location('_dmcr_textures', sys.argv[6]); "
              "m = sys.modules['_dmcr_textures'] = importlib.util.module_from_spec(spec); "
              "spec.loader.exec_module(m); "
              "m._worker_main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], "
              "int(sys.argv[4]), int(sys.argv[5]))")
      env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
      procs = [subprocess.Popen([sys.executable, "-c", code, str(w), str(workers), tmp,
                                 str(nf), str(nb), os.path.abspath(__file__)],
                                stdout=subprocess.PIPE, env=env)
               for w in range(workers)]
      lock = threading.Lock()

      def pump(proc):
        for _ in proc.stdout:
          with lock:
            bar.update()
      threads = [threading.Thread(target=pump, args=(p,), daemon=True) for p in procs]
      for t in threads:
        t.start()
      codes = [p.wait() for p in procs]
      for t in threads:
        t.join()
      if any(codes):
        raise RuntimeError(f"texture workers failed with exit codes {codes}")
      for kind, i in jobs:
        (floors if kind == "floor" else bgs)[i] = np.load(
            os.path.join(tmp, f"{kind}_{i}.npy"))
  finally:
    bar.close()
  return floors, bgs


_BANK_CACHE: dict[tuple, TextureBank] = {}


def load_bank(floor_dir: str | os.PathLike | None = None,
              background_dir: str | os.PathLike | None = None,
              progress: bool = True) -> TextureBank:
  """The texture bank: procedural (built once, cached on disk) or user folders.

  Args:
    floor_dir: optional folder of floor images (sorted by file name; centre-
      cropped and resized to 256×256). Replaces the procedural floors.
    background_dir: optional folder of landscape images (sorted by file name;
      wrapped around the horizon of a cube map). Replaces the procedural skies.
    progress: show a progress bar while building the procedural bank.

  Returns:
    A `TextureBank` (cached in-process).
  """
  key = (str(floor_dir) if floor_dir else None,
         str(background_dir) if background_dir else None)
  if key in _BANK_CACHE:
    return _BANK_CACHE[key]
  floors = bgs = None
  fnames = tuple(floor_name(i) for i in range(NUM_FLOORS))
  bnames = tuple(background_name(i) for i in range(NUM_BACKGROUNDS))
  source = [f"procedural/{VERSION}"]
  if floor_dir:
    files = _list_images(floor_dir)
    floors = np.stack([floor_from_image(_read_rgb(f)) for f in files])
    fnames = tuple(f.name for f in files)
    source.append(f"floors={pathlib.Path(floor_dir).expanduser().resolve()}")
  if background_dir:
    files = _list_images(background_dir)
    bgs = np.stack([background_from_image(_read_rgb(f)) for f in files])
    bnames = tuple(f.name for f in files)
    source.append(f"backgrounds={pathlib.Path(background_dir).expanduser().resolve()}")
  if floors is None or bgs is None:
    pf, pb = _procedural_cached(progress)
    floors = pf if floors is None else floors
    bgs = pb if bgs is None else bgs
  bank = TextureBank(floors=floors, backgrounds=bgs, floor_names=fnames,
                     background_names=bnames, source=";".join(source))
  _BANK_CACHE[key] = bank
  return bank


def _procedural_cached(progress: bool) -> tuple[np.ndarray, np.ndarray]:
  fpath, bpath = _bank_paths()
  want_f = (NUM_FLOORS, FLOOR_SIZE, FLOOR_SIZE, 3)  # read at call time
  want_b = (NUM_BACKGROUNDS, 6, BACKGROUND_SIZE, BACKGROUND_SIZE, 3)
  try:
    floors = np.load(fpath, mmap_mode="r")
    bgs = np.load(bpath, mmap_mode="r")
    if floors.shape == want_f and bgs.shape == want_b and floors.dtype == np.uint8:
      return np.asarray(floors), np.asarray(bgs)
  except (OSError, ValueError):
    pass
  floors, bgs = build_procedural(progress=progress)
  write_atomic(fpath, lambda f: np.save(f, floors))
  write_atomic(bpath, lambda f: np.save(f, bgs))
  return floors, bgs


def texture_hash(img: np.ndarray) -> str:
  """sha256 (first 16 hex digits) of a texture's bytes and shape."""
  h = hashlib.sha256(repr((img.shape, str(img.dtype))).encode())
  h.update(np.ascontiguousarray(img).tobytes())
  return h.hexdigest()[:16]
