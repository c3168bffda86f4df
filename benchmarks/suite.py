"""`python -m dmcr_jax.benchmarks`: every benchmark in one process tree, one JSONL, one summary.

Each benchmark module of this package runs as a child process, one after the other
(they would otherwise compete for the cores and the accelerator), each within a
wall-clock limit; a child that fails or runs out of time is recorded and the others
still run. A child appends rows in the one row format (`dmcr_jax.benchmarks.rows`) to
`<out>/raw/<job>.jsonl` (its output: `<out>/logs/<job>.log`); the suite writes
`<out>/benchmarks.jsonl` (every row, with "benchmark", "job" and "mode"), `summary.md`
and `throughput.png` (`dmcr_jax.benchmarks.report`) and `runs.json` (every job's command,
status, exit code and wall time). Runs into an existing ``--out`` folder replace the
jobs run again and keep the others, so a sweep can be run in parts.

    python -m dmcr_jax.benchmarks --quick --out /tmp/suite_quick   # tiny sizes: minutes on 2 cores
    python -m dmcr_jax.benchmarks --only physics,env-exact --out /tmp/suite        # some jobs
    python -m dmcr_jax.benchmarks --dry-run                        # print the commands of the plan
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Sequence

from dmcr_jax.benchmarks import report
from dmcr_jax.benchmarks import rows as R

BENCHMARKS = R.BENCHMARKS
"""What ``--only`` accepts, in the order the suite runs them."""

MODES = ("quick", "full")

DEFAULT_TIMEOUT_S = {"quick": 240.0, "full": 1200.0}
"""Per-job wall-clock limit in seconds unless ``--timeout`` is given."""

OUT_PLACEHOLDER = "{out}"
"""In a job's argv, replaced by the path of the job's raw JSONL file."""

CPUS_PLACEHOLDER = "{cpus}"
"""In a job's argv, replaced by the number of cores of the machine."""

# Per benchmark and mode, job suffix -> "module arguments" (module of this package).
# Quick: tiny sizes, the task that compiles fastest (pendulum) and 32×32 images for
# the learner; full: the sizes of the project's targets.
_PLANS: dict[str, dict[str, dict[str, str]]] = {
    "quick": {
        "physics": {"": "physics --tasks pendulum-swingup --sizes 1,16 --steps 2 --repeats 2"},
        "render": {"": "render --batches 8,32 --workers 2 --qualities fastest --repeats 2 "
                       "--baseline-frames 20"},
        "env": {"": "env --task pendulum-swingup --sizes 1,4 --qualities fastest --workers 2 "
                    "--seconds 0.5 --original-steps 20"},
        "jax_render": {
            "": "jax_render --task pendulum-swingup --size 32 --batches 4,16 --repeats 2",
            "-env": "jax_render --mode env --task pendulum-swingup --size 32 --batches 4 "
                    "--repeats 2 --steps 3 --scan-steps 3"},
        "augment": {"": "augment --batch 16 --names none,drq,cj+drq --min-time 0.1 "
                        "--min-reps 3 --max-reps 20"},
        "learner": {"": "learner --agents 1 --dtypes float32 --batch 8 --size 32 --pairs 1 "
                        "--capacity 256 --seconds 0.2"},
        "step_profile": {"": "step_profile --task pendulum-swingup --sizes 4 --quality fastest "
                             "--workers 2 --image-size 32 --steps 5 --batch 8 --capacity 256 "
                             "--pairs 1"},
        "train": {"": "training --task pendulum-swingup --action-repeat 8 --steps 130 "
                      "--num-envs 1 --warmup-steps 100 --batch-size 8 --image-size 32 "
                      "--buffer-capacity 1000 --dtype float32 --quality fastest --workers 2 "
                      "--log-every 10"},
    },
    "full": {
        "physics": {"": "physics --tasks walker-walk --sizes 1,64,1024,8192 --steps 20 "
                        "--repeats 5 --parallel-compiles 4"},
        "render": {"": "render --batches 16,64,256,1024 --workers {cpus} "
                       "--qualities exact,fast,fastest --repeats 3 --baseline-frames 300"},
        # Largest first: a job cut at its time limit keeps the rows of the target size.
        # env-target: the settings that meet the agent-steps/s target at N = 1,024.
        "env": {"-fastest": "env --sizes 1024,256,16,1 --qualities fastest --seconds 3",
                "-exact": "env --sizes 1024,256,16,1 --qualities exact --seconds 3 "
                          "--original-steps 50",
                "-target": "env --sizes 1024 --renderers pool,jax --qualities fastest "
                           "--ls-iterations 4 --no-copy --seconds 3 --original-steps 50"},
        # The JAX env at 4,096 envs only (its compilation is long); 1,024 is in env-target.
        "jax_render": {"": "jax_render --batches 1024,4096,16384 --chunk 256",
                       "-env": "jax_render --mode env --batches 4096 --chunk 256 --repeats 2 "
                               "--steps 5 --scan-steps 10"},
        "augment": {"": "augment --batch 256",
                    "-b64": "augment --batch 64 --names none,drq",
                    "-b1024": "augment --batch 1024 --names none,drq"},
        # learner-algos: CURL and SAC+AE at their own batch sizes.
        "learner": {"": "learner --agents 1,8 --dtypes float32,bfloat16 --loops map,vmap "
                        "--batch 256 --pairs 25 --seconds 3",
                    "-algos": "learner --algos curl,sac_ae --agents 1 --dtypes "
                              "float32,bfloat16 --pairs 25 --seconds 3 --no-baseline"},
        "step_profile": {"": "step_profile --task walker-walk --sizes 1024 --quality fastest "
                             "--steps 20 --batch 256 --capacity 100000"},
        # End to end against the learner alone, both renderers.
        "train": {suffix: "training --task ball_in_cup-catch --steps 24000 "
                          "--dtype bfloat16 --quality exact --log-every 500" + extra
                  for suffix, extra in (("", ""), ("-jax", " --renderer jax"))},
    },
}


