"""Moves trained policies between machines as small files (encoder + actor parameters).

The GPU machine returns at most a few files of 16 MiB, and a full checkpoint
(optimizer states, critics, targets) is ~80 MB per agent. `export` writes one
`<dest>/agent<i>.msgpack` per agent of a `train` run (flax serialization of
``{"encoder": …, "actor": …}``, float32, ~12 MB) plus its config.json and, for a
run that ended, its summary.json (how it trained: `evaluate` records it); `import`
rebuilds a run folder from them that `evaluate` and `dmcr_jax.train.analysis` accept. The
imported agents' critics, targets and optimizer states are fresh, so such a run is
for evaluation only, not for `--resume`.

    python -m dmcr_jax.benchmarks.export_params export RUN_DIR DEST
    python -m dmcr_jax.benchmarks.export_params import DEST NEW_RUN_DIR
"""

from __future__ import annotations

import argparse
import glob
import os
import shutil

import flax.serialization
import jax
import jax.numpy as jnp

from dmcr_jax._files import write_atomic
from dmcr_jax.train import loop


def export(run_dir: str, dest: str) -> int:
  """Writes the run's agent<i>.msgpack files, then its summary.json (if any) and
  config.json; returns the count.

  Each file is written whole or not at all, and config.json last: a `dest`
  holding config.json holds every agent (what `benchmarks/paper_runs.sh` checks).
  """
  _, agents, step = loop.load_run(run_dir)
  k = agents.step.shape[0]
  for i in range(k):
    params = jax.tree.map(lambda x, i=i: x[i], agents.params)
    data = flax.serialization.to_bytes({"encoder": params["encoder"],
                                        "actor": params["actor"], "step": step})
    write_atomic(os.path.join(dest, f"agent{i}.msgpack"), lambda f, data=data: f.write(data))
  for name in ("summary.json", "config.json"):
    if os.path.exists(os.path.join(run_dir, name)):
      with open(os.path.join(run_dir, name), "rb") as src:
        data = src.read()
      write_atomic(os.path.join(dest, name), lambda f, data=data: f.write(data))
  return k


def import_run(src: str, run_dir: str) -> int:
  """Builds `run_dir` (config.json, summary.json if exported, a checkpoint) from
  `export`'s files."""
  import dmcr_jax
  cfg = loop.load_config(src)
  files = sorted(glob.glob(os.path.join(src, "agent*.msgpack")),
                 key=lambda p: int(os.path.basename(p)[5:-8]))
  specs = cfg.agents()
  if len(files) != len(specs):
    raise ValueError(f"{src} holds {len(files)} agent files; its config has {len(specs)}")
  cfg = loop.TrainConfig(**{**cfg.__dict__, "out_dir": run_dir})
  os.makedirs(run_dir, exist_ok=True)
  loop.save_config(cfg, run_dir)
  if os.path.exists(os.path.join(src, "summary.json")):
    shutil.copy(os.path.join(src, "summary.json"), os.path.join(run_dir, "summary.json"))
  obs_shape = (cfg.image_size, cfg.image_size, 3 * cfg.frame_stack)
  agents = loop.init_agents(cfg, obs_shape, dmcr_jax.load(cfg.task).action_size)
  one = jax.tree.map(lambda x: x[0], agents.params)
  like = {"encoder": one["encoder"], "actor": one["actor"]}
  loaded = []
  for path in files:
    with open(path, "rb") as f:
      raw = flax.serialization.msgpack_restore(f.read())
    restored = flax.serialization.from_state_dict(
        like, {"encoder": raw["encoder"], "actor": raw["actor"]})
    loaded.append(dict(restored, step=int(raw.get("step", 0))))
  stack = lambda name: jax.tree.map(lambda *x: jnp.stack(x), *[p[name] for p in loaded])
  params = {**agents.params, "encoder": stack("encoder"), "actor": stack("actor")}
  agents = agents.replace(params=params)
  loop._save(loop._checkpointer(run_dir), int(loaded[0]["step"]), agents, jax.random.key(0))
  return len(files)


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("action", choices=("export", "import"))
  p.add_argument("src", help="export: a train run folder; import: export's folder")
  p.add_argument("dest", help="export: a folder for the files; import: the new run folder")
  a = p.parse_args(argv)
  if a.action == "export":
    print(f"exported {export(a.src, a.dest)} agents to {a.dest}")
  else:
    print(f"imported {import_run(a.src, a.dest)} agents into {a.dest}")


if __name__ == "__main__":
  main()
