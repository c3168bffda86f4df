"""`python -m benchmarks`: every benchmark in one process tree, one JSONL, one summary.

The suite runs each benchmark module of this package (`physics`, `render`, `env`,
`augment`, `learner`, `step_profile`, `training`) as a child process, one after the
other (they would otherwise compete for the cores and the accelerator), each with
a wall-clock limit. A child that fails or runs out of time is recorded and the
others still run. Every child writes its own JSON lines (`<out>/raw/<job>.jsonl`;
its output goes to `<out>/logs/<job>.log`); the suite then normalises them into
one schema (`normalise`) and writes:

- `<out>/benchmarks.jsonl` — one row per measurement: benchmark, variant, device,
  batch and the other sizes, compile_s, run_s (per timed call), throughput and
  its unit, and, where the benchmark measures a baseline in the same run, the
  baseline's name, throughput and the ratio; baselines are rows of their own
  (``is_baseline``) too;
- `<out>/summary.md` — a headline table (physics steps/s, frames/s, agent-steps/s
  with pixels, updates/s, end-to-end training time, the time of one agent step),
  the status of every job, and one table per benchmark;
- `<out>/throughput.png` — throughput against batch size, log-log, one panel per
  benchmark, one line per variant, baselines dashed;
- `<out>/runs.json` — every job's command, status, exit code and wall time.

Modes: ``--quick`` uses tiny sizes and cheap tasks (a plumbing check that also
gives rough numbers; a few minutes on a 2-core CPU); the default, full mode uses
the sizes of the project's targets (walker-walk physics up to 8,192 envs, render
batches up to 1,024, env N ∈ {1, 16, 256, 1,024}, learner batch 256 for one and
eight agents, the step profile at N = 1,024, cartpole-balance trained end to end).
``--only`` picks benchmarks; runs into an existing ``--out`` folder replace those
benchmarks' jobs and keep the others, so a full sweep can be run in parts (e.g.
one device call per benchmark) and summarised as one.

    python -m benchmarks --quick --out /tmp/suite_quick
    python -m benchmarks --only physics,render --out benchmarks/results/suite-h100-2026-11-24
    python -m benchmarks --dry-run            # print the commands of the plan
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Iterable, Sequence

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
"""The repository root: children run there, so `python -m benchmarks.x` resolves."""

BENCHMARKS = ("physics", "render", "env", "jax_render", "augment", "learner", "step_profile",
              "train")
"""What ``--only`` accepts, in the order the suite runs them."""

MODES = ("quick", "full")

DEFAULT_TIMEOUT_S = {"quick": 240.0, "full": 1200.0}
"""Per-job wall-clock limit in seconds unless ``--timeout`` is given."""

OUT_PLACEHOLDER = "{out}"
"""In a job's argv, replaced by the path of the job's raw JSONL file."""

CPUS_PLACEHOLDER = "{cpus}"
"""In a job's argv, replaced by the number of cores of the machine."""

# (job suffix, module, arguments) per benchmark and mode. Quick: tiny sizes, the
# cheapest task to compile (pendulum: 4–5 s per physics compilation on 2 cores;
# cartpole and walker 10–14 s, results/physics_cpu.md) and 32×32 images for the
# learner; full: the sizes of the project's targets.
_PLANS: dict[str, dict[str, list[tuple[str, str, tuple[str, ...]]]]] = {
    "quick": {
        "physics": [("", "benchmarks.physics", (
            "--tasks", "pendulum-swingup", "--sizes", "1,16", "--steps", "2",
            "--repeats", "2"))],
        "render": [("", "benchmarks.render", (
            "--batches", "8,32", "--workers", "2", "--qualities", "fastest",
            "--repeats", "2", "--baseline-frames", "20"))],
        "env": [("", "benchmarks.env", (
            "--task", "pendulum-swingup", "--sizes", "1,4", "--qualities", "fastest",
            "--workers", "2", "--seconds", "0.5", "--original-steps", "20"))],
        "jax_render": [("", "benchmarks.jax_render", (
            "--task", "pendulum-swingup", "--size", "32", "--batches", "4,16",
            "--repeats", "2")),
                       ("-env", "benchmarks.jax_render", (
            "--mode", "env", "--task", "pendulum-swingup", "--size", "32", "--batches",
            "4", "--repeats", "2", "--steps", "3", "--scan-steps", "3"))],
        "augment": [("", "benchmarks.augment", (
            "--batch", "16", "--names", "none,drq,cj+drq", "--min-time", "0.1",
            "--min-reps", "3", "--max-reps", "20"))],
        "learner": [("", "benchmarks.learner", (
            "--agents", "1", "--dtypes", "float32", "--batch", "8", "--size", "32",
            "--pairs", "1", "--capacity", "256", "--seconds", "0.2"))],
        "step_profile": [("", "benchmarks.step_profile", (
            "--task", "pendulum-swingup", "--sizes", "4", "--quality", "fastest",
            "--workers", "2", "--image-size", "32", "--steps", "5", "--batch", "8",
            "--capacity", "256", "--pairs", "1"))],
        "train": [("", "benchmarks.training", (
            "--task", "pendulum-swingup", "--action-repeat", "8", "--steps", "130",
            "--num-envs", "1", "--warmup-steps", "100", "--batch-size", "8",
            "--image-size", "32", "--buffer-capacity", "1000", "--dtype", "float32",
            "--quality", "fastest", "--workers", "2", "--log-every", "10"))],
    },
    "full": {
        "physics": [("", "benchmarks.physics", (
            "--tasks", "walker-walk", "--sizes", "1,64,1024,8192", "--steps", "20",
            "--repeats", "5", "--parallel-compiles", "4"))],
        "render": [("", "benchmarks.render", (
            "--batches", "16,64,256,1024", "--workers", CPUS_PLACEHOLDER,
            "--qualities", "exact,fast,fastest", "--repeats", "3",
            "--baseline-frames", "300"))],
        # Largest first: a job cut at its time limit keeps the rows of the target size.
        "env": [("-fastest", "benchmarks.env", (
            "--sizes", "1024,256,16,1", "--qualities", "fastest", "--seconds", "3")),
                ("-exact", "benchmarks.env", (
                    "--sizes", "1024,256,16,1", "--qualities", "exact", "--seconds", "3",
                    "--original-steps", "50")),
                # The settings that meet the 10,000 agent-steps/s target at N = 1,024:
                # line search capped at 4, pool observations as shared-memory views,
                # and the JAX renderer beside the pool.
                ("-target", "benchmarks.env", (
                    "--sizes", "1024", "--renderers", "pool,jax", "--qualities", "fastest",
                    "--ls-iterations", "4", "--no-copy", "--seconds", "3",
                    "--original-steps", "50"))],
        "jax_render": [("", "benchmarks.jax_render", (
            "--batches", "1024,4096,16384", "--chunk", "256")),
                       ("-env", "benchmarks.jax_render", (
            # ~2 min of compilation per size: 4,096 envs only, to fit one device call
            # beside env-target (whose JAX row is the env at 1,024).
            "--mode", "env", "--batches", "4096", "--chunk", "256",
            "--repeats", "2", "--steps", "5", "--scan-steps", "10"))],
        "augment": [("", "benchmarks.augment", ("--batch", "256")),
                    ("-b64", "benchmarks.augment", ("--batch", "64", "--names", "none,drq")),
                    ("-b1024", "benchmarks.augment", (
                        "--batch", "1024", "--names", "none,drq"))],
        "learner": [("", "benchmarks.learner", (
            "--agents", "1,8", "--dtypes", "float32,bfloat16", "--loops", "map,vmap",
            "--batch", "256", "--pairs", "25", "--seconds", "3")),
                    # CURL and SAC+AE at their own batch sizes (256, 128).
                    ("-algos", "benchmarks.learner", (
            "--algos", "curl,sac_ae", "--agents", "1", "--dtypes", "float32,bfloat16",
            "--pairs", "25", "--seconds", "3", "--no-baseline"))],
        "step_profile": [("", "benchmarks.step_profile", (
            "--task", "walker-walk", "--sizes", "1024", "--quality", "fastest",
            "--steps", "20", "--batch", "256", "--capacity", "100000"))],
        # Issue 26's measure: end to end against the learner alone, both renderers.
        "train": [(suffix, "benchmarks.training", (
            "--task", "ball_in_cup-catch", "--steps", "12000", "--num-envs", "16",
            "--dtype", "bfloat16", "--quality", "exact", "--log-every", "500") + extra)
            for suffix, extra in (("", ()), ("-jax", ("--renderer", "jax")))],
    },
}


