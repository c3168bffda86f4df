"""End-to-end training time: one `train` run (cartpole-balance by default), timed, beside its learner alone.

Runs the `train` command's parse and `dmcr_jax.train.loop.train` in this process with the
arguments given (unknown ones go to `train`; see ``python -m dmcr_jax.train --help``) on
top of the README's H100 command (cartpole-balance, 50,000 training steps,
bfloat16, dm_control's exact look, no intermediate checkpoints; `train`'s defaults
otherwise, e.g. its number of envs), into a
fresh run folder, and reports: the wall time of the training loop (compilation
included, as `train` reports it) and of the whole run (env start-up too),
transitions per second per agent, the first training step (and its loop time)
at which an episode's return reached ``--threshold``, the final return
(mean of the last episodes, as `train` computes it), and, with the host driver,
where the loop's time went (summary.json's "host_seconds": act, learn, the env's
step_async and step_wait, store; "env_seconds": the env's own parts). With
``--eval-every N`` (`train`'s evaluation during training), the evaluations'
seconds and their share of the loop's wall time (`eval_seconds`, `eval_share`).

The baseline in the same run: the learner alone (`dmcr_jax.benchmarks.learner`'s scanned
updates of the same agents, batch, dtype and augmentation on full random
buffers). The end-to-end rate compared with it is the steady one: transitions
per second per agent between the first and the last episode ends after the
warm-up (so compilation and the random-action phase are left out; a run with one
such end: from it to the run's end, summary.json's "steady"), times `utd`;
`ratio` = that rate over the learner's updates/s. 1.0 means the env costs the
training loop nothing.

Devices: `train` shards its K agents over the local devices (`dmcr_jax.train.loop`).
``--devices 1,2,4,8`` runs the same training once per count, the agents
sharded over that many local devices (each count at most the local device
count and dividing K, and 1 with the device driver; otherwise the run is
refused before anything compiles), each run with its learner-alone baseline on
the same devices; without it, one run on the devices `train` picks. Each row
carries its device count and the total steady rate over all agents (steady
transitions/s per agent × K); with several counts also its scaling efficiency:
that total over D times the one-device run's (1.0: linear; none when a run is
too short for a steady rate: no episode end past the warm-up).

    python -m dmcr_jax.benchmarks.training --out benchmarks/results/train_h100.jsonl
    python -m dmcr_jax.benchmarks.training --steps 2000 --num-envs 4 --quality fastest --out /tmp/t.jsonl
    python -m dmcr_jax.benchmarks.training --devices 1,2 --seeds 0,1 --out /tmp/scaling.jsonl
    python -m dmcr_jax.benchmarks.training --beside-one --renderer jax --seeds 0,1 --aug drq,cj+drq

``--beside-one`` runs, before a run of K > 1 agents, the same training with its first
agent alone (the first look group, augmentation and seed) and gives the K-agent row
`beside_one`: its total steady transitions/s (all agents) over the one-agent run's,
in the same process (1.0: K agents cost K one-agent runs; K: they cost one).

One JSON line per run appended to `--out`, a Markdown table beside it.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import sys
import tempfile
import time

from dmcr_jax.benchmarks import rows as R

DEFAULT_TRAIN_ARGS = ("--task", "cartpole-balance", "--steps", "50000", "--dtype", "bfloat16",
                      "--quality", "exact", "--checkpoint-every", "0",
                      "--log-every", "500")
"""The `train` arguments of the README's paper-length cartpole run (train's own defaults
for the rest, e.g. its number of envs); given arguments override them."""


def first_reaching(log_rows: list[dict], threshold: float) -> dict | None:
  """The first log.csv row (by step) whose episode return is at least `threshold`.

  Args:
    log_rows: rows of a run's log.csv (strings, as `csv.DictReader` gives them).
    threshold: the return to reach.

  Returns:
    {"step", "wall_s", "episode_return"} or None if no episode reached it.
  """
  hits = [r for r in log_rows if float(r["episode_return"]) >= threshold]
  if not hits:
    return None
  r = min(hits, key=lambda r: (int(r["step"]), float(r["wall_s"])))
  return dict(step=int(r["step"]), wall_s=float(r["wall_s"]),
              episode_return=float(r["episode_return"]))


def steady_rate(log_rows: list[dict], after_step: int, window: dict | None = None
                ) -> float | None:
  """Transitions/s per agent between the first and the last episode end past
  `after_step`; with fewer than two such ends, over `window` (summary.json's
  "steady": from the first episode end past the warm-up to the run's end, the host
  driver's), else None.

  Args:
    log_rows: rows of a run's log.csv (strings, as `csv.DictReader` gives them).
    after_step: the warm-up's last step.
    window: summary.json's "steady" ({"steps", "wall_s", …} per agent) or None.
  """
  ends = sorted({(int(r["step"]), float(r["wall_s"])) for r in log_rows
                 if int(r["step"]) > after_step})
  if len(ends) >= 2 and ends[-1][1] > ends[0][1]:
    (s0, w0), (s1, w1) = ends[0], ends[-1]
    return (s1 - s0) / (w1 - w0)
  if window and window.get("steps", 0) > 0 and window.get("wall_s", 0) > 0:
    return window["steps"] / window["wall_s"]
  return None


def learner_alone(cfg, seconds: float = 3.0, devices: int = 1) -> dict:
  """`dmcr_jax.benchmarks.learner`'s row for the run's learner (agents, dtype, loop, batch,
  augmentation, frames) on full random buffers, the agents sharded over
  `devices` local devices."""
  import jax
  from dmcr_jax.benchmarks import learner
  from dmcr_jax import models
  on_cpu = jax.default_backend() == "cpu"
  task = models.load(cfg.task)
  k = len(cfg.agents())
  return learner.bench_scanned(
      k, cfg.sac.compute_dtype, cfg.agent_loop or ("vmap" if on_cpu else "map"),
      cfg.sac.batch_size, 25, cfg.image_size if cfg.sac.algo != "curl" else cfg.sac.curl_crop,
      cfg.frame_stack, task.action_size, 10_000, seconds, cfg.sac.algo,
      cfg.sac.aug if cfg.sac.algo == "sac_aug" else None, devices=devices)


def run(train_argv: list[str], threshold: float, run_dir: str, baseline: bool = True,
        devices: int | None = None) -> dict:
  """Trains with `train_argv` into `run_dir` (after timing the learner alone), the
  agents sharded over `devices` local devices (None: as `train` picks); one
  result row."""
  from dmcr_jax.train import __main__ as train_cli
  from dmcr_jax.train import config, loop

  cfg, _ = train_cli.parse(list(train_argv) + ["--out", run_dir])
  plan = config.resolve(cfg, devices)
  used = plan.devices
  alone = learner_alone(cfg, devices=used) if baseline else None
  if alone:
    print(f"learner alone: {alone['updates_per_s_per_agent']:.1f} updates/s per agent",
          flush=True)
  t0 = time.perf_counter()
  summary = loop.train(plan, progress=False)
  process_s = time.perf_counter() - t0
  with open(os.path.join(run_dir, "log.csv")) as f:
    log_rows = list(csv.DictReader(f))
  hit = first_reaching(log_rows, threshold)
  finals = [v for v in (summary.get("final_return") or {}).values() if v is not None]
  import jax
  device = jax.devices()[0]
  agents = len(cfg.agents())
  # After the warm-up and a little more: the first episode end past it still
  # carries the update's compilation, the rate starts there.
  steady = steady_rate(log_rows, cfg.warmup_steps, summary.get("steady"))
  updates_alone = alone and alone["updates_per_s_per_agent"]
  return dict(
      bench="train", device=device.device_kind, platform=device.platform,
      jax=jax.__version__, cpus=os.cpu_count(), task=cfg.task, steps=summary["steps"],
      agents=agents, devices=used, num_envs=cfg.num_envs, quality=cfg.quality,
      dtype=cfg.sac.compute_dtype, batch_size=cfg.sac.batch_size, utd=cfg.utd,
      action_repeat=cfg.action_repeat, wall_s=summary["wall_s"], process_s=process_s,
      transitions_per_s=summary["steps"] / summary["wall_s"] if summary["wall_s"] else None,
      renderer=cfg.renderer, physics=plan.physics_device or jax.default_backend(),
      physics_workers=plan.physics_workers,
      steady_transitions_per_s=steady,
      total_transitions_per_s=steady * agents if steady else None,
      learner_updates_per_s=updates_alone,
      ratio=(steady * cfg.utd / updates_alone) if steady and updates_alone else None,
      episodes=len(log_rows), final_return=sum(finals) / len(finals) if finals else None,
      threshold=threshold, step_at_threshold=hit and hit["step"],
      time_to_threshold_s=hit and hit["wall_s"], interrupted=summary["interrupted"],
      host_seconds=summary.get("host_seconds"), env_seconds=summary.get("env_seconds"),
      steady=summary.get("steady"),
      eval_every=cfg.eval_every or None, eval_seconds=summary.get("eval_seconds"),
      eval_share=eval_share(summary),
      train_args=list(train_argv), run_dir=run_dir,
      time_utc=R.utc_now())


def eval_share(summary: dict) -> float | None:
  """The fraction of the loop's wall time its evaluations during training took
  (`train --eval-every`; summary.json's "eval_seconds" over "wall_s"); None without
  them."""
  if summary.get("eval_seconds") is None or not summary.get("wall_s"):
    return None
  return summary["eval_seconds"] / summary["wall_s"]


def first_agent_args(cfg) -> list[str]:
  """`train` arguments that, appended to a run's own, train its first agent alone:
  the first seed, augmentation and look group of each that has several."""
  out = []
  if len(cfg.seeds) > 1:
    out += ["--seeds", str(cfg.seeds[0])]
  if len(cfg.sac.aug_names) > 1:
    out += ["--aug", cfg.sac.aug_names[0]]
  if len(cfg.looks) > 1:
    out += ["--visual-seeds", str(cfg.visual_seeds).split(",")[0]]
  return out


def check_device_counts(text: str, cfg) -> list[int]:
  """`--devices`' counts for the run `cfg`, sorted (`dmcr_jax.benchmarks.learner.device_counts`
  with its K agents; only 1 with the device driver).

  Raises:
    ValueError: naming the valid counts.
  """
  import jax
  from dmcr_jax.benchmarks import learner
  from dmcr_jax.train import config
  counts = learner.device_counts(text, [len(cfg.agents())], jax.local_device_count())
  for n in counts:
    config.resolve(cfg, n)
  return counts


def _reached(r: dict) -> str:
  if r.get("step_at_threshold") is not None:
    return f"≥ {r['threshold']:g}: {r['step_at_threshold']:,}, {r['time_to_threshold_s']:.0f} s"
  return f"never ≥ {r['threshold']:g}"


def vector_step_ms(r: dict) -> dict | None:
  """A run's steady loop per vector step (one step of all `num_envs` envs of an
  agent), in milliseconds: "step" (wall time), "act", "env" (dispatch and wait),
  "store", and, where the env reports them, "physics" and "frames"; "updates" is
  what the learner alone needs for the step's `num_envs × utd` updates. None
  without a steady window (the device driver keeps no host breakdown)."""
  s = r.get("steady")
  if not s or not s.get("steps"):
    return None
  per = 1000.0 * r["num_envs"] / s["steps"]
  host, env = s.get("host_seconds", {}), s.get("env_seconds", {})
  out = dict(step=s["wall_s"] * per, act=host.get("act", 0.0) * per,
             env=(host.get("env_step_async", 0.0) + host.get("env_step_wait", 0.0)) * per,
             store=host.get("store", 0.0) * per)
  if "physics" in env and "render" in env:
    out.update(physics=env["physics"] * per, frames=env["render"] * per)
  if r.get("learner_updates_per_s"):
    out["updates"] = 1000.0 * r["num_envs"] * (r.get("utd") or 1.0) / r["learner_updates_per_s"]
  return out


def _vector_step_text(r: dict) -> str:
  ms = vector_step_ms(r)
  if ms is None:
    return "–"
  text = f"{ms['step']:.1f}: act {ms['act']:.1f}, env {ms['env']:.1f}"
  if "physics" in ms:
    text += f" (physics {ms['physics']:.1f}, frames {ms['frames']:.1f})"
  text += f", store {ms['store']:.1f}"
  return text + (f"; updates alone {ms['updates']:.1f}" if "updates" in ms else "")


def markdown(rows: list[dict]) -> str:
  """The rows as one Markdown table."""
  return R.table(rows, [
      ("device", "device"), ("task", "task"), ("renderer", lambda r: r.get("renderer", "pool")),
      ("physics", lambda r: r.get("physics", "–")),
      ("physics workers", lambda r: r.get("physics_workers", "–")),
      ("agents × envs",
       lambda r: f"{r['agents']} × {r['num_envs']}"),
      ("devices", lambda r: r.get("devices", "–")), ("steps", lambda r: f"{r['steps']:,}"),
      ("dtype", "dtype"),
      ("quality", lambda r: r["quality"] if r.get("renderer", "pool") == "pool" else "–"),
      ("loop wall s", lambda r: f"{r['wall_s']:,.1f}"),
      ("whole run s", lambda r: f"{r['process_s']:,.1f}"),
      ("transitions/s", lambda r: f"{r['transitions_per_s'] or 0:,.1f}"),
      ("steady transitions/s", lambda r: R.fmt(r.get("steady_transitions_per_s"), ",.1f")),
      ("total steady transitions/s", lambda r: R.fmt(r.get("total_transitions_per_s"), ",.1f")),
      ("scaling", lambda r: R.fmt(r.get("scaling_efficiency"), ".2f")),
      ("× one agent", lambda r: R.fmt(r.get("beside_one"), ".2f")),
      ("learner alone updates/s", lambda r: R.fmt(r.get("learner_updates_per_s"), ",.1f")),
      ("ratio", lambda r: R.fmt(r.get("ratio"), ".2f")),
      ("steady ms per vector step", _vector_step_text),
      ("first ≥ threshold (step, s)", _reached),
      ("final return", lambda r: R.fmt(r.get("final_return"), ".1f")),
      ("eval s (share)", lambda r: "–" if r.get("eval_share") is None else
       f"{r['eval_seconds']:,.1f} ({100 * r['eval_share']:.1f} %)"),
      ("UTC", lambda r: r["time_utc"][11:16])])


def headline(r: dict) -> str:
  """The suite headline's text for a run: its time, the steady rate against the
  learner alone, the final return and when it first reached the threshold."""
  text = f"{R.secs(r['wall_s'])} s for {r['steps']:,} steps"
  if r.get("ratio") is not None:
    text += (f", {r['steady_transitions_per_s']:,.1f} transitions/s steady against "
             f"{r['learner_updates_per_s']:,.1f} updates/s alone (ratio {r['ratio']:.2f})")
  if r.get("final_return") is not None:
    text += f", final return {r['final_return']:.1f}"
  if r.get("time_to_threshold_s") is not None:
    return text + f", ≥ {r['threshold']:g} after {r['time_to_threshold_s']:.0f} s"
  return text + f", never ≥ {r['threshold']:g}"


def suite_row(r: dict) -> dict:
  """The run's row with the suite's fields (`dmcr_jax.benchmarks.rows`)."""
  n = r.get("devices") or 1
  return R.row(r, f"{r['task']} {r['renderer']} {r['dtype']}"
               + (f" on {n} devices" if n > 1 else ""), n=r["num_envs"],
               throughput=r["transitions_per_s"], unit="transitions/s", run_s=r["wall_s"],
               headline=headline(r))


def main(argv=None) -> None:
  """Command-line entry: one run per device count, appended to --out, and the
  Markdown beside."""
  argv = sys.argv[1:] if argv is None else argv
  p = argparse.ArgumentParser(
      description=__doc__.splitlines()[0],
      allow_abbrev=False,
      epilog="Other arguments go to `train` (after the defaults "
             f"{' '.join(DEFAULT_TRAIN_ARGS)}, so they override them).")
  p.add_argument("--threshold", type=float, default=900.0,
                 help="the return whose first reaching is timed (default: %(default)s)")
  p.add_argument("--run-dir", default=None,
                 help="train's output folder, checkpoints included (default: a new folder "
                      "in the system's temporary folder; its log.csv and learning curve "
                      "are copied beside --out)")
  p.add_argument("--out", default=None, help="JSONL path (appended to); .md beside")
  p.add_argument("--no-baseline", action="store_true",
                 help="skip timing the learner alone (and the ratio)")
  p.add_argument("--devices", default=None,
                 help="comma-separated local device counts to shard the agents over, "
                      "one run each (e.g. 1,2,4,8; each must divide the number of "
                      "agents; default: one run on the devices train picks, all of them "
                      "when they divide the agents)")
  p.add_argument("--beside-one", action="store_true",
                 help="first train the run's first agent alone, then the run; the run's "
                      "row gets its total transitions/s over the one agent's")
  a, train_argv = p.parse_known_args(argv)
  if "--resume" in train_argv:
    p.error("--resume is not timed here: start a new run")
  if a.run_dir and os.path.exists(os.path.join(a.run_dir, "checkpoints")):
    p.error(f"--run-dir {a.run_dir} already holds a run; give a new folder")
  train_argv = list(DEFAULT_TRAIN_ARGS) + train_argv
  if a.beside_one:
    from dmcr_jax.train import __main__ as train_cli
    cfg, _ = train_cli.parse(train_argv)  # creates nothing
    if a.devices is not None:
      p.error("--beside-one and --devices: give one of them")
    if len(cfg.agents()) < 2:
      p.error("--beside-one: the run trains one agent; give several (e.g. --seeds 0,1,2 "
              "or --aug drq,cj+drq)")
    return _beside_one(a, argv, train_argv, first_agent_args(cfg))
  counts = [None]
  if a.devices is not None:
    from dmcr_jax.train import __main__ as train_cli
    cfg, _ = train_cli.parse(train_argv)  # creates nothing
    try:
      counts = check_device_counts(a.devices, cfg)
    except ValueError as e:
      p.error(f"--devices: {e}")
  from dmcr_jax.benchmarks.learner import scaling_efficiency
  several = len(counts) > 1
  rows, one = [], None
  for n in counts:  # ascending: the one-device run, if asked for, comes first
    run_dir = (os.path.join(a.run_dir, f"devices-{n}") if a.run_dir and several
               else a.run_dir or tempfile.mkdtemp(prefix="dmcr_train_bench_"))
    row = run(train_argv, a.threshold, run_dir, not a.no_baseline, devices=n)
    if several:
      one = row["total_transitions_per_s"] if n == 1 else one
      row["scaling_efficiency"] = scaling_efficiency(row["total_transitions_per_s"], one, n)
    row = suite_row(row)
    rows.append(row)
    if a.out:
      copy_outputs(run_dir, os.path.splitext(a.out)[0] + (f"_devices{n}" if several else ""))
    R.emit(row, a.out)
  _report(a.out, argv, rows)


def _report(out: str | None, argv, rows: list[dict]) -> None:
  """Prints the rows' table and rewrites the Markdown beside `out` from all its rows."""
  if out:
    R.write_markdown(out, f"Rows of `python -m dmcr_jax.benchmarks.training` appended to "
                     f"`{os.path.basename(out)}`; the last run: `python -m "
                     f"dmcr_jax.benchmarks.training {' '.join(argv)}` ({os.cpu_count()} cores).\n\n"
                     + markdown(R.read(out)))
  print(markdown(rows))


