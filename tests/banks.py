"""Small texture banks for tests: a few procedural floors and skies instead of the
whole bank (what the tests of one look need; small is fast)."""

import numpy as np

from dmcr_jax.visuals import textures as T


def procedural_bank(floors, skies, source: str) -> T.TextureBank:
  """A `TextureBank` of the procedural floors and backgrounds of those indices,
  named by `source`."""
  return T.TextureBank(
      floors=np.stack([T.procedural_floor(i) for i in floors]),
      backgrounds=np.stack([T.procedural_background(i) for i in skies]),
      floor_names=tuple(T.floor_name(i) for i in floors),
      background_names=tuple(T.background_name(i) for i in skies),
      source=source)