@dataclasses.dataclass(frozen=True)
class Job:
  """One child process of the suite.

  Attributes:
    name: unique in a run; the stem of its raw JSONL and log files ("env-exact").
    benchmark: which of `BENCHMARKS` its rows belong to (picks the normaliser).
    argv: the command; `OUT_PLACEHOLDER` in an item becomes the raw JSONL path.
    timeout_s: its wall-clock limit in seconds.
  """
  name: str
  benchmark: str
  argv: tuple[str, ...]
  timeout_s: float


@dataclasses.dataclass
class JobResult:
  """What became of a job.

  Attributes:
    name, benchmark: as the job's.
    argv: the command as run (placeholders filled in).
    status: "ok", "failed" (non-zero exit), "timeout", "no rows" (exit 0 but
      nothing written) or "interrupted" (Ctrl-C).
    returncode: the exit code (None when killed at the time limit).
    wall_s: seconds the child ran.
    rows: JSON lines it wrote.
    tail: its last lines of output (what to look at when it failed).
    time_utc: when it started.
  """
  name: str
  benchmark: str
  argv: list[str]
  status: str
  returncode: int | None
  wall_s: float
  rows: int
  tail: list[str]
  time_utc: str


# Planning ---------------------------------------------------------------------------


def job_names(mode: str) -> tuple[str, ...]:
  """The names of a mode's jobs ("physics", "env-fastest", "augment-b64", …)."""
  return tuple(bench + suffix for bench in BENCHMARKS for suffix, *_ in _PLANS[mode][bench])


def parse_only(text: str | None, mode: str = "full") -> tuple[str, ...]:
  """What ``--only`` selects: benchmark names ("physics,env") and/or job names of
  `mode` ("env-exact"); None or "all": every benchmark.

  Returns:
    The names given, benchmarks first in the order of `BENCHMARKS`, then jobs.

  Raises:
    ValueError: an unknown name (the message names the valid choices).
  """
  if text is None or text.strip() == "all":
    return BENCHMARKS
  names = [t.strip() for t in text.split(",") if t.strip()]
  jobs = [j for j in job_names(mode) if j not in BENCHMARKS]
  unknown = [n for n in names if n not in BENCHMARKS and n not in jobs]
  if unknown or not names:
    raise ValueError(
        f"unknown benchmark(s) {', '.join(map(repr, unknown)) or '(none given)'} in --only; "
        f"choose from: {', '.join(BENCHMARKS)} (or all)"
        + (f", or single jobs of {mode} mode: {', '.join(jobs)}" if jobs else ""))
  return (tuple(b for b in BENCHMARKS if b in names)
          + tuple(j for j in jobs if j in names))


def plan(mode: str, only: Sequence[str] = BENCHMARKS, timeout_s: float | None = None,
         cpus: int | None = None, python: str = sys.executable) -> list[Job]:
  """The jobs of a suite run.

  Args:
    mode: "quick" or "full".
    only: the benchmarks (all their jobs) and jobs to run (see `parse_only`).
    timeout_s: per-job limit (None: `DEFAULT_TIMEOUT_S[mode]`).
    cpus: the cores to give render workers in full mode (None: this machine's).
    python: the interpreter of the children.

  Returns:
    One `Job` per benchmark invocation, in the order of `BENCHMARKS`.

  Raises:
    ValueError: an unknown mode, benchmark or job.
  """
  if mode not in MODES:
    raise ValueError(f"unknown mode {mode!r}; choose from: {', '.join(MODES)}")
  parse_only(",".join(only), mode)
  limit = DEFAULT_TIMEOUT_S[mode] if timeout_s is None else float(timeout_s)
  cores = str(cpus or os.cpu_count() or 1)
  jobs = []
  for bench in BENCHMARKS:
    for suffix, module, args in _PLANS[mode][bench]:
      if bench not in only and bench + suffix not in only:
        continue
      args = tuple(a.replace(CPUS_PLACEHOLDER, cores) for a in args)
      jobs.append(Job(bench + suffix, bench,
                      (python, "-m", module, *args, "--out", OUT_PLACEHOLDER), limit))
  return jobs


# Running ----------------------------------------------------------------------------


def read_jsonl(path: str) -> list[dict]:
  """The JSON objects of a JSONL file (blank and malformed lines skipped; [] if absent)."""
  if not os.path.exists(path):
    return []
  rows = []
  with open(path) as f:
    for line in f:
      try:
        row = json.loads(line)
      except ValueError:
        continue
      if isinstance(row, dict):
        rows.append(row)
  return rows


