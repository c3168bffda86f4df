"""Writes the encoder and actor parameters of each agent of a `train` run as msgpack.

Used to bring trained policies back from the GPU machine (whose outputs are
limited to a few files of 16 MiB): one `<dest>/agent<i>.msgpack` per agent
(flax serialization of ``{"encoder": …, "actor": …}``, float32), which
`train.loop.import_params` turns back into a checkpointed run.

    python -m benchmarks.export_params RUN_DIR DEST_DIR
"""

import os
import sys

import flax.serialization
import jax

from train import loop


def main(argv=None) -> None:
  run_dir, dest = (argv or sys.argv[1:])[:2]
  _, agents, step = loop.load_run(run_dir)
  os.makedirs(dest, exist_ok=True)
  k = agents.step.shape[0]
  for i in range(k):
    params = jax.tree.map(lambda x, i=i: x[i], agents.params)
    with open(os.path.join(dest, f"agent{i}.msgpack"), "wb") as f:
      f.write(flax.serialization.to_bytes({"encoder": params["encoder"],
                                           "actor": params["actor"]}))
  print(f"exported {k} agents at step {step} to {dest}")


if __name__ == "__main__":
  main()
