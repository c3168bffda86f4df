"""The texture bank's fixed shape: its version, texture sizes, counts and floor kinds.

Texture `i` is a pure function of `(VERSION, i)`; a new `VERSION` names a new bank
(and a new cache folder). `IMAGE_SUFFIXES` are the files read from a user's folder.
"""

VERSION = "dmcr-textures-v1"
FLOOR_SIZE = 256
BACKGROUND_SIZE = 192
FLOOR_KINDS: tuple[str, ...] = (
    "grass", "soil", "sand", "gravel", "rock", "ice", "concrete", "brick",
    "tiles", "moss", "leaves", "lichen", "snow", "mud", "cobblestone",
    "frozen_ground")
FLOORS_PER_KIND = 20
NUM_FLOORS = len(FLOOR_KINDS) * FLOORS_PER_KIND          # 320
NUM_BACKGROUNDS = 120
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".gif", ".tif", ".tiff", ".webp")