def _utc_now() -> str:
  return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _kill_group(proc: subprocess.Popen, grace_s: float = 10.0) -> None:
  """Stops the child's process group (the child leads one): SIGTERM, up to `grace_s`
  for the child to exit, then SIGKILL for whatever of the group is left."""
  try:
    os.killpg(proc.pid, signal.SIGTERM)
  except ProcessLookupError:
    return
  try:
    proc.wait(timeout=grace_s)
  except subprocess.TimeoutExpired:
    pass
  try:
    os.killpg(proc.pid, signal.SIGKILL)
  except ProcessLookupError:
    pass
  proc.wait()


def run_job(job: Job, out_dir: str, on_line: Callable[[str], None] | None = None,
            tail_lines: int = 20) -> JobResult:
  """Runs one job as a child process in its own process group, within its limit.

  Its raw JSONL (`<out_dir>/raw/<name>.jsonl`) is removed first, so the rows are
  this run's; its output goes to `<out_dir>/logs/<name>.log`. At the time limit
  the whole group (the child and, e.g., its render workers) gets SIGTERM, then
  SIGKILL; rows it wrote before are kept.

  Args:
    job: the job.
    out_dir: the suite's output folder.
    on_line: called with every line the child prints (e.g. for progress).
    tail_lines: how many last lines of output the result keeps.

  Returns:
    Its `JobResult`. A Ctrl-C kills the child and is re-raised.
  """
  raw, log = raw_path(out_dir, job.name), os.path.join(out_dir, "logs", job.name + ".log")
  os.makedirs(os.path.dirname(raw), exist_ok=True)
  os.makedirs(os.path.dirname(log), exist_ok=True)
  if os.path.exists(raw):
    os.remove(raw)
  argv = [a.replace(OUT_PLACEHOLDER, raw) for a in job.argv]
  env = dict(os.environ, PYTHONUNBUFFERED="1")
  started, t0 = _utc_now(), time.perf_counter()
  tail: list[str] = []
  status, rc = None, None
  with open(log, "w") as log_file:
    log_file.write(f"$ {shlex.join(argv)}\n")
    log_file.flush()
    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, errors="replace",
                            start_new_session=True)

    def pump():
      for line in proc.stdout:
        try:
          log_file.write(line)
          log_file.flush()
        except ValueError:  # closed: a straggler of the group still printing
          return
        line = line.rstrip("\n").split("\r")[-1]
        tail.append(line)
        del tail[:-tail_lines]
        if on_line is not None and line.strip():
          on_line(line)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
      rc = proc.wait(timeout=job.timeout_s)
      _kill_group(proc, grace_s=5.0)  # what it left behind (e.g. orphaned workers)
    except subprocess.TimeoutExpired:
      status = "timeout"
      _kill_group(proc)
    except KeyboardInterrupt:
      _kill_group(proc, grace_s=2.0)
      raise
    reader.join(timeout=10.0)
  rows = len(read_jsonl(raw))
  if status is None:
    status = "failed" if rc != 0 else ("ok" if rows else "no rows")
  return JobResult(job.name, job.benchmark, argv, status, rc,
                   round(time.perf_counter() - t0, 2), rows, list(tail), started)


def raw_path(out_dir: str, job_name: str) -> str:
  """Where a job's child writes its rows."""
  return os.path.join(os.path.abspath(out_dir), "raw", job_name + ".jsonl")


# Normalising ------------------------------------------------------------------------

ROW_KEYS = ("benchmark", "variant", "device", "platform", "batch", "sizes", "compile_s",
            "run_s", "throughput", "unit", "baseline", "baseline_throughput", "ratio",
            "is_baseline", "extra", "time_utc")
"""The keys of every normalised row (plus "job" and "mode", added by the suite)."""


def make_row(benchmark: str, variant: str, *, device: str, batch: int | None,
             throughput: float | None, unit: str, compile_s: float | None = None,
             run_s: float | None = None, baseline: str | None = None,
             baseline_throughput: float | None = None, ratio: float | None = None,
             is_baseline: bool = False, sizes: dict | None = None, extra: dict | None = None,
             platform: str | None = None, time_utc: str | None = None) -> dict:
  """One normalised row (keys `ROW_KEYS`); the ratio is computed when not given.

  Args:
    benchmark: one of `BENCHMARKS`.
    variant: what distinguishes the row's line in a plot ("fastest", "K=1 bfloat16").
    device: the device kind ("NVIDIA H100 80GB HBM3", "cpu").
    batch: the size along the plot's x axis (envs, frames or images per call).
    throughput: work per second, in `unit`.
    unit: e.g. "physics steps/s".
    compile_s: compile (or start-up) time in seconds, apart from the run time.
    run_s: seconds of one timed call (or of the whole run, for training).
    baseline: the name of the baseline measured in the same run, if any.
    baseline_throughput: its throughput in `unit`.
    ratio: throughput / baseline_throughput (computed when None and both known).
    is_baseline: the row IS a baseline measurement.
    sizes: the other sizes and settings (task, workers, dtype, …).
    extra: benchmark-specific numbers (time splits, returns, …).
    platform: the JAX backend, if known.
    time_utc: when the benchmark ran, if known.
  """
  if ratio is None and throughput and baseline_throughput:
    ratio = throughput / baseline_throughput
  return dict(benchmark=benchmark, variant=variant, device=device, platform=platform,
              batch=None if batch is None else int(batch), sizes=dict(sizes or {}),
              compile_s=compile_s, run_s=run_s, throughput=throughput, unit=unit,
              baseline=baseline, baseline_throughput=baseline_throughput, ratio=ratio,
              is_baseline=bool(is_baseline), extra=dict(extra or {}), time_utc=time_utc)


def _device(row: dict) -> str:
  """The row's device kind; `render`'s "none" (no NVIDIA GPU) is the CPU."""
  device = row.get("device") or row.get("device_kind") or "unknown"
  return "cpu" if device == "none" else str(device)


def _common(row: dict) -> dict:
  return dict(device=_device(row), platform=row.get("platform"),
              time_utc=row.get("time_utc"))


