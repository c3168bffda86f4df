"""FLOPs and bytes of one SAC+AUG update pair per op category, K agents, from its HLO.

Lowers (traces only: nothing compiles or runs, so it works on any machine)
`dmcr_jax.train.step.learn_jit` for one update pair of K agents with the agent
loop "vmap", as `dmcr_jax.benchmarks.learner` runs it ("map" runs the K = 1
program K times: its counts per agent-update are the K = 1 ones), and counts
each instruction of the unoptimised HLO once per execution (computations called
from several sites count per site; while bodies once: one pair; reducers' bodies
are part of their reduce). Per op:

- FLOPs: a dot 2·|out|·|contracted|; a convolution 2·|out|·|kernel|/out-features
  (grouped or not); an elementwise op or a reduce one per output or input element.
- bytes: a dot or convolution its operands and output (the least it must move);
  a gather or dynamic slice twice its output, a dynamic-update-slice twice its
  update (the rows moved, not the replay buffer they index: XLA's own count
  charges the whole buffer); reshapes, broadcasts, constants, parameters, tuples
  none; every other op its operands and output, as if unfused (an upper bound:
  XLA fuses elementwise chains on GPUs).

The roofline time of a category is max(FLOPs / peak FLOP/s, bytes / memory
bandwidth) at the rates given (default: an H200, bf16 dense 989 TFLOP/s and
4.8 TB/s), so a category is compute- or memory-bound by which term wins.

Usage::

    python -m dmcr_jax.benchmarks.learner_roofline [--agents 1,8] [--dtype bfloat16] \\
        [--impl blocks] [--out PATH.md]
"""

from __future__ import annotations

import argparse
import collections
import re
import sys

import numpy as np

from dmcr_jax.benchmarks import rows as R

_BYTES = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4,
          "u32": 4, "f32": 4, "s64": 8, "u64": 8, "f64": 8}
_SHAPE = re.compile(r"\b(pred|[suf]\d+|bf16)\[([\d,]*)\]")
_INSTR = re.compile(r"^\s+(?:ROOT )?%?(\S+) = (.+?) ([\w-]+)\((.*)$")
_FREE = {"reshape", "bitcast", "broadcast", "constant", "parameter", "tuple",
         "get-tuple-element", "iota", "after-all", "partition-id", "replica-id",
         "while", "call", "conditional", "custom-call", "opt-barrier"}
_MOVES = {"transpose", "concatenate", "pad", "slice", "copy", "reverse", "convert",
          "bitcast-convert", "select", "clamp"}
CATEGORIES = ("convolution", "grouped convolution", "dot", "replay rows (gather, dynamic slices)", "reduce",
              "elementwise", "data movement (transpose, concat, pad, slice, convert)",
              "random bits and other")


def _shapes(text: str) -> list[tuple[int, int]]:
  """(elements, bytes) of every array shape in `text`, in order."""
  out = []
  for dtype, dims in _SHAPE.findall(text):
    n = int(np.prod([int(d) for d in dims.split(",") if d] or [1]))
    out.append((n, n * _BYTES[dtype]))
  return out


def category(opcode: str, attrs: str = "") -> str:
  """The `CATEGORIES` entry of an HLO instruction (its opcode; a convolution's
  attributes tell a grouped one: feature or batch group count > 1)."""
  if opcode == "convolution":
    grouped = re.search(r"(feature|batch)_group_count=(?!1\b)\d+", attrs)
    return CATEGORIES[1] if grouped else CATEGORIES[0]
  if opcode == "dot":
    return CATEGORIES[2]
  if opcode in ("gather", "dynamic-slice", "dynamic-update-slice", "scatter"):
    return CATEGORIES[3]
  if opcode in ("reduce", "reduce-window"):
    return CATEGORIES[4]
  if opcode in _MOVES:
    return CATEGORIES[6]
  if opcode in ("rng-bit-generator", "rng", "sort"):
    return CATEGORIES[7]
  return CATEGORIES[5]


