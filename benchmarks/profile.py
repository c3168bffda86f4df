"""Where a jitted call's device time goes: a JAX profiler trace summarised per kernel.

`profile_call(call, out_dir)` runs a (compiled, warmed-up) callable a few times
under `jax.profiler.trace` and `summarise(events)` reads the Perfetto trace that JAX
writes (`perfetto_trace.json.gz`, `load_trace`): the events of the device's streams
(processes named ``/device:GPU:…``), grouped by XLA op (the kernel event's
``hlo_op``), by kind of op, by kernel name or by the Python source of the op
(``--by source``: file, line and function of the op and its two callers, read from
the compiled module's stack-frame tables, `hlo_sources`), with calls, total and mean
time and share of the traced device time.
On a CPU-only machine there are no device processes; XLA's CPU worker threads
stand in (the rows are then host-side op events, coarse but enough for tests).

The command profiles the two workloads the open speed targets are about:

    python -m dmcr_jax.benchmarks.profile render --batch 1024 --chunk 1024 --out $OUT/prof
    python -m dmcr_jax.benchmarks.profile learner --dtype bfloat16 --out $OUT/prof
    python -m dmcr_jax.benchmarks.profile learner --agents 8 --agent-loop vmap --out $OUT/prof8

Each writes ``summary.md`` (the top `--top` rows) and ``summary.json`` into --out
beside the raw trace, and prints the table. ``--trace-dir`` puts the trace
elsewhere; ``--no-keep-trace`` deletes it once summarised, leaving only the two
summary files under --out. Why its own tool: GPU time is scarce
here, and a table of kernels is what decides the next optimisation; the trace
viewers (TensorBoard, Perfetto UI) are not on the GPU machine. XLA's CUDA command
buffers are turned off for the run (`--command-buffers` keeps them): with them a
trace shows each captured graph as one kernel and no op inside it.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import shutil
import sys
import tempfile
import time
from typing import Any, Callable, Sequence

from dmcr_jax.benchmarks import rows as R

HOST_THREAD_PREFIXES = ("tf_XLA",)
"""Thread-name prefixes of XLA's CPU worker threads (used when no device is traced)."""

HOST_WRAPPER_PREFIXES = ("ThunkExecutor", "ThreadpoolListener", "end: ")
"""Events on those threads that enclose or mark ops rather than being one."""


def load_trace(path: str) -> list[dict]:
  """The event list of a Perfetto / Chrome JSON trace (``.json`` or ``.json.gz``)."""
  opener = gzip.open if path.endswith(".gz") else open
  with opener(path, "rt") as f:
    data = json.load(f)
  return data["traceEvents"] if isinstance(data, dict) else data


def device_events(events: Sequence[dict]) -> tuple[list[dict], str]:
  """The complete ("X") events of the device streams, and what they are.

  Returns:
    (events, "device") when the trace has processes named ``/device:…``;
    otherwise the op events of XLA's CPU worker threads and "host threads".
  """
  procs = {e["pid"]: e["args"]["name"] for e in events
           if e.get("ph") == "M" and e.get("name") == "process_name"}
  threads = {(e["pid"], e.get("tid")): e["args"]["name"] for e in events
             if e.get("ph") == "M" and e.get("name") == "thread_name"}
  complete = [e for e in events if e.get("ph") == "X" and "dur" in e]
  device_pids = {pid for pid, name in procs.items() if name.startswith("/device:")}
  if device_pids:
    return [e for e in complete if e["pid"] in device_pids], "device"
  host = {key for key, name in threads.items() if name.startswith(HOST_THREAD_PREFIXES)}
  return [e for e in complete if (e["pid"], e.get("tid")) in host
          and not e["name"].startswith(HOST_WRAPPER_PREFIXES)], "host threads"


GROUPINGS = ("op", "category", "kernel", "source")
"""How `summarise` groups events (``--by``)."""


def _hlo_table(text: str, name: str) -> dict[int, str]:
  """One of the numbered tables a compiled HLO module's text ends with (FileNames,
  FunctionNames, FileLocations, StackFrames): {id: the rest of its line}."""
  match = re.search(rf"^{name}\n(.*?)(?:\n\n|\Z)", text, re.S | re.M)
  rows = {}
  for line in (match.group(1).splitlines() if match else []):
    head, _, rest = line.partition(" ")
    if head.isdigit():
      rows[int(head)] = rest.strip().strip('"')
  return rows