def _norm_physics(rows: list[dict]) -> list[dict]:
  """`benchmarks.physics`: Task.step vs bare MJX (one row each per task and N)."""
  out = []
  for r in rows:
    sizes = dict(task=r["task"], num_envs=r["num_envs"], control_steps=r.get("control_steps"),
                 n_sub_steps=r.get("n_sub_steps"), solver_iterations=r.get("solver_iterations"),
                 ls_iterations=r.get("ls_iterations"))
    bare = r.get("bare_physics_steps_per_s")
    name = f"{r['task']} bare MJX"
    out.append(make_row("physics", r["task"], batch=r["num_envs"],
                        throughput=r["physics_steps_per_s"], unit="physics steps/s",
                        compile_s=r.get("compile_s"), run_s=r.get("run_s"),
                        baseline=name if bare else None, baseline_throughput=bare,
                        sizes=sizes, **_common(r)))
    if bare:
      out.append(make_row("physics", name, batch=r["num_envs"], throughput=bare,
                          unit="physics steps/s", compile_s=r.get("bare_compile_s"),
                          run_s=r.get("bare_run_s"), is_baseline=True, sizes=sizes,
                          **_common(r)))
  return out


def _norm_render(rows: list[dict]) -> list[dict]:
  """`benchmarks.render`: pool rows; the naive loop (one number per run) as a baseline row."""
  out, seen = [], set()
  for r in rows:
    if r.get("kind") == "baseline" or "frames_per_s" not in r:
      continue
    base = r.get("baseline_fps")
    sizes = dict(task=r.get("task"), image_size=r.get("size"), workers=r.get("workers"),
                 quality=r.get("quality"), gl=r.get("gl"), vary=r.get("vary"))
    out.append(make_row("render", f"{r['quality']}, {r['workers']} workers", batch=r["batch"],
                        throughput=r["frames_per_s"], unit="frames/s",
                        compile_s=r.get("start_s"), run_s=r.get("run_s"),
                        baseline="naive mujoco.Renderer loop" if base else None,
                        baseline_throughput=base, ratio=r.get("speedup"), sizes=sizes,
                        extra=dict(reference_equal=r.get("reference_equal"),
                                   compile_is="pool start-up"), **_common(r)))
    if base and base not in seen:
      seen.add(base)
      out.append(make_row("render", "naive mujoco.Renderer loop", batch=1, throughput=base,
                          unit="frames/s", run_s=1.0 / base, is_baseline=True,
                          sizes=dict(task=r.get("task"), image_size=r.get("size")),
                          **_common(r)))
  return out


def _env_variant(r: dict) -> str:
  variant = r["quality"]
  if r.get("renderer") == "jax" and r.get("obs_on_device"):
    variant += ", obs on device"
  if r.get("copy_obs") is False:
    variant += ", no copy"
  if r.get("ls_iterations") not in (None, "default"):
    variant += f", line search {r['ls_iterations']}"
  return variant


def _norm_env(rows: list[dict]) -> list[dict]:
  """`benchmarks.env`: `dmcr_jax.make` rows with their time split; the original pipeline."""
  out = []
  for r in rows:
    if r.get("kind") == "original":
      out.append(make_row("env", "original DMCR pipeline", batch=1,
                          throughput=r["agent_steps_per_s"], unit="agent-steps/s",
                          run_s=r["step_ms"] / 1e3, is_baseline=True,
                          sizes=dict(task=r.get("task"), frame_skip=r.get("frame_skip"),
                                     image_size=r.get("image_size")),
                          extra=dict(rebuild_ms=r.get("rebuild_ms"),
                                     without_rebuilds=r.get("agent_steps_per_s_no_rebuild")),
                          **_common(r)))
    elif r.get("kind") == "env":
      parts = {k[:-3]: r[k] for k in ("physics_ms", "transfer_ms", "render_ms", "copy_ms",
                                       "stack_ms", "other_ms") if k in r}
      start, warm = r.get("start_s"), r.get("warmup_s")
      out.append(make_row(
          "env", _env_variant(r), batch=r["num_envs"], throughput=r["agent_steps_per_s"],
          unit="agent-steps/s", compile_s=None if warm is None else warm - (start or 0.0),
          run_s=r["step_ms"] / 1e3, baseline="original DMCR pipeline",
          baseline_throughput=r.get("original_agent_steps_per_s"), ratio=r.get("speedup"),
          sizes=dict(task=r.get("task"), num_envs=r["num_envs"], workers=r.get("workers"),
                     quality=r["quality"], frame_skip=r.get("frame_skip"),
                     image_size=r.get("image_size"), copy_obs=r.get("copy_obs"),
                     ls_iterations=r.get("ls_iterations")),
          extra=dict(parts_ms=parts, start_s=start,
                     compile_is="reset + first steps after start-up"), **_common(r)))
  return out


def _norm_augment(rows: list[dict]) -> list[dict]:
  """`benchmarks.augment`: images/s of each augmentation (no baseline)."""
  out = []
  for r in rows:
    run_s = r["median_ms"] / 1e3
    out.append(make_row("augment", r["name"], batch=r["batch"], throughput=r["batch"] / run_s,
                        unit="images/s", compile_s=r.get("compile_s"), run_s=run_s,
                        sizes=dict(shape=r.get("shape")),
                        extra=dict(pair_median_ms=r.get("pair_median_ms"),
                                   p10_ms=r.get("p10_ms"), p90_ms=r.get("p90_ms")),
                        **_common(r)))
  return out


def _on_devices(r: dict) -> str:
  """A variant's suffix for a row sharded over several devices ("" for one)."""
  n = r.get("devices") or 1
  return f" on {n} devices" if n > 1 else ""


def _norm_learner(rows: list[dict]) -> list[dict]:
  """`benchmarks.learner`: agent-updates/s; the python loop is the baseline."""
  out, base = [], None
  for r in rows:
    algo = r.get("algo", "sac_aug")
    sizes = dict(algo=algo, agents=r["agents"], dtype=r["dtype"], agent_loop=r["agent_loop"],
                 batch=r["batch"], updates_per_call=2 * r["pairs_per_call"] or 1,
                 image_size=r.get("size"), stack=r.get("stack"))
    extra = dict(updates_per_s_per_agent=r.get("updates_per_s_per_agent"),
                 ms_per_call=r.get("ms_per_call"))
    if r["kind"] == "python_loop":
      base = r["updates_per_s_per_agent"]
      out.append(make_row("learner", "python loop (one dispatch per update)", batch=r["batch"],
                          throughput=base, unit="agent-updates/s",
                          compile_s=r.get("compile_s"), run_s=r["ms_per_call"] / 1e3,
                          is_baseline=True, sizes=sizes, extra=extra, **_common(r)))
      continue
    variant = ("" if algo == "sac_aug" else f"{algo} ") + f"K={r['agents']} {r['dtype']}" + (
        f" {r['agent_loop']}" if r["agents"] > 1 else "") + _on_devices(r)
    out.append(make_row("learner", variant, batch=r["batch"],
                        throughput=r["agent_updates_per_s"], unit="agent-updates/s",
                        compile_s=r.get("compile_s"), run_s=r["ms_per_call"] / 1e3,
                        baseline="python loop (one dispatch per update)" if base else None,
                        baseline_throughput=base, ratio=r.get("x_baseline"), sizes=sizes,
                        extra=extra, **_common(r)))
  return out


