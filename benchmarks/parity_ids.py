"""Which side of the renderer-parity check a machine changes: MuJoCo's or the ray caster's.

`dump` renders the parity check's frames (`dmcr_jax.benchmarks.jax_render_parity.compare`:
dm_control states × visual seeds) and saves, per domain, MuJoCo's segmentation
(body ids) and the ray caster's body ids, and optionally both RGB frames, to an
`.npz`. `compare` reads two dumps made on different machines (say the CPU
machine with Mesa's GL and the GPU machine with NVIDIA's EGL) and counts, per
domain, the body-id pixels in which each side changed between them (and how many
of MuJoCo's lie on a silhouette edge), next to each machine's own count of
pixels where the two renderers disagree.

    MUJOCO_GL=egl python -m dmcr_jax.benchmarks.parity_ids dump --domains walker,humanoid \\
        --seeds 25 --states 3 --out parity_ids_cpu.npz
    python -m dmcr_jax.benchmarks.parity_ids compare parity_ids_cpu.npz parity_ids_h100.npz
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from dmcr_jax.benchmarks import rows as R


def dump(domains: list[str], seeds: int, states: int, out: str, rgb: bool = False) -> None:
  """Saves `compare`'s body ids (int8, (frames, H, W)) per domain to `out`."""
  from dmcr_jax.benchmarks import jax_render_parity
  arrays = {}
  for domain in domains:
    res = jax_render_parity.compare(domain, range(seeds), states=states)
    ref, jax_ids = (np.stack(x).astype(np.int8) for x in zip(*res["ids"]))
    arrays[f"{domain}_refbody"], arrays[f"{domain}_jaxbody"] = ref, jax_ids
    if rgb:
      arrays[f"{domain}_ref"], arrays[f"{domain}_jax"] = (np.stack(x) for x in zip(*res["frames"]))
    print(f"{domain}: {len(ref)} frames", flush=True)
  np.savez_compressed(out, **arrays)


def on_edge(ids: np.ndarray) -> np.ndarray:
  """Pixels whose 3×3 neighbourhood (within the frame) holds more than one id."""
  padded = np.pad(ids, ((0, 0), (1, 1), (1, 1)), mode="edge")
  h, w = ids.shape[1:]
  shifts = [padded[:, 1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
            for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
  return np.any([s != ids for s in shifts], axis=0)


def compare(a: dict, b: dict) -> list[dict]:
  """One row per domain of two dumps (`np.load` results or dicts of arrays)."""
  rows = []
  domains = sorted({k.rsplit("_", 1)[0] for k in a if k.endswith("_refbody")})
  for d in domains:
    if f"{d}_refbody" not in b:
      raise ValueError(f"domain {d!r} is in the first dump but not the second "
                       f"(it has: {sorted(k for k in b if k.endswith('_refbody'))})")
    ra, rb, ja, jb = a[f"{d}_refbody"], b[f"{d}_refbody"], a[f"{d}_jaxbody"], b[f"{d}_jaxbody"]
    if ra.shape != rb.shape:
      raise ValueError(f"{d}: dumps of different sizes {ra.shape} and {rb.shape}")
    changed = ra != rb
    rows.append(dict(domain=d, frames=len(ra), pixels=int(ra.size),
                     mujoco_changed=int(changed.sum()),
                     mujoco_changed_on_edges=int((changed & on_edge(ra)).sum()),
                     mujoco_frames_changed=int(changed.any(axis=(1, 2)).sum()),
                     ray_caster_changed=int((ja != jb).sum()),
                     disagree_first=int((ra != ja).sum()),
                     disagree_second=int((rb != jb).sum())))
  return rows


def markdown(rows: list[dict], first: str, second: str) -> str:
  """`compare`'s rows as a Markdown table; `first` and `second` name the two dumps."""
  count = lambda key: lambda r: f"{r[key]:,}"
  return R.table(rows, [
      ("domain", "domain"), ("frames", "frames"),
      ("MuJoCo ids changed (px)", count("mujoco_changed")),
      ("of them on silhouette edges", count("mujoco_changed_on_edges")),
      ("frames with a change", "mujoco_frames_changed"),
      ("ray-caster ids changed (px)", count("ray_caster_changed")),
      (f"MuJoCo ≠ ray caster, {first}", count("disagree_first")),
      (f"MuJoCo ≠ ray caster, {second}", count("disagree_second"))])


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  sub = p.add_subparsers(dest="cmd", required=True)
  d = sub.add_parser("dump", help="render and save body ids")
  d.add_argument("--domains", default="walker,humanoid")
  d.add_argument("--seeds", type=int, default=25, help="visual seeds 0 … N−1")
  d.add_argument("--states", type=int, default=3, help="dm_control states per domain")
  d.add_argument("--rgb", action="store_true", help="also save both RGB frames")
  d.add_argument("--out", required=True, help=".npz path")
  c = sub.add_parser("compare", help="compare two dumps")
  c.add_argument("first")
  c.add_argument("second")
  args = p.parse_args(sys.argv[1:] if argv is None else argv)
  if args.cmd == "dump":
    from dmcr_jax.visuals.factors import DOMAINS
    domains = args.domains.split(",")
    bad = [x for x in domains if x not in DOMAINS]
    if bad:
      p.error(f"unknown domain(s) {', '.join(bad)}; valid: {', '.join(DOMAINS)}")
    dump(domains, args.seeds, args.states, args.out, args.rgb)
  else:
    print(markdown(compare(np.load(args.first), np.load(args.second)), args.first, args.second))


if __name__ == "__main__":
  main()