def hlo_sources(text: str, depth: int = 3) -> dict[str, str]:
  """Python source of each instruction of a compiled HLO module (`Compiled.as_text()`).

  Each instruction's metadata names a stack frame; frames chain to their callers
  (the text prints a frame's parent id plus one, 0 for none). The label holds the
  innermost `depth` frames, innermost first: ``"jax_render.py:92 _dot ← 115
  _sphere_t ← 166 intersect"`` (the file is named once, where it changes).

  Returns:
    {instruction name (as a trace's ``hlo_op``): label}; instructions without a
    stack frame are left out.
  """
  files, funcs = _hlo_table(text, "FileNames"), _hlo_table(text, "FunctionNames")
  locs = {i: dict(re.findall(r"(\w+)=(\d+)", v))
          for i, v in _hlo_table(text, "FileLocations").items()}
  frames = {i: dict(re.findall(r"(\w+)=(\d+)", v))
            for i, v in _hlo_table(text, "StackFrames").items()}

  def label(frame_id: int) -> str:
    parts, last_file, seen = [], None, set()
    while frame_id in frames and frame_id not in seen and len(parts) < depth:
      seen.add(frame_id)
      loc = locs.get(int(frames[frame_id].get("file_location_id", 0)), {})
      file = os.path.basename(files.get(int(loc.get("file_name_id", 0)), "?"))
      func = funcs.get(int(loc.get("function_name_id", 0)), "?").split(".")[-1]
      where = f"{file}:{loc.get('line', '?')}" if file != last_file else loc.get("line", "?")
      parts.append(f"{where} {func}")
      last_file = file
      frame_id = int(frames[frame_id].get("parent_frame_id", 0)) - 1
    return " ← ".join(parts)

  sources = {}
  for name, frame in re.findall(r"^\s*(?:ROOT )?%(\S+) = .*?stack_frame_id=(\d+)", text, re.M):
    sources[name] = label(int(frame))
  return sources


def summarise(events: Sequence[dict], by: str = "op", top: int = 30,
              sources: dict[str, str] | None = None) -> dict[str, Any]:
  """Per group, calls and time of the traced device events.

  Args:
    events: a trace's events (`load_trace`).
    by: "op" groups by the event's ``hlo_op`` argument (falling back to its name),
      "category" by that op name without its ".N" suffix ("fusion", "custom-call",
      …), "kernel" by the event's name, "source" by the Python source of the op
      (`sources`; ops it lacks are grouped as "<op> (no source)").
    top: rows kept, longest total first.
    sources: for "source", `hlo_sources` of the profiled computation.

  Returns:
    {"source": "device" | "host threads", "total_ms": all traced time,
     "rows": [{"name", "calls", "total_ms", "mean_us", "share"}], "groups": count}.
  """
  if by not in GROUPINGS:
    raise ValueError(f"by must be one of {', '.join(GROUPINGS)}, got {by!r}")
  picked, source = device_events(events)
  totals: dict[str, float] = collections.defaultdict(float)
  calls: dict[str, int] = collections.Counter()
  for e in picked:
    name = e["name"]
    if by in ("op", "category", "source"):
      name = (e.get("args") or {}).get("hlo_op", name)
    if by == "source":
      name = (sources or {}).get(name, f"{name} (no source)")
    if by == "category":
      name = re.sub(r"\.\d+$", "", name)
    totals[name] += e["dur"]
    calls[name] += 1
  total_us = sum(totals.values())
  rows = [dict(name=n, calls=calls[n], total_ms=t / 1e3, mean_us=t / calls[n],
               share=t / total_us if total_us else 0.0)
          for n, t in sorted(totals.items(), key=lambda kv: -kv[1])[:top]]
  return dict(source=source, total_ms=total_us / 1e3, rows=rows, groups=len(totals))


def markdown(summary: dict[str, Any], title: str = "") -> str:
  """The summary as a Markdown table."""
  lines = [f"{title}\n" if title else "",
           f"Traced time on the {summary['source']}: {summary['total_ms']:,.1f} ms in "
           f"{summary['groups']} groups (top {len(summary['rows'])} below).", "",
           R.table(summary["rows"], [
               ("op / kernel", lambda r: "`" + (r["name"] if len(r["name"]) <= 100
                                                else r["name"][:97] + "…") + "`"),
               ("calls", lambda r: f"{r['calls']:,}"),
               ("total ms", lambda r: f"{r['total_ms']:,.2f}"),
               ("mean µs", lambda r: f"{r['mean_us']:,.1f}"),
               ("share", lambda r: f"{r['share']:.1%}")])]
  return "\n".join(lines).lstrip("\n")


def profile_call(call: Callable[[], Any], out_dir: str, calls: int = 3) -> str:
  """Runs ``call()`` (compiled and warm) `calls` times under JAX's profiler.

  Returns:
    The path of the Perfetto trace written under `out_dir`.
  """
  import jax
  pattern = os.path.join(out_dir, "**", "perfetto_trace.json.gz")
  os.makedirs(out_dir, exist_ok=True)
  before = set(glob.glob(pattern, recursive=True))
  with jax.profiler.trace(out_dir, create_perfetto_trace=True):
    for _ in range(calls):
      jax.block_until_ready(call())
  new = set(glob.glob(pattern, recursive=True)) - before
  if not new:
    raise RuntimeError(f"the profiler wrote no perfetto_trace.json.gz under {out_dir}")
  return max(new, key=os.path.getmtime)