def _norm_step_profile(rows: list[dict]) -> list[dict]:
  """`benchmarks.step_profile`: one row per N, the parts of an agent step in `extra`."""
  out = []
  for r in rows:
    out.append(make_row(
        "step_profile", f"{r['task']} {r['quality']}", batch=r["num_envs"],
        throughput=r["train_agent_steps_per_s"], unit="agent-steps/s with updates",
        compile_s=r.get("compile_s"), run_s=r["total_ms"] / 1e3,
        sizes=dict(task=r["task"], num_envs=r["num_envs"], quality=r["quality"],
                   workers=r.get("workers"), frame_skip=r.get("frame_skip"),
                   batch=r.get("batch"), utd=r.get("utd"), dtype=r.get("dtype")),
        extra=dict(parts_ms=r["parts_ms"], shares=r.get("shares"),
                   per_update_ms=r.get("per_update_ms"),
                   updates_per_agent_step=r.get("updates_per_agent_step"),
                   env_agent_steps_per_s=r.get("env_agent_steps_per_s"),
                   collect_agent_steps_per_s=r.get("collect_agent_steps_per_s"),
                   stack_one_process_ms=r.get("stack_one_process_ms")),
        **_common(r)))
  return out


def _norm_train(rows: list[dict]) -> list[dict]:
  """`benchmarks.training`: one end-to-end run; transitions/s and the wall time."""
  out = []
  for r in rows:
    out.append(make_row(
        "train",
        f"{r['task']} {r.get('renderer', '')} {r.get('dtype', '')}".strip() + _on_devices(r),
        batch=r.get("num_envs"), throughput=r.get("transitions_per_s"), unit="transitions/s",
        compile_s=None, run_s=r.get("wall_s"),
        sizes=dict(task=r["task"], steps=r.get("steps"), num_envs=r.get("num_envs"),
                   agents=r.get("agents"), quality=r.get("quality"), dtype=r.get("dtype"),
                   batch=r.get("batch_size")),
        extra=dict(steady_transitions_per_s=r.get("steady_transitions_per_s"),
                   learner_updates_per_s=r.get("learner_updates_per_s"),
                   ratio=r.get("ratio"), renderer=r.get("renderer"),
                   final_return=r.get("final_return"), threshold=r.get("threshold"),
                   step_at_threshold=r.get("step_at_threshold"),
                   time_to_threshold_s=r.get("time_to_threshold_s"),
                   process_s=r.get("process_s"), run_dir=r.get("run_dir")),
        **_common(r)))
  return out


def _norm_jax_render(rows: list[dict]) -> list[dict]:
  """`benchmarks.jax_render`: ray-cast frames/s, and the JAX env's agent-steps/s
  (stepped by `env.step` and scanned on the device)."""
  out = []
  for r in rows:
    look = ", ".join(n for n, on in (("shadows", r["shadows"]), ("reflection", r["reflection"]))
                     if on) or "no shadows, no reflection"
    sizes = dict(task=r["task"], image_size=r["size"], chunk=r.get("chunk"),
                 shadows=r["shadows"], reflection=r["reflection"], vary=r.get("vary"))
    if r["bench"] == "jax_render":
      out.append(make_row("jax_render", f"frames ({look})", batch=r["batch"],
                          throughput=r["frames_per_s"], unit="frames/s",
                          compile_s=r["compile_s"], run_s=r["run_s"], sizes=sizes,
                          **_common(r)))
      continue
    sizes.update(frame_skip=r["frame_skip"], frame_stack=r["frame_stack"])
    for how, per_s, step_s, compile_s in (
        ("env.step", r["agent_steps_per_s"], r["step_s"], r["compile_s"]),
        ("scanned", r["scan_agent_steps_per_s"], r["scan_step_s"], r["scan_compile_s"])):
      out.append(make_row("jax_render", f"env, {how} ({look})", batch=r["batch"],
                          throughput=per_s, unit="agent-steps/s", compile_s=compile_s,
                          run_s=step_s, sizes=sizes, **_common(r)))
  return out


NORMALISERS: dict[str, Callable[[list[dict]], list[dict]]] = {
    "physics": _norm_physics, "render": _norm_render, "env": _norm_env,
    "jax_render": _norm_jax_render,
    "augment": _norm_augment, "learner": _norm_learner,
    "step_profile": _norm_step_profile, "train": _norm_train}


def normalise(benchmark: str, rows: list[dict]) -> list[dict]:
  """A benchmark's raw rows (as its module writes them) in the suite's schema.

  Rows already in the schema (they hold "throughput" and "unit") pass through,
  completed with `make_row`'s defaults; rows a normaliser cannot read (a key
  missing) are dropped with a note on stderr rather than stopping the summary.

  Args:
    benchmark: one of `BENCHMARKS`.
    rows: its raw rows.

  Returns:
    Normalised rows (keys `ROW_KEYS`).

  Raises:
    ValueError: an unknown benchmark (the message names the valid ones).
  """
  if benchmark not in NORMALISERS:
    raise ValueError(f"unknown benchmark {benchmark!r}; choose from: {', '.join(BENCHMARKS)}")
  out, good = [], []
  for row in rows:
    if "throughput" in row and "unit" in row:
      fields = {k: row[k] for k in ROW_KEYS if k in row and k not in ("benchmark", "variant")}
      fields.setdefault("device", _device(row))
      fields.setdefault("batch", None)
      out.append(make_row(benchmark, str(row.get("variant", benchmark)), **fields))
      continue
    try:  # each row alone first, so one bad row drops only itself
      NORMALISERS[benchmark]([row])
      good.append(row)
    except (KeyError, TypeError, ValueError, ZeroDivisionError) as e:
      print(f"benchmarks: dropped a {benchmark} row ({type(e).__name__}: {e})",
            file=sys.stderr)
  out.extend(NORMALISERS[benchmark](good))  # together: baselines span rows
  return out