def op_cost(opcode: str, out_type: str, operand_types: list[str], attrs: str
            ) -> tuple[float, float]:
  """(FLOPs, bytes) of one instruction (module doc), from its result type, its
  operands' types and its attributes (the text after its operand list)."""
  if opcode in _FREE:
    return 0.0, 0.0
  out = _shapes(out_type)
  out_n, out_b = sum(n for n, _ in out), sum(b for _, b in out)
  operands = [_shapes(t) for t in operand_types]
  in_b = sum(b for shapes in operands for _, b in shapes)
  if opcode == "dot":
    lhs = [int(d) for d in _SHAPE.search(operand_types[0]).group(2).split(",") if d]
    dims = re.search(r"lhs_contracting_dims=\{([\d,]*)\}", attrs).group(1)
    contracted = int(np.prod([lhs[int(i)] for i in dims.split(",") if i] or [1]))
    return 2.0 * out_n * contracted, in_b + out_b
  if opcode == "convolution":
    rhs = [int(d) for d in _SHAPE.search(operand_types[1]).group(2).split(",") if d]
    labels = re.search(r"dim_labels=\w+_(\w+)->", attrs).group(1)
    per_output = int(np.prod(rhs)) // rhs[labels.index("o")]
    return 2.0 * out_n * per_output, in_b + out_b
  if opcode in ("gather", "dynamic-slice"):
    return 0.0, 2.0 * out_b
  if opcode == "dynamic-update-slice":
    return 0.0, 2.0 * operands[1][0][1]
  if opcode in ("reduce", "reduce-window"):
    return float(sum(n for shapes in operands[:len(operands) // 2] for n, _ in shapes)), \
        in_b + out_b
  if opcode in _MOVES:
    return 0.0, in_b + out_b
  return float(out_n), in_b + out_b


def hlo_costs(text: str) -> dict[str, dict[str, float]]:
  """{category: {"flops", "bytes", "ops"}} of an unoptimised HLO module's text
  (`Lowered.as_text(dialect="hlo")`)."""
  comps, current, types = {}, None, {}
  for line in text.splitlines():
    head = re.match(r"^(ENTRY )?%?([\w.-]+)\b.*\{$", line)
    if head and not line.startswith("HloModule"):
      current = head.group(2)
      comps[current] = {"entry": bool(head.group(1)), "instrs": []}
      continue
    m = _INSTR.match(line)
    if current and m:
      name, out_type, opcode, rest = m.groups()
      types[name] = out_type
      depth, end = 1, 0
      for end, ch in enumerate(rest):  # the operand list ends at its closing parenthesis
        depth += {"(": 1, ")": -1}.get(ch, 0)
        if not depth:
          break
      comps[current]["instrs"].append((opcode, out_type, rest[:end], rest[end + 1:]))
  reducers = set()
  calls = collections.defaultdict(list)  # computation → computations it runs
  for name, comp in comps.items():
    for opcode, _, _, attrs in comp["instrs"]:
      for attr, callee in re.findall(r"(to_apply|body|condition|calls|branch_computations|"
                                     r"true_computation|false_computation)=\{?%?([\w.-]+)",
                                     attrs):
        if opcode in ("call", "while", "conditional", "custom-call") or attr != "to_apply":
          calls[name].append(callee)
        else:
          reducers.add(callee)
  runs = collections.Counter()
  stack = [n for n, c in comps.items() if c["entry"]]
  while stack:
    name = stack.pop()
    runs[name] += 1
    stack.extend(calls[name])
  totals = {c: {"flops": 0.0, "bytes": 0.0, "ops": 0} for c in CATEGORIES}
  for name, count in runs.items():
    if name in reducers:
      continue
    for opcode, out_type, operand_text, attrs in comps[name]["instrs"]:
      if opcode in _FREE:
        continue
      operand_types = [types.get(o.strip().lstrip("%"), o) for o in operand_text.split(",")
                       if o.strip()]
      flops, nbytes = op_cost(opcode, out_type, operand_types, attrs)
      t = totals[category(opcode, attrs)]
      t["flops"] += count * flops
      t["bytes"] += count * nbytes
      t["ops"] += count
  return totals


def lowered_text(k: int, dtype: str = "bfloat16", batch: int = 256, size: int = 84,
                 stack: int = 3, action_size: int = 6) -> str:
  """The unoptimised HLO of one update pair of K vmapped agents (`learn_jit`,
  pairs = 1), lowered from abstract shapes (nothing is initialised, compiled or run)."""
  import jax
  from dmcr_jax.benchmarks.learner import _agents, filled_buffers
  from dmcr_jax.train import sac
  from dmcr_jax.train import step as train_step
  config = sac.SACConfig(batch_size=batch, compute_dtype=dtype)
  spec = train_step.StepSpec(agents=k, num_envs=1, warmup_steps=0, utd=1.0, sac=config,
                             agent_loop="vmap", low=(-1.0,) * action_size,
                             high=(1.0,) * action_size)
  obs_shape = (size, size, 3 * stack)
  learner = jax.eval_shape(lambda: train_step.init_learner(
      _agents(k, obs_shape, action_size, config),
      filled_buffers(k, 4 * batch, size, stack, action_size), jax.random.key(1), 0, spec))
  return train_step.learn_jit.lower(learner, pairs=1, spec=spec).as_text(dialect="hlo")


def markdown(results: list[tuple[int, dict]], peak_tflops: float, tbps: float) -> str:
  """One table: per K and category (`hlo_costs`' totals), GFLOP, GB and the
  roofline ms per agent-update, and which bound it is."""
  lines = []
  for k, totals in results:
    per = 2 * k  # updates in the pair, all agents
    for name, t in totals.items():
      if not t["ops"]:
        continue
      compute, memory = t["flops"] / (peak_tflops * 1e12), t["bytes"] / (tbps * 1e12)
      lines.append(dict(k=k, category=name, ops=t["ops"],
                        gflop=t["flops"] / per / 1e9, gb=t["bytes"] / per / 1e9,
                        ms=max(compute, memory) / per * 1e3,
                        bound="compute" if compute >= memory else "memory",
                        intensity=t["flops"] / t["bytes"] if t["bytes"] else float("inf")))
    flops = sum(t["flops"] for t in totals.values())
    nbytes = sum(t["bytes"] for t in totals.values())
    ms = sum(max(t["flops"] / (peak_tflops * 1e12), t["bytes"] / (tbps * 1e12))
             for t in totals.values()) / per * 1e3
    lines.append(dict(k=k, category="**all**",
                      ops=sum(t["ops"] for t in totals.values()), gflop=flops / per / 1e9,
                      gb=nbytes / per / 1e9, ms=ms, bound="", intensity=flops / nbytes))
  return R.table(lines, [
      ("K", "k"), ("category", "category"),
      ("ops per pair", "ops"), ("GFLOP per agent-update", lambda r: f"{r['gflop']:.2f}"),
      ("GB per agent-update", lambda r: f"{r['gb']:.3f}"),
      ("FLOP/byte", lambda r: f"{r['intensity']:.0f}"),
      ("roofline ms per agent-update", lambda r: f"{r['ms']:.3f}"), ("bound", "bound")])


def main(argv=None) -> None:
  """Command-line entry: the table, printed and written to --out."""
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--agents", default="1,8")
  p.add_argument("--dtype", default="bfloat16")
  p.add_argument("--impl", default="blocks", choices=("pixels", "blocks"),
                 help="the encoder's layout (default: the GPU's, blocks)")
  p.add_argument("--peak-tflops", type=float, default=989.0)
  p.add_argument("--tbps", type=float, default=4.8, help="memory bandwidth, TB/s")
  p.add_argument("--out", default=None, help="Markdown file (default: print only)")
  a = p.parse_args(argv)
  from dmcr_jax.train import layouts
  layouts.default_impl = lambda platform=None: a.impl  # the layout to count
  results = []
  for k in [int(x) for x in a.agents.split(",")]:
    results.append((k, hlo_costs(lowered_text(k, a.dtype))))
    print(f"K={k}: lowered", file=sys.stderr, flush=True)
  table = markdown(results, a.peak_tflops, a.tbps)
  print(table)
  if a.out:
    with open(a.out, "w") as f:
      f.write(f"`python -m dmcr_jax.benchmarks.learner_roofline "
              f"{' '.join(sys.argv[1:] if argv is None else argv)}` (module doc: the "
              f"counting rules), {a.dtype}, the {a.impl} layout, rates {a.peak_tflops:g} "
              f"TFLOP/s and {a.tbps:g} TB/s.\n\n{table}\n")


if __name__ == "__main__":
  main()
