"""The benchmarks' one row format: timing a call, writing its row, one table writer.

Every benchmark appends JSON lines to its ``--out`` file. A line holds the
benchmark's own fields (task, sizes, its own rates) and the suite's fields
(`FIELDS`), which `dmcr_jax.benchmarks.suite` reads as they are:

- variant: what tells the row's line in a plot apart ("fastest", "K=8 bfloat16 map");
- n: the size along the plot's x axis (envs, frames or images per call);
- throughput, unit: work per second and its unit ("physics steps/s");
- compile_s: compile (or start-up) seconds, apart from run_s, the seconds of one
  timed call;
- baseline, baseline_throughput: the baseline measured in the same run, if any;
- is_baseline: the row is that baseline's own measurement;
- device, platform: the device kind ("NVIDIA H100 80GB HBM3", "cpu") and the JAX
  backend (None where the benchmark does not use JAX);
- time_utc: when it ran (ISO 8601).

A row may also hold "headline": the text the suite's headline shows for it
(default: its throughput and unit). This module imports no JAX at import time: the
suite's own process must not take accelerator memory from its children.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import re
import statistics
import subprocess
import sys
import time
from typing import Callable, Sequence

BENCHMARKS = ("physics", "render", "env", "jax_render", "augment", "learner", "step_profile",
              "train")
"""The suite's benchmarks (a row's "benchmark" in its output), in the order it runs them."""

FIELDS = ("variant", "n", "throughput", "unit", "compile_s", "run_s", "baseline",
          "baseline_throughput", "is_baseline", "device", "platform", "time_utc")
"""The suite's fields of every row (module docstring)."""


def utc_now() -> str:
  """The current UTC time, ISO 8601 to the second."""
  return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def row(own: dict, variant: str, *, n: int | None, throughput: float | None, unit: str,
        compile_s: float | None = None, run_s: float | None = None,
        baseline: str | None = None, baseline_throughput: float | None = None,
        is_baseline: bool = False, headline: str | None = None) -> dict:
  """`own` (the benchmark's fields, "device" among them) with the suite's fields set.

  Args:
    own: the benchmark's fields; its "platform" and "time_utc" are kept if given
      (else None and now).
    variant, n, throughput, unit, compile_s, run_s, baseline, baseline_throughput,
      is_baseline: as in the module docstring (seconds; throughput per second).
    headline: the suite headline's text for the row, if not "throughput unit".
  """
  out = dict(own, variant=variant, n=None if n is None else int(n), throughput=throughput,
             unit=unit, compile_s=compile_s, run_s=run_s, baseline=baseline,
             baseline_throughput=baseline_throughput, is_baseline=bool(is_baseline))
  out.setdefault("platform", None)
  out.setdefault("time_utc", utc_now())
  if headline:
    out["headline"] = headline
  return out


def emit(r: dict, path: str | None) -> None:
  """Prints `r` as a JSON line and appends it to `path` (if given; folders made)."""
  print(json.dumps(r), flush=True)
  if path:
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path, "a") as f:
      f.write(json.dumps(r) + "\n")


def read(path: str) -> list[dict]:
  """The JSON objects of a JSONL file (blank and malformed lines skipped; [] if absent)."""
  if not os.path.exists(path):
    return []
  out = []
  with open(path) as f:
    for line in f:
      try:
        r = json.loads(line)
      except ValueError:
        continue
      if isinstance(r, dict):
        out.append(r)
  return out


GENERATED_MARKER = ("<!-- written by a dmcr_jax benchmark from the JSONL rows beside; "
                    "rewritten by its next run -->")


def print_and_write(rows: Sequence[dict], out: str | None,
                    markdown: Callable[[list[dict]], str]) -> None:
  """A benchmark's end: prints `markdown(rows)` and, with an `out` JSONL file, writes
  the table of all its rows (`write_markdown`)."""
  print(markdown(list(rows)))
  if out:
    write_markdown(out, markdown(read(out)))


def write_markdown(out: str, text: str) -> str:
  """Writes `text` beside the JSONL file `out` (same name, ".md"); returns that path.

  The file starts with `GENERATED_MARKER`. A file of that name without the marker
  (written by hand: notes, analysis) is left as it is, and the table goes to
  "<name>_table.md" instead (said on stderr).
  """
  stem = os.path.splitext(out)[0]
  path = stem + ".md"
  if os.path.exists(path):
    with open(path) as f:
      first = f.readline().rstrip("\n")
    if first != GENERATED_MARKER:
      path = stem + "_table.md"
      print(f"{stem}.md was not written by a benchmark; the table goes to {path}",
            file=sys.stderr)
  with open(path, "w") as f:
    f.write(f"{GENERATED_MARKER}\n{text}")
  return path