# Summary ----------------------------------------------------------------------------

HEADLINE = {
    "physics": ("physics steps/s", lambda r: r["variant"]),
    "render": ("frames/s", lambda r: r["sizes"].get("quality")),
    "env": ("agent-steps/s with pixels", lambda r: r["variant"]),
    "jax_render": ("JAX renderer", lambda r: r["variant"]),
    "learner": ("updates/s", lambda r: (r["sizes"].get("agents"), r["sizes"].get("dtype"))),
    "train": ("end-to-end training", lambda r: r["variant"]),
    "step_profile": ("one agent step, all parts", lambda r: r["variant"]),
}
"""Per benchmark in the headline: its label and how rows are grouped; each group
shows its row at the largest batch (the fastest there)."""


def headline(rows: list[dict]) -> list[dict]:
  """The headline rows: per benchmark and group, the fastest row at the largest batch.

  Baseline rows are left out (they appear as the rows' baseline columns).
  """
  picked = []
  for bench, (_, key) in HEADLINE.items():
    groups: dict = {}
    for r in rows:
      if r["benchmark"] == bench and not r["is_baseline"] and r["throughput"]:
        groups.setdefault(key(r), []).append(r)
    for group in groups.values():
      picked.append(max(group, key=lambda r: ((r["batch"] or 0), r["throughput"])))
  return picked


def _num(x, digits: int = 0) -> str:
  """A number for a table: thousands separated, '–' when missing."""
  if x is None or (isinstance(x, float) and math.isnan(x)):
    return "–"
  if isinstance(x, (int, float)):
    if abs(x) >= 100 or digits == 0:
      return f"{x:,.0f}" if abs(x) >= 10 or x == 0 else f"{x:.2g}"
    return f"{x:,.{digits}f}"
  return str(x)


def _secs(x) -> str:
  """Seconds for a table: 3 significant digits below 1, one decimal below 100."""
  if x is None:
    return "–"
  return f"{x:.3g}" if x < 1 else (f"{x:.1f}" if x < 100 else f"{x:,.0f}")


def _headline_value(r: dict) -> str:
  if r["benchmark"] == "train":
    e = r["extra"]
    text = f"{_secs(r['run_s'])} s for {r['sizes'].get('steps'):,} steps"
    if e.get("ratio") is not None:
      text += (f", {e['steady_transitions_per_s']:,.1f} transitions/s steady against "
               f"{e['learner_updates_per_s']:,.1f} updates/s alone (ratio {e['ratio']:.2f})")
    if e.get("final_return") is not None:
      text += f", final return {e['final_return']:.1f}"
    if e.get("time_to_threshold_s") is not None:
      text += f", ≥ {e['threshold']:g} after {e['time_to_threshold_s']:.0f} s"
    elif e.get("threshold") is not None:
      text += f", never ≥ {e['threshold']:g}"
    return text
  if r["benchmark"] == "step_profile":
    return (f"{r['run_s'] * 1e3:,.1f} ms per agent step, i.e. {_num(r['throughput'])} "
            f"{r['unit']}")
  return f"{_num(r['throughput'])} {r['unit']}"


def _setting(r: dict) -> str:
  s = r["sizes"]
  if r["benchmark"] in ("physics", "env", "jax_render", "step_profile"):
    return f"{r['variant']}, N = {r['batch']:,}"
  if r["benchmark"] == "render":
    return f"{r['variant']}, batch {r['batch']:,}"
  if r["benchmark"] == "learner":
    return f"{r['variant']}, batch {r['batch']:,}"
  if r["benchmark"] == "train":
    renderer = r["extra"].get("renderer") or ""
    return (f"{s.get('task')}, {renderer + ', ' if renderer else ''}N = {s.get('num_envs')}, "
            f"{s.get('dtype') or ''} {s.get('quality') or ''}").strip()
  return r["variant"]


def headline_markdown(rows: list[dict]) -> str:
  """The headline table (see `HEADLINE`), or a line saying there is nothing yet."""
  picked = headline(rows)
  if not picked:
    return "No headline rows (no benchmark produced results).\n"
  lines = ["| what | setting | device | result | baseline (same run) | × baseline |",
           "|---|---|---|---|---|---:|"]
  for r in picked:
    base = (f"{r['baseline']}: {_num(r['baseline_throughput'])}" if r["baseline"] else "–")
    lines.append(f"| {HEADLINE[r['benchmark']][0]} | {_setting(r)} | {r['device']} | "
                 f"{_headline_value(r)} | {base} | "
                 f"{'–' if r['ratio'] is None else format(r['ratio'], '.1f')} |")
  return "\n".join(lines) + "\n"


def benchmark_markdown(rows: list[dict]) -> str:
  """One table of a benchmark's rows (and, where rows carry them, their time splits)."""
  lines = ["| variant | device | batch | compile s | run s / call | throughput | unit "
           "| baseline | × baseline |", "|---|---|---:|---:|---:|---:|---|---:|---:|"]
  for r in sorted(rows, key=lambda r: (r["is_baseline"], r["variant"], r["batch"] or 0)):
    name = f"{r['variant']} (baseline)" if r["is_baseline"] else r["variant"]
    lines.append(f"| {name} | {r['device']} | {_num(r['batch'])} | {_secs(r['compile_s'])} | "
                 f"{_secs(r['run_s'])} | {_num(r['throughput'])} | {r['unit']} | "
                 f"{_num(r['baseline_throughput'])} | "
                 f"{'–' if r['ratio'] is None else format(r['ratio'], '.2f')} |")
  split = [r for r in rows if r["extra"].get("parts_ms")]
  if split:
    parts = list(dict.fromkeys(p for r in split for p in r["extra"]["parts_ms"]))
    lines += ["", "Time per agent step (ms):", "",
              "| variant | N | " + " | ".join(parts) + " |",
              "|---|---:|" + "---:|" * len(parts)]
    for r in split:
      p = r["extra"]["parts_ms"]
      lines.append(f"| {r['variant']} | {_num(r['batch'])} | "
                   + " | ".join(_secs(p.get(k)) for k in parts) + " |")
  return "\n".join(lines) + "\n"


