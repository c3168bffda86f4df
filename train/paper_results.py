"""The DMCR paper's Table 4: returns of pixel SAC variants under each visual condition.

Agents trained on dm_control's default look ("none") and tested with one factor
of the scene changed (light, camera, body colour, floor, background) or all of
them; 300 episodes over 100 visual seeds, averaged over five runs (the paper's
caption). `evaluate` prints a run's row beside the paper's. CURL's camera entry for
Hopper, Stand reads "202.7.4" in the paper's source; it is kept as 202.7.
"""

from __future__ import annotations

COLUMNS: tuple[str, ...] = ("none", "light", "camera", "body", "floor", "background", "all")
"""The conditions of Table 4, in its column order (`body` is "Body Color")."""

METHODS: tuple[str, ...] = ("SAC+AE", "CURL", "SAC+AUG", "SAC+CJ+AUG", "SAC+NR+AUG")

_TABLE: dict[str, dict[str, tuple[float, ...]]] = {
    "ball_in_cup-catch": {
        "SAC+AE": (647.0, 610.5, 489.9, 334.5, 105.3, 107.5, 99.2),
        "CURL": (822.5, 707.0, 766.9, 342.3, 169.4, 106.5, 109.2),
        "SAC+AUG": (934.5, 918.9, 873.4, 261.0, 147.1, 118.6, 103.0),
        "SAC+CJ+AUG": (955.6, 954.9, 889.6, 928.2, 949.3, 509.4, 322.1),
        "SAC+NR+AUG": (948.5, 947.8, 864.9, 937.6, 932.6, 582.3, 411.2)},
    "walker-walk": {
        "SAC+AE": (643.6, 538.0, 145.9, 316.9, 31.7, 53.8, 25.0),
        "CURL": (622.7, 472.8, 532.6, 231.7, 25.8, 46.3, 25.3),
        "SAC+AUG": (919.3, 830.1, 518.3, 550.7, 31.1, 106.2, 28.0),
        "SAC+CJ+AUG": (925.1, 905.4, 459.6, 852.6, 535.3, 240.3, 71.9)},
    "finger-spin": {
        "SAC+AE": (622.1, 615.7, 76.4, 347.4, 8.1, 38.8, 0.1),
        "CURL": (731.3, 716.9, 521.1, 433.7, 29.6, 53.6, 1.6),
        "SAC+AUG": (916.7, 873.2, 441.7, 525.3, 470.3, 98.1, 7.4),
        "SAC+CJ+AUG": (798.5, 796.4, 388.8, 760.6, 795.7, 274.6, 82.8),
        "SAC+NR+AUG": (797.6, 788.0, 420.6, 779.5, 795.5, 332.4, 154.7)},
    "cheetah-run": {
        "SAC+AE": (387.9, 252.9, 36.4, 252.6, 65.8, 75.9, 4.2),
        "CURL": (202.3, 142.6, 157.9, 109.3, 18.5, 32.1, 2.4),
        "SAC+AUG": (712.7, 321.8, 259.3, 471.3, 127.9, 310.6, 19.8),
        "SAC+CJ+AUG": (669.2, 406.3, 278.9, 620.6, 144.3, 359.7, 47.4)},
    "cartpole-balance": {
        "SAC+AE": (942.8, 810.8, 377.2, 492.6, 313.8, 254.2, 212.3),
        "CURL": (885.7, 789.9, 831.7, 521.2, 403.9, 261.4, 233.3),
        "SAC+AUG": (987.4, 963.0, 878.1, 655.2, 565.1, 422.2, 218.8),
        "SAC+CJ+AUG": (984.2, 920.9, 876.5, 865.5, 978.3, 457.1, 358.6),
        "SAC+NR+AUG": (946.0, 859.8, 855.6, 860.9, 923.2, 462.5, 377.4)},
    "hopper-stand": {
        "SAC+AE": (631.8, 616.4, 7.7, 260.4, 6.3, 1.4, 1.6),
        "CURL": (425.5, 311.9, 202.7, 72.1, 12.4, 4.7, 1.9),
        "SAC+AUG": (878.1, 764.9, 195.2, 403.4, 46.0, 39.5, 3.3),
        "SAC+CJ+AUG": (848.3, 778.6, 188.2, 693.4, 144.5, 50.5, 1.8)},
}

METHOD_OF_AUG: dict[str, str] = {"drq": "SAC+AUG", "cj+drq": "SAC+CJ+AUG",
                                 "nr+drq": "SAC+NR+AUG"}
"""The paper's method name for an SAC+AUG run trained with this augmentation."""


def method_name(algo: str, aug: str) -> str | None:
  """The paper's name for an agent trained with `algo` ("sac_aug", "curl", "sac_ae")
  and augmentation `aug`, or None when the paper has no such method."""
  if algo == "sac_aug":
    return METHOD_OF_AUG.get(aug)
  if aug == "none":
    return {"curl": "CURL", "sac_ae": "SAC+AE"}.get(algo)
  return None


def table4(task: str, method: str) -> dict[str, float] | None:
  """The paper's Table 4 row for `task` and `method` as {condition: return}, or None."""
  row = _TABLE.get(task, {}).get(method)
  return None if row is None else dict(zip(COLUMNS, row))