def _beside_one(a, argv, train_argv, one_args) -> None:
  """`main` with --beside-one: the first agent alone, then the run, one row each."""
  rows = []
  for label, args in (("one", train_argv + one_args), ("all", train_argv)):
    run_dir = (os.path.join(a.run_dir, f"agents-{label}") if a.run_dir
               else tempfile.mkdtemp(prefix="dmcr_train_bench_"))
    row = run(args, a.threshold, run_dir, not a.no_baseline)
    if rows and rows[0]["total_transitions_per_s"] and row["total_transitions_per_s"]:
      row["beside_one"] = row["total_transitions_per_s"] / rows[0]["total_transitions_per_s"]
    row = suite_row(row)
    rows.append(row)
    if a.out:
      copy_outputs(run_dir, os.path.splitext(a.out)[0] + f"_agents-{label}")
    R.emit(row, a.out)
  _report(a.out, argv, rows)


def copy_outputs(run_dir: str, stem: str) -> None:
  """The run's log.csv and learning curve copied to `<stem>_log.csv` and
  `<stem>_curve.png` (those that exist)."""
  os.makedirs(os.path.dirname(os.path.abspath(stem)), exist_ok=True)
  for name, suffix in (("log.csv", "_log.csv"), ("learning_curve.png", "_curve.png")):
    if os.path.exists(os.path.join(run_dir, name)):
      shutil.copyfile(os.path.join(run_dir, name), stem + suffix)


if __name__ == "__main__":
  main()