def jobs_markdown(results: Iterable[dict]) -> str:
  """The status of every job; failed ones with their last line of output."""
  lines = ["| job | status | exit | rows | wall s | last output |",
           "|---|---|---:|---:|---:|---|"]
  for r in results:
    last = ""
    if r["status"] != "ok":
      last = next((t for t in reversed(r.get("tail") or []) if t.strip()), "")
      last = "`" + last.strip().replace("|", "\\|").replace("`", "'")[:160] + "`" if last else ""
    lines.append(f"| {r['name']} | {r['status']} | {'–' if r['returncode'] is None else r['returncode']}"
                 f" | {r['rows']} | {r['wall_s']:,.1f} | {last} |")
  return "\n".join(lines) + "\n"


def summary_markdown(rows: list[dict], results: Sequence[dict], meta: dict) -> str:
  """The whole `summary.md`: what ran, the headline, the jobs, a table per benchmark.

  Args:
    rows: normalised rows.
    results: `JobResult`s as dicts, in run order.
    meta: "commands" (the suite invocations), "mode", "wall_s", "cpus", "host".
  """
  devices = sorted({r["device"] for r in rows}) or ["(no rows)"]
  out = [f"# Benchmark suite ({', '.join(devices)})", ""]
  for c in meta.get("commands", []):
    out.append(f"- `{c['command']}` — {c['mode']} mode, {c['time_utc']}, "
               f"{c['wall_s']:,.0f} s, {c.get('cpus')} cores ({c.get('host')})")
  failed = [r for r in results if r["status"] != "ok"]
  out += ["", f"{len(results)} job(s), {len(failed)} not ok. Throughputs are medians of timed "
          "calls after compilation; compile (or start-up) time is reported apart; ratios "
          "are to the baseline measured in the same run. Rows: `benchmarks.jsonl`; plot: "
          "`throughput.png`; child output: `logs/`.", "", "## Headline", "",
          headline_markdown(rows), "## Jobs", "", jobs_markdown(results)]
  for bench in BENCHMARKS:
    mine = [r for r in rows if r["benchmark"] == bench]
    if mine:
      out += [f"## {bench}", "", benchmark_markdown(mine)]
  return "\n".join(out)


def plot_throughput(rows: list[dict], path: str) -> bool:
  """Throughput against batch size, log-log, one panel per benchmark (PNG).

  Each variant is a line (markers at the measured batches); baselines are dashed,
  and a baseline measured at one batch only (the one-env original pipeline, the
  naive render loop) is a dashed horizontal line across the panel.

  Returns:
    False (and no file) when no row has a batch and a throughput.
  """
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  usable = [r for r in rows if r["batch"] and r["throughput"] and r["benchmark"] != "train"]
  benches = [b for b in BENCHMARKS if any(r["benchmark"] == b for r in usable)]
  if not benches:
    return False
  cols = min(3, len(benches))
  nrows = math.ceil(len(benches) / cols)
  fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 4.0 * nrows), squeeze=False)
  for ax, bench in zip(axes.flat, benches):
    mine = [r for r in usable if r["benchmark"] == bench]
    variants = list(dict.fromkeys((r["variant"], r["is_baseline"]) for r in mine))
    flat = []
    for variant, is_base in variants:
      pts = sorted((r["batch"], r["throughput"]) for r in mine
                   if r["variant"] == variant and r["is_baseline"] == is_base)
      xs, ys = zip(*pts)
      if is_base and len(set(xs)) == 1:
        flat.append((variant, ys[-1]))
        continue
      ax.plot(xs, ys, "--" if is_base else "-", marker="o", ms=4,
              label=variant + (" (baseline)" if is_base else ""))
    for i, (variant, y) in enumerate(flat):
      ax.axhline(y, ls="--", lw=1, color=f"C{(len(variants) + i) % 10}",
                 label=f"{variant} (baseline)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title(bench)
    ax.set_xlabel("batch size (envs / frames / images)")
    ax.set_ylabel(" / ".join(dict.fromkeys(r["unit"] for r in mine)))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6 if len(variants) > 6 else 7, ncol=2 if len(variants) > 8 else 1)
  for ax in list(axes.flat)[len(benches):]:
    ax.axis("off")
  devices = ", ".join(sorted({r["device"] for r in usable}))
  fig.suptitle(f"dmcr_jax benchmarks — throughput against batch size ({devices})")
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)
  return True


# The suite --------------------------------------------------------------------------


def gpu_name() -> str | None:
  """The first NVIDIA GPU's name from nvidia-smi, or None (no JAX import: the
  suite's own process must not take accelerator memory from its children)."""
  try:
    out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                         capture_output=True, text=True, timeout=10).stdout.strip()
  except (OSError, subprocess.SubprocessError):
    return None
  return out.splitlines()[0].strip() if out else None


def device_slug(name: str | None) -> str:
  """A short folder tag for a device name: "h100", "a100", … or "cpu" for None."""
  if not name:
    return "cpu"
  match = re.search(r"([A-Z]+\d{2,4})", name)
  return match.group(1).lower() if match else re.sub(r"\W+", "-", name.lower()).strip("-")


def default_out(now: datetime.datetime | None = None, device: str | None = None) -> str:
  """`benchmarks/results/suite-<device>-<UTC date>` (under the repository root)."""
  now = now or datetime.datetime.now(datetime.timezone.utc)
  return os.path.join(ROOT, "benchmarks", "results",
                      f"suite-{device_slug(device)}-{now:%Y-%m-%d}")


def load_state(out_dir: str) -> dict:
  """`<out>/runs.json`: the suite invocations and every job's latest result."""
  path = os.path.join(out_dir, "runs.json")
  if os.path.exists(path):
    with open(path) as f:
      return json.load(f)
  return {"commands": [], "jobs": {}}


def collect(out_dir: str, state: dict) -> list[dict]:
  """Normalised rows of every job recorded in `state`, with "job" and "mode" added
  (and the job's start time where a row has no time of its own).

  A job whose raw JSONL is gone although its run wrote rows (a folder copied back
  without `raw/`, say) keeps the rows `<out>/benchmarks.jsonl` already holds for it,
  so rebuilding the outputs never drops a measurement that was made.
  """
  kept: dict[str, list[dict]] = {}
  for r in read_jsonl(os.path.join(out_dir, "benchmarks.jsonl")):
    kept.setdefault(r.get("job"), []).append(r)
  rows = []
  for name, result in state["jobs"].items():
    raw = raw_path(out_dir, name)
    if not os.path.exists(raw) and result.get("rows"):
      rows.extend(kept.get(name, []))
      continue
    for r in normalise(result["benchmark"], read_jsonl(raw)):
      r["time_utc"] = r["time_utc"] or result.get("time_utc")  # render rows carry none
      rows.append(dict(r, job=name, mode=result.get("mode")))
  return rows