@dataclasses.dataclass(frozen=True)
class Job:
  """One child process: `name` (unique in a run, the stem of its raw JSONL and log
  files), the `benchmark` of `BENCHMARKS` its rows belong to, its `argv`
  (`OUT_PLACEHOLDER` becomes the raw JSONL path) and its limit `timeout_s` (seconds)."""
  name: str
  benchmark: str
  argv: tuple[str, ...]
  timeout_s: float


@dataclasses.dataclass
class JobResult:
  """What became of a job: its name, benchmark and argv as run; `status` "ok",
  "failed" (non-zero exit), "timeout", "no rows" (exit 0, nothing written) or
  "interrupted" (Ctrl-C); `returncode` (None when killed); `wall_s`; `rows` it wrote;
  `tail`, its last lines of output; `time_utc`, when it started."""
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
  return tuple(bench + suffix for bench in BENCHMARKS for suffix in _PLANS[mode][bench])


def parse_only(text: str | None, mode: str = "full") -> tuple[str, ...]:
  """What ``--only`` selects: benchmark names ("physics,env") and/or job names of
  `mode` ("env-exact"), benchmarks first in the order of `BENCHMARKS`, then jobs;
  None or "all": every benchmark.

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
  return (tuple(b for b in BENCHMARKS if b in names) + tuple(j for j in jobs if j in names))


def plan(mode: str, only: Sequence[str] = BENCHMARKS, timeout_s: float | None = None,
         cpus: int | None = None, python: str = sys.executable) -> list[Job]:
  """The jobs of a suite run, in the order of `BENCHMARKS`.

  Args:
    mode: "quick" or "full".
    only: the benchmarks (all their jobs) and jobs to run (see `parse_only`).
    timeout_s: per-job limit in seconds (None: `DEFAULT_TIMEOUT_S[mode]`).
    cpus: the cores to give render workers in full mode (None: this machine's).
    python: the interpreter of the children.

  Raises:
    ValueError: an unknown mode, benchmark or job.
  """
  if mode not in MODES:
    raise ValueError(f"unknown mode {mode!r}; choose from: {', '.join(MODES)}")
  parse_only(",".join(only), mode)
  limit = DEFAULT_TIMEOUT_S[mode] if timeout_s is None else float(timeout_s)
  cores = str(cpus or os.cpu_count() or 1)
  return [Job(bench + suffix, bench,
              (python, "-m", "benchmarks." + module,
               *[a.replace(CPUS_PLACEHOLDER, cores) for a in args],
               "--out", OUT_PLACEHOLDER), limit)
          for bench in BENCHMARKS for suffix, (module, *args) in
          ((s, shlex.split(c)) for s, c in _PLANS[mode][bench].items())
          if bench in only or bench + suffix in only]


# Running ----------------------------------------------------------------------------


def raw_path(out_dir: str, job_name: str) -> str:
  """Where a job's child writes its rows."""
  return os.path.join(os.path.abspath(out_dir), "raw", job_name + ".jsonl")


def _kill_group(proc: subprocess.Popen, grace_s: float = 10.0) -> None:
  """Stops the child's process group: SIGTERM, up to `grace_s` seconds for the child
  to exit, then SIGKILL for whatever of the group is left."""
  for sig, wait_s in ((signal.SIGTERM, grace_s), (signal.SIGKILL, None)):
    try:
      os.killpg(proc.pid, sig)
    except ProcessLookupError:
      break
    try:
      proc.wait(timeout=wait_s)
    except subprocess.TimeoutExpired:
      pass


def run_job(job: Job, out_dir: str, on_line: Callable[[str], None] | None = None,
            tail_lines: int = 20) -> JobResult:
  """Runs one job as a child process in its own process group, within its limit.

  Its raw JSONL is removed first, so the rows are this run's; its output goes to
  `<out_dir>/logs/<name>.log` and, line by line, to `on_line`. At the time limit the
  whole group (the child and, e.g., its render workers) is stopped; rows it wrote
  before are kept. A Ctrl-C stops the child and is re-raised.
  """
  raw, log = raw_path(out_dir, job.name), os.path.join(out_dir, "logs", job.name + ".log")
  for folder in (os.path.dirname(raw), os.path.dirname(log)):
    os.makedirs(folder, exist_ok=True)
  if os.path.exists(raw):
    os.remove(raw)
  argv = [a.replace(OUT_PLACEHOLDER, raw) for a in job.argv]
  started, t0 = R.utc_now(), time.perf_counter()
  tail: list[str] = []
  status, rc = None, None
  with open(log, "w") as log_file:
    log_file.write(f"$ {shlex.join(argv)}\n")
    log_file.flush()
    proc = subprocess.Popen(argv, env=dict(os.environ, PYTHONUNBUFFERED="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            errors="replace", start_new_session=True)

    def pump():
      for line in proc.stdout:
        try:
          log_file.write(line)
          log_file.flush()
        except ValueError:  # closed: a straggler of the group still printing
          return
        line = line.rstrip("\n").split("\r")[-1]
        tail[:] = (tail + [line])[-tail_lines:]
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
  rows = len(R.read(raw))
  if status is None:
    status = "failed" if rc != 0 else ("ok" if rows else "no rows")
  return JobResult(job.name, job.benchmark, argv, status, rc,
                   round(time.perf_counter() - t0, 2), rows, list(tail), started)


# The suite --------------------------------------------------------------------------


def default_out(now: datetime.datetime | None = None, device: str | None = None) -> str:
  """`benchmarks/results/suite-<device>-<UTC date>`, relative to the current directory
  (the repository root, where the committed results live)."""
  now = now or datetime.datetime.now(datetime.timezone.utc)
  return os.path.join("benchmarks", "results",
                      f"suite-{R.device_slug(device)}-{now:%Y-%m-%d}")


def load_state(out_dir: str) -> dict:
  """`<out>/runs.json`: the suite invocations and every job's latest result."""
  path = os.path.join(out_dir, "runs.json")
  if os.path.exists(path):
    with open(path) as f:
      return json.load(f)
  return {"commands": [], "jobs": {}}


def _flatten(r: dict) -> dict:
  """A row of a `benchmarks.jsonl` written before the one row format (its settings in
  "sizes" and "extra", N in "batch") in today's shape."""
  if "sizes" not in r:
    return r
  flat = dict(r["sizes"] or {}, **(r.get("extra") or {}))
  flat.update({k: v for k, v in r.items() if k not in ("sizes", "extra", "ratio")})
  return dict(flat, n=r.get("batch"))


def collect(out_dir: str, state: dict) -> list[dict]:
  """The rows of every job recorded in `state` (those in the one row format: they
  hold a "unit"), with "benchmark", "job" and "mode" added.

  A job whose raw rows are gone or older than the row format although its run wrote
  rows (a folder copied back without `raw/`, say) keeps the rows
  `<out>/benchmarks.jsonl` already holds for it, so rebuilding the outputs never
  drops a measurement that was made.
  """
  kept: dict[str, list[dict]] = {}
  for r in R.read(os.path.join(out_dir, "benchmarks.jsonl")):
    kept.setdefault(r.get("job"), []).append(_flatten(r))
  rows = []
  for name, result in state["jobs"].items():
    raw = [r for r in R.read(raw_path(out_dir, name)) if "unit" in r]
    if not raw and result.get("rows"):
      rows += kept.get(name, [])
    else:
      rows += [dict(r, benchmark=result["benchmark"], job=name, mode=result.get("mode"))
               for r in raw]
  return rows


def write_outputs(out_dir: str, state: dict) -> list[dict]:
  """Writes runs.json, benchmarks.jsonl, summary.md and throughput.png; the rows."""
  with open(os.path.join(out_dir, "runs.json"), "w") as f:
    json.dump(state, f, indent=1)
  rows = collect(out_dir, state)
  with open(os.path.join(out_dir, "benchmarks.jsonl"), "w") as f:
    f.writelines(json.dumps(r) + "\n" for r in rows)
  with open(os.path.join(out_dir, "summary.md"), "w") as f:
    f.write(report.summary_markdown(rows, list(state["jobs"].values()), state))
  png = os.path.join(out_dir, "throughput.png")
  if not report.plot_throughput(rows, png) and os.path.exists(png):
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
  invocation = dict(command=command, mode=mode, time_utc=R.utc_now(), wall_s=0.0,
                    cpus=os.cpu_count(), host=os.uname().nodename)
  state["commands"].append(invocation)
  t0 = time.perf_counter()
  bar = None
  if progress:
    from tqdm.auto import tqdm
    bar = tqdm(total=len(jobs), unit="job", dynamic_ncols=True)
  say = bar.write if bar is not None else print

  def on_line(line: str) -> None:
    if verbose:
      say(line)
    if bar is not None:
      bar.set_postfix_str(line.strip()[:70], refresh=True)

  try:
    for job in jobs:
      if bar is not None:
        bar.set_description(job.name)
      try:
        result = run_job(job, out_dir, on_line)
      except KeyboardInterrupt:
        result = JobResult(job.name, job.benchmark, list(job.argv), "interrupted", None, 0.0,
                           len(R.read(raw_path(out_dir, job.name))), [], R.utc_now())
        state["jobs"][job.name] = dict(dataclasses.asdict(result), mode=mode)
        raise
      finally:
        invocation["wall_s"] = round(time.perf_counter() - t0, 1)
      state["jobs"].pop(job.name, None)  # keep run order in the summary
      state["jobs"][job.name] = dict(dataclasses.asdict(result), mode=mode)
      say(f"{job.name}: {result.status} ({result.rows} rows, {result.wall_s:,.0f} s)")
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
  """The command line of `python -m dmcr_jax.benchmarks`."""
  p = argparse.ArgumentParser(
      prog="python -m dmcr_jax.benchmarks",
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
  out_dir = os.path.abspath(a.out or default_out(device=R.gpu_name()))
  if a.dry_run:
    for job in jobs:
      cmd = [x.replace(OUT_PLACEHOLDER, raw_path(out_dir, job.name)) for x in job.argv]
      print(f"# {job.name} (limit {job.timeout_s:.0f} s)\n{shlex.join(cmd)}")
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
  bad = [j.name for j in jobs if state["jobs"][j.name]["status"] != "ok"]
  print(f"benchmarks: wrote {out_dir}/benchmarks.jsonl, summary.md, throughput.png"
        + (f"; not ok: {', '.join(bad)}" if bad else ""))
  return 1 if bad else 0


if __name__ == "__main__":
  sys.exit(main())