def render_workload(task: str, batch: int, chunk: int, size: int) -> Callable[[], Any]:
  """``call()`` rendering `batch` envs of `task` (`dmcr_jax.benchmarks.jax_render`'s render mode)."""
  import functools
  import jax
  from dmcr_jax.benchmarks.jax_render import inputs
  from dmcr_jax.visuals import jax_render as JR
  scene, bp, looks = inputs(task, batch)
  fn = jax.jit(functools.partial(JR.render_batch, scene, chunk=chunk or None,
                                 height=size, width=size))
  call = lambda: fn(bp, looks)
  call.hlo_text = lambda: fn.lower(bp, looks).compile().as_text()
  return call


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("workload", choices=("render", "learner"))
  p.add_argument("--task", default="walker-walk", help="render: the task")
  p.add_argument("--batch", type=int, default=None,
                 help="render: envs (1,024); learner: batch size (256)")
  p.add_argument("--chunk", type=int, default=0, help="render: envs per chunk (0: all)")
  p.add_argument("--size", type=int, default=84, help="image side")
  p.add_argument("--dtype", default="bfloat16", help="learner: compute dtype")
  p.add_argument("--pairs", type=int, default=5, help="learner: update pairs per call")
  p.add_argument("--agents", type=int, default=1, help="learner: agents K")
  p.add_argument("--agent-loop", default="vmap",
                 help="learner: how the K agents are batched (vmap, map)")
  p.add_argument("--calls", type=int, default=3, help="profiled calls")
  p.add_argument("--by", default="op", choices=GROUPINGS)
  p.add_argument("--top", type=int, default=30)
  p.add_argument("--command-buffers", action="store_true",
                 help="keep XLA's CUDA command buffers (graphs) on; off by default, as "
                      "a trace then shows each graph as one kernel (command_buffer_N)")
  p.add_argument("--out", required=True, help="folder for summary.{md,json} (and the trace)")
  p.add_argument("--trace-dir", default=None,
                 help="folder for the profiler's trace (default: --out)")
  p.add_argument("--keep-trace", action=argparse.BooleanOptionalAction, default=True,
                 help="keep the trace; --no-keep-trace writes it to a temporary folder "
                      "and deletes it after summarising")
  argv = sys.argv[1:] if argv is None else list(argv)
  args = p.parse_args(argv)
  for name in ("batch", "chunk", "size", "pairs", "agents", "calls", "top"):
    value = getattr(args, name)
    if value is not None and (value < 0 if name == "chunk" else value < 1):
      p.error(f"--{name} must be {'≥ 0' if name == 'chunk' else 'positive'}, got {value}")
  if args.trace_dir and not args.keep_trace:
    p.error("--trace-dir keeps the trace there; leave it out with --no-keep-trace")
  flags = os.environ.get("XLA_FLAGS", "")
  if not args.command_buffers and "xla_gpu_enable_command_buffer" not in flags:
    # Set before JAX starts its backend, so that the trace shows each kernel by its
    # op's name rather than a captured graph as one command_buffer_N kernel.
    os.environ["XLA_FLAGS"] = (flags + " --xla_gpu_enable_command_buffer=").strip()
  import jax
  if args.workload == "render":
    call = render_workload(args.task, args.batch or 1024, args.chunk, args.size)
    what = f"render_batch, {args.task}, N = {args.batch or 1024}, {args.size}×{args.size}"
  else:
    from dmcr_jax.benchmarks.learner import scanned_workload
    from dmcr_jax.train.config import AGENT_LOOPS
    if args.agent_loop not in AGENT_LOOPS:
      p.error(f"--agent-loop must be one of {', '.join(AGENT_LOOPS)}, got {args.agent_loop!r}")
    call, _, _ = scanned_workload(args.agents, args.dtype, args.agent_loop,
                                  batch=args.batch or 256, pairs=args.pairs, size=args.size)
    what = (f"SAC+AUG, K = {args.agents} ({args.agent_loop}), {args.pairs} update pairs per "
            f"call, batch {args.batch or 256}, {args.size}×{args.size}×9, {args.dtype}")
  t0 = time.perf_counter()
  jax.block_until_ready(call())  # compiles
  compile_s = time.perf_counter() - t0
  jax.block_until_ready(call())  # warm
  os.makedirs(args.out, exist_ok=True)
  trace_dir = (args.trace_dir or args.out) if args.keep_trace else tempfile.mkdtemp()
  try:
    trace = profile_call(call, trace_dir, args.calls)
    events = load_trace(trace)
  finally:
    if not args.keep_trace:
      shutil.rmtree(trace_dir, ignore_errors=True)
  sources = hlo_sources(call.hlo_text()) if args.by == "source" else None
  summary = summarise(events, by=args.by, top=args.top, sources=sources)
  device = getattr(jax.devices()[0], "device_kind", jax.default_backend())
  kept = None
  if args.keep_trace:
    kept = trace if args.trace_dir else os.path.relpath(trace, args.out)
  summary.update(workload=what, device=device, calls=args.calls, compile_s=compile_s,
                 trace=kept,
                 time_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
  table = markdown(summary, f"{what} on {device}, {args.calls} calls "
                            f"(`python -m dmcr_jax.benchmarks.profile {' '.join(argv)}`)")
  with open(os.path.join(args.out, "summary.json"), "w") as f:
    json.dump(summary, f, indent=1)
  with open(os.path.join(args.out, "summary.md"), "w") as f:
    f.write(table)
  print(table)


if __name__ == "__main__":
  main()