# Timing -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Timing:
  """A measured call: `compile_s` (its first call: compilation and one run), and the
  seconds of each timed call after it (`times`)."""
  compile_s: float
  times: tuple[float, ...]

  @property
  def run_s(self) -> float:
    """The median seconds of a timed call."""
    return statistics.median(self.times)

  def percentile(self, q: float) -> float:
    """The q-th percentile (0–100) of the timed calls' seconds, linearly interpolated."""
    xs = sorted(self.times)
    at = (len(xs) - 1) * q / 100.0
    lo = math.floor(at)
    return xs[lo] + (xs[min(lo + 1, len(xs) - 1)] - xs[lo]) * (at - lo)


def block(x):
  """`x` once every JAX array in it is computed (anything else as it is)."""
  import jax
  return jax.block_until_ready(x)


def time_calls(call: Callable[[], object], *, repeats: int = 3, seconds: float = 0.0,
               max_calls: int | None = None, warmup: int = 1) -> tuple[float, ...]:
  """Seconds of each timed ``call()``, its result blocked on.

  Args:
    call: the work; called with no arguments (a closure may carry state).
    repeats: timed calls at least …
    seconds: … and more until this many seconds have passed,
    max_calls: but never more than this many (None: no cap).
    warmup: untimed calls first.
  """
  for _ in range(warmup):
    block(call())
  times, start = [], time.perf_counter()
  while len(times) < max(1, repeats) or time.perf_counter() - start < seconds:
    if max_calls is not None and len(times) >= max_calls:
      break
    t0 = time.perf_counter()
    block(call())
    times.append(time.perf_counter() - t0)
  return tuple(times)


def measure(call: Callable[[], object], *, repeats: int = 3, seconds: float = 0.0,
            max_calls: int | None = None, warmup: int = 0) -> Timing:
  """The first ``call()`` timed apart (compile_s), then `time_calls` with the rest."""
  t0 = time.perf_counter()
  block(call())
  compile_s = time.perf_counter() - t0
  return Timing(compile_s, time_calls(call, repeats=repeats, seconds=seconds,
                                      max_calls=max_calls, warmup=warmup))


# Devices ----------------------------------------------------------------------------


def gpu_name() -> str | None:
  """The first NVIDIA GPU's name from nvidia-smi, or None (no JAX import)."""
  try:
    out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                         capture_output=True, text=True, timeout=10).stdout.strip()
  except (OSError, subprocess.SubprocessError):
    return None
  return out.splitlines()[0].strip() if out else None


def device_slug(name: str | None) -> str:
  """A short file-name tag for a device name: "h100", "a100", … or "cpu" for None."""
  if not name or name == "cpu":
    return "cpu"
  match = re.search(r"([A-Z]+\d{2,4})", name)
  return match.group(1).lower() if match else re.sub(r"\W+", "-", name.lower()).strip("-")


# Markdown ---------------------------------------------------------------------------


def num(x, digits: int = 0) -> str:
  """A number for a table: thousands separated, '–' when missing."""
  if x is None or (isinstance(x, float) and math.isnan(x)):
    return "–"
  if isinstance(x, (int, float)):
    if abs(x) >= 100 or digits == 0:
      return f"{x:,.0f}" if abs(x) >= 10 or x == 0 else f"{x:.2g}"
    return f"{x:,.{digits}f}"
  return str(x)


def secs(x) -> str:
  """Seconds for a table: 3 significant digits below 1, one decimal below 100."""
  if x is None:
    return "–"
  return f"{x:.3g}" if x < 1 else (f"{x:.1f}" if x < 100 else f"{x:,.0f}")


def fmt(x, spec: str) -> str:
  """`x` formatted with `spec` (e.g. ",.0f"), or '–' when None."""
  return "–" if x is None else format(x, spec)


_NUMERIC = re.compile(r"^(–|\**[-+]?\d[\d,.]*(e[-+]?\d+)?%?\**)$")


def table(rows: Sequence[dict], columns: Sequence[tuple[str, str | Callable[[dict], object]]]
          ) -> str:
  """A Markdown table: one line per row, one column per (header, key or function of
  the row); None cells show '–'; columns whose every cell is a number are right-aligned."""
  cells = [[r.get(get) if isinstance(get, str) else get(r) for _, get in columns] for r in rows]
  cells = [["–" if c is None else str(c) for c in line] for line in cells]
  right = [all(_NUMERIC.match(line[i]) for line in cells) if cells else False
           for i in range(len(columns))]
  lines = ["| " + " | ".join(h for h, _ in columns) + " |",
           "|" + "|".join("---:" if r else "---" for r in right) + "|"]
  lines += ["| " + " | ".join(line) + " |" for line in cells]
  return "\n".join(lines) + "\n"