def write_outputs(out_dir: str, state: dict) -> list[dict]:
  """Writes runs.json, benchmarks.jsonl, summary.md and throughput.png; the rows."""
  with open(os.path.join(out_dir, "runs.json"), "w") as f:
    json.dump(state, f, indent=1)
  rows = collect(out_dir, state)
  with open(os.path.join(out_dir, "benchmarks.jsonl"), "w") as f:
    for r in rows:
      f.write(json.dumps(r) + "\n")
  results = list(state["jobs"].values())
  with open(os.path.join(out_dir, "summary.md"), "w") as f:
    f.write(summary_markdown(rows, results, state))
  png = os.path.join(out_dir, "throughput.png")
  if not plot_throughput(rows, png) and os.path.exists(png):
    os.remove(png)
  return rows


def run_suite(jobs: Sequence[Job], out_dir: str, mode: str, command: str,
              progress: bool = True, verbose: bool = False) -> dict:
  """Runs the jobs one after the other and writes the outputs after each.

  Args:
    jobs: from `plan` (or hand-made, e.g. in tests).
    out_dir: the output folder; jobs recorded there by earlier runs are kept
      unless run again.
    mode: recorded with each job's result.
    command: the command line, recorded in runs.json and summary.md.
    progress: show a progress bar (tqdm) with each child's latest line.
    verbose: also echo every line the children print.

  Returns:
    The state written to runs.json (its "jobs" hold the `JobResult`s as dicts).
  """
  os.makedirs(out_dir, exist_ok=True)
  state = load_state(out_dir)
  invocation = dict(command=command, mode=mode, time_utc=_utc_now(), wall_s=0.0,
                    cpus=os.cpu_count(), host=os.uname().nodename)
  state["commands"].append(invocation)
  t0 = time.perf_counter()
  bar = None
  if progress:
    from tqdm.auto import tqdm
    bar = tqdm(total=len(jobs), unit="job", dynamic_ncols=True)

  def on_line(line: str) -> None:
    if verbose:
      (bar.write if bar is not None else print)(line)
    if bar is not None:
      bar.set_postfix_str(line.strip()[:70], refresh=True)

  try:
    for job in jobs:
      if bar is not None:
        bar.set_description(job.name)
      try:
        result = run_job(job, out_dir, on_line)
      except KeyboardInterrupt:
        state["jobs"][job.name] = dict(dataclasses.asdict(JobResult(
            job.name, job.benchmark, list(job.argv), "interrupted", None, 0.0,
            len(read_jsonl(raw_path(out_dir, job.name))), [], _utc_now())), mode=mode)
        raise
      finally:
        invocation["wall_s"] = round(time.perf_counter() - t0, 1)
      state["jobs"].pop(job.name, None)  # keep run order in the summary
      state["jobs"][job.name] = dict(dataclasses.asdict(result), mode=mode)
      msg = f"{job.name}: {result.status} ({result.rows} rows, {result.wall_s:,.0f} s)"
      (bar.write if bar is not None else print)(msg)
      if bar is not None:
        bar.update(1)
      write_outputs(out_dir, state)
  finally:
    if bar is not None:
      bar.close()
    invocation["wall_s"] = round(time.perf_counter() - t0, 1)
    write_outputs(out_dir, state)
  return state


def build_parser() -> argparse.ArgumentParser:
  """The command line of `python -m benchmarks`."""
  p = argparse.ArgumentParser(
      prog="python -m benchmarks",
      description="Run every dmcr_jax benchmark (each as a child process) and write "
                  "benchmarks.jsonl, summary.md and throughput.png.")
  p.add_argument("--quick", action="store_true",
                 help="tiny sizes and cheap tasks: a few minutes on a 2-core CPU")
  p.add_argument("--only", default=None,
                 help=f"comma-separated benchmarks to run: {', '.join(BENCHMARKS)} "
                      "(default: all); single jobs by name too, e.g. env-exact "
                      f"(full mode's: {', '.join(job_names('full'))})")
  p.add_argument("--out", default=None,
                 help="output folder (default: benchmarks/results/suite-<device>-<UTC date>)")
  p.add_argument("--timeout", type=float, default=None,
                 help="per-job wall-clock limit in seconds (default: "
                      f"{DEFAULT_TIMEOUT_S['quick']:.0f} quick, {DEFAULT_TIMEOUT_S['full']:.0f} full)")
  p.add_argument("--dry-run", action="store_true", help="print the jobs' commands and exit")
  p.add_argument("--verbose", action="store_true", help="echo the children's output")
  p.add_argument("--no-progress", action="store_true", help="no progress bar")
  return p


def main(argv: Sequence[str] | None = None) -> int:
  """Command-line entry; returns the exit status (1 if any job was not ok)."""
  argv = list(sys.argv[1:] if argv is None else argv)
  p = build_parser()
  a = p.parse_args(argv)
  mode = "quick" if a.quick else "full"
  try:
    only = parse_only(a.only, mode)
  except ValueError as e:
    p.error(str(e))
  if a.timeout is not None and not a.timeout > 0:
    p.error(f"--timeout must be > 0 seconds, got {a.timeout}")
  jobs = plan(mode, only, a.timeout)
  out_dir = os.path.abspath(a.out or default_out(device=gpu_name()))
  if a.dry_run:
    for job in jobs:
      argv = [x.replace(OUT_PLACEHOLDER, raw_path(out_dir, job.name)) for x in job.argv]
      print(f"# {job.name} (limit {job.timeout_s:.0f} s)\n{shlex.join(argv)}")
    return 0
  command = shlex.join(["python", "-m", "benchmarks", *argv])
  print(f"benchmarks: {len(jobs)} job(s), {mode} mode -> {out_dir}", flush=True)
  try:
    state = run_suite(jobs, out_dir, mode, command, progress=not a.no_progress,
                      verbose=a.verbose)
  except KeyboardInterrupt:
    print(f"benchmarks: interrupted; partial results in {out_dir}", file=sys.stderr)
    return 130
  with open(os.path.join(out_dir, "summary.md")) as f:
    print(f.read())
  bad = [n for n, r in state["jobs"].items() if r["status"] != "ok" and n in
         {j.name for j in jobs}]
  print(f"benchmarks: wrote {out_dir}/benchmarks.jsonl, summary.md, throughput.png"
        + (f"; not ok: {', '.join(bad)}" if bad else ""))
  return 1 if bad else 0
