"""The benchmark suite's plumbing (`python -m dmcr_jax.benchmarks`), without running a benchmark.

The one row format (`dmcr_jax.benchmarks.rows`: the row, timing, the table writer), the rows
the benchmarks build, the headline, summary and plot from such rows, a suite run of
fake child commands (one fails, one runs past its limit, the others still run and are
collected), merging runs into one folder, and the command line's errors.
"""

import json
import os
import sys

import pytest

from dmcr_jax.benchmarks import report, suite
from dmcr_jax.benchmarks import rows as R
from dmcr_jax.benchmarks.training import first_reaching

PY = sys.executable
CPU = dict(device="cpu", platform="cpu", time_utc="2026-11-23T10:00:00Z")


def _rows() -> dict[str, list[dict]]:
  """Rows of every benchmark as its module writes them (built by its own helpers
  where it has them)."""
  from dmcr_jax.benchmarks import env, jax_render, learner, training
  physics = [R.row(dict(CPU, task="walker-walk", num_envs=n, compile_s=10.0, run_s=0.5,
                        physics_steps_per_s=1000.0 * n, bare_compile_s=9.0),
                   "walker-walk", n=n, throughput=1000.0 * n, unit="physics steps/s",
                   compile_s=10.0, run_s=0.5, baseline="walker-walk bare MJX",
                   baseline_throughput=1250.0 * n) for n in (1, 64)]
  render = [R.row(dict(device="cpu", quality="fast", workers=2, batch=b), "fast, 2 workers",
                  n=b, throughput=240.0, unit="frames/s", compile_s=3.0, run_s=b / 240.0,
                  baseline="naive mujoco.Renderer loop", baseline_throughput=60.0)
            for b in (256, 1024)]
  own = dict(CPU, kind="env", num_envs=16, quality="fastest", copy_obs=False,
             ls_iterations=4, parts_ms=dict(physics=30.0, render=45.0))
  envs = [R.row(dict(CPU, kind="original"), "original DMCR pipeline", n=1, throughput=40.0,
                unit="agent-steps/s", run_s=0.02, is_baseline=True),
          R.row(own, env.variant(own), n=16, throughput=200.0, unit="agent-steps/s",
                compile_s=10.0, run_s=0.08, baseline="original DMCR pipeline",
                baseline_throughput=40.0)]
  shape = dict(CPU, task="walker-walk", size=84, batch=1024, chunk=1024, shadows=True)
  jax_rows = (jax_render.suite_rows(dict(shape, bench="jax_render", reflection=True,
                                         compile_s=39.0, run_s=0.02, frames_per_s=51200.0))
              + jax_render.suite_rows(dict(shape, bench="jax_env", reflection=False,
                                           compile_s=68.0, scan_compile_s=49.0, step_s=0.125,
                                           scan_step_s=0.1, agent_steps_per_s=8192.0,
                                           scan_agent_steps_per_s=10240.0)))
  augment = [R.row(dict(CPU, name="drq", batch=256), "drq", n=256, throughput=6400.0,
                   unit="images/s", compile_s=1.0, run_s=0.04)]
  loop = dict(CPU, kind="python_loop", agents=1, dtype="float32", agent_loop="-")
  scanned = dict(CPU, kind="scanned", agents=8, dtype="bfloat16", agent_loop="map")
  learners = [R.row(loop, learner.variant(loop), n=256, throughput=100.0,
                    unit="agent-updates/s", compile_s=5.0, run_s=0.01, is_baseline=True),
              R.row(scanned, learner.variant(scanned), n=256, throughput=400.0,
                    unit="agent-updates/s", compile_s=12.0, run_s=1.0,
                    baseline=learner.PYTHON_LOOP, baseline_throughput=100.0)]
  profile = [R.row(dict(CPU, num_envs=1024, parts_ms=dict(physics=60.0, update=4000.0)),
                   "walker-walk fastest", n=1024, throughput=248.5,
                   unit="agent-steps/s with updates", compile_s=50.0, run_s=4.12,
                   headline="4,120.0 ms per agent step")]
  train = [training.suite_row(dict(
      CPU, task="cartpole-balance", renderer="pool", dtype="bfloat16", steps=50000, agents=1,
      num_envs=16, wall_s=367.0, transitions_per_s=136.2, steady_transitions_per_s=150.0,
      learner_updates_per_s=300.0, ratio=0.5, final_return=956.8, threshold=900.0,
      time_to_threshold_s=112.0))]
  return dict(physics=physics, render=render, env=envs, jax_render=jax_rows, augment=augment,
              learner=learners, step_profile=profile, train=train)


def _all_rows():
  return [dict(r, benchmark=b) for b, rows in _rows().items() for r in rows]


def test_a_row_holds_the_suite_fields_beside_the_benchmarks_own():
  r = R.row(dict(device="cpu", task="t", compile_s=1.0), "v", n=4, throughput=8.0, unit="u/s")
  assert set(R.FIELDS) <= set(r) and r["task"] == "t" and r["compile_s"] is None
  assert r["platform"] is None and r["time_utc"] and "headline" not in r
  assert R.row(dict(CPU), "v", n=None, throughput=1.0, unit="u", headline="h")["headline"] == "h"
  for bench, rows in _rows().items():
    for r in rows:
      assert set(R.FIELDS) <= set(r), (bench, r)
      assert r["throughput"] > 0 and r["unit"] and r["device"] == "cpu"


def test_benchmarks_name_their_variants_and_split_their_measurements():
  from dmcr_jax.benchmarks import env, learner
  rows = _rows()
  assert rows["env"][1]["variant"] == "fastest, no copy, line search 4"
  assert learner.variant(dict(kind="scanned", agents=8, dtype="bfloat16", agent_loop="map",
                              devices=2)) == "K=8 bfloat16 map on 2 devices"
  assert learner.variant(dict(kind="scanned", algo="curl", agents=1, dtype="float32",
                              agent_loop="vmap")) == "curl K=1 float32"
  assert env.variant(dict(quality="ray caster", renderer="jax", obs_on_device=True)) == (
      "ray caster, obs on device")
  frames, step, scanned = rows["jax_render"]
  assert frames["variant"] == "frames (shadows, reflection)" and frames["unit"] == "frames/s"
  assert (step["variant"], step["throughput"], step["compile_s"], step["run_s"]) == (
      "env, env.step (shadows)", 8192.0, 68.0, 0.125)
  assert (scanned["variant"], scanned["run_s"], scanned["compile_s"]) == (
      "env, scanned (shadows)", 0.1, 49.0)
  assert "agent_steps_per_s" not in scanned and scanned["task"] == "walker-walk"
  (train,) = rows["train"]
  assert train["variant"] == "cartpole-balance pool bfloat16" and train["ratio"] == 0.5
  assert train["headline"].startswith("367 s for 50,000 steps, 150.0 transitions/s steady")
  assert train["headline"].endswith("final return 956.8, ≥ 900 after 112 s")


def test_timing_keeps_compilation_apart_and_counts_calls():
  calls = []
  timing = R.measure(lambda: calls.append(len(calls)), repeats=4, warmup=1)
  assert len(calls) == 6 and len(timing.times) == 4  # first (compile) + warm-up + 4
  assert timing.compile_s >= 0 and timing.run_s >= 0
  assert len(R.time_calls(lambda: None, repeats=2, seconds=10.0, max_calls=5)) == 5
  assert R.Timing(0.0, (1.0, 2.0, 3.0, 4.0, 5.0)).percentile(90) == pytest.approx(4.6)


def test_the_table_writer_aligns_numbers_and_marks_missing_cells():
  table = R.table([dict(a="x", b=1.5), dict(a="y", b=None)], [("name", "a"), ("value", "b")])
  assert table.splitlines() == ["| name | value |", "|---|---:|", "| x | 1.5 |", "| y | – |"]
  assert R.num(12345.6) == "12,346" and R.secs(0.01234) == "0.0123" and R.fmt(None, ".1f") == "–"
  assert R.device_slug("NVIDIA H100 80GB HBM3") == "h100" and R.device_slug(None) == "cpu"


def test_a_table_beside_rows_never_replaces_a_hand_written_file(tmp_path, capsys):
  out = str(tmp_path / "train_h200.jsonl")
  assert R.write_markdown(out, "table 1") == str(tmp_path / "train_h200.md")
  assert R.write_markdown(out, "table 2") == str(tmp_path / "train_h200.md")   # its own: rewritten
  assert (tmp_path / "train_h200.md").read_text().splitlines()[1:] == ["table 2"]
  (tmp_path / "train_h200.md").write_text("Analysis written by hand.\n")
  assert R.write_markdown(out, "table 3") == str(tmp_path / "train_h200_table.md")
  assert (tmp_path / "train_h200.md").read_text() == "Analysis written by hand.\n"
  assert (tmp_path / "train_h200_table.md").read_text().endswith("table 3")
  assert "train_h200_table.md" in capsys.readouterr().err


def test_headline_summary_and_plot(tmp_path):
  rows = _all_rows()
  picked = report.headline(rows)
  physics = [r for r in picked if r["benchmark"] == "physics"]
  assert len(physics) == 1 and physics[0]["n"] == 64  # the largest N
  assert not any(r["is_baseline"] for r in picked)
  assert report.ratio(physics[0]) == pytest.approx(0.8)
  results = [dict(name="physics", benchmark="physics", argv=[], status="ok", returncode=0,
                  wall_s=1.0, rows=2, tail=[], time_utc=""),
             dict(name="render", benchmark="render", argv=[], status="failed", returncode=1,
                  wall_s=1.0, rows=0, tail=["Traceback", "RuntimeError: no GL | here"],
                  time_utc="")]
  meta = dict(commands=[dict(command="python -m dmcr_jax.benchmarks --quick", mode="quick",
                             time_utc="2026-11-23T10:00:00+00:00", wall_s=12.0, cpus=2,
                             host="h")])
  md = report.summary_markdown(rows, results, meta)
  for text in ("## Headline", "physics steps/s", "frames/s", "agent-steps/s with pixels",
               "updates/s", "end-to-end training", "367 s for 50,000 steps",
               "≥ 900 after 112 s", "one agent step", "4,120.0 ms per agent step", "## Jobs",
               "RuntimeError: no GL \\| here", "## step_profile", "Time per agent step",
               "python -m dmcr_jax.benchmarks --quick", "original DMCR pipeline (baseline)",
               "walker-walk bare MJX: 80,000 | 0.8 |"):
    assert text in md, text
  png = tmp_path / "t.png"
  assert report.plot_throughput(rows, str(png))
  assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
  assert not report.plot_throughput([], str(tmp_path / "none.png"))


def _writer(row: dict) -> tuple:
  """A fake benchmark: appends `row` to its --out path and prints a line."""
  code = ("import json, sys; open(sys.argv[1], 'a').write(json.dumps(%r) + '\\n'); "
          "print('wrote a row')" % (row,))
  return (PY, "-c", code, suite.OUT_PLACEHOLDER)


def test_failing_and_hanging_children_are_reported_and_others_run(tmp_path):
  jobs = [suite.Job("physics", "physics", (PY, "-c", "import sys; print('boom'); sys.exit(3)"),
                    30),
          suite.Job("render", "render", (PY, "-c", "import time; time.sleep(60)"), 1.5),
          suite.Job("augment", "augment", _writer(_rows()["augment"][0]), 30),
          suite.Job("learner", "learner", (PY, "-c", "pass"), 30)]
  state = suite.run_suite(jobs, str(tmp_path), "quick", "test", progress=False)
  status = {n: (r["status"], r["returncode"], r["rows"]) for n, r in state["jobs"].items()}
  assert status == {"physics": ("failed", 3, 0), "render": ("timeout", None, 0),
                    "augment": ("ok", 0, 1), "learner": ("no rows", 0, 0)}
  assert state["jobs"]["physics"]["tail"][-1] == "boom"
  assert state["jobs"]["render"]["wall_s"] < 20
  rows = R.read(str(tmp_path / "benchmarks.jsonl"))
  assert [(r["benchmark"], r["job"], r["mode"]) for r in rows] == [("augment", "augment", "quick")]
  md = (tmp_path / "summary.md").read_text()
  assert "| physics | failed | 3 |" in md and "`boom`" in md and "| render | timeout |" in md
  assert (tmp_path / "throughput.png").exists()
  assert "boom" in (tmp_path / "logs" / "physics.log").read_text()

  # A second run into the same folder replaces its jobs and keeps the others.
  again = [suite.Job("physics", "physics", _writer(_rows()["physics"][0]), 30)]
  state = suite.run_suite(again, str(tmp_path), "quick", "test 2", progress=False)
  assert state["jobs"]["physics"]["status"] == "ok" and "augment" in state["jobs"]
  assert len(state["commands"]) == 2
  benches = {r["benchmark"] for r in R.read(str(tmp_path / "benchmarks.jsonl"))}
  assert benches == {"physics", "augment"}

  # Outputs rebuilt without a job's raw rows (a folder copied without raw/) keep
  # its rows; a re-run of that job that writes none drops them.
  os.remove(suite.raw_path(str(tmp_path), "augment"))
  suite.write_outputs(str(tmp_path), state)
  jobs_of = lambda: {r["job"] for r in R.read(str(tmp_path / "benchmarks.jsonl"))}
  assert jobs_of() == {"physics", "augment"}
  suite.run_suite([suite.Job("augment", "augment", (PY, "-c", "pass"), 30)], str(tmp_path),
                  "quick", "test 3", progress=False)
  assert jobs_of() == {"physics"}


def test_rows_of_an_older_suite_folder_are_kept_in_todays_shape(tmp_path):
  # A folder written before the one row format: raw rows without the suite's
  # fields, its benchmarks.jsonl rows with their settings in "sizes" and "extra".
  os.makedirs(tmp_path / "raw")
  (tmp_path / "raw" / "train.jsonl").write_text(json.dumps(dict(bench="train", wall_s=1.0)) + "\n")
  old = dict(benchmark="train", variant="cartpole-balance", device="cpu", platform="cpu",
             batch=16, sizes=dict(task="cartpole-balance", steps=100, batch=256),
             compile_s=None, run_s=1.0, throughput=100.0, unit="transitions/s", baseline=None,
             baseline_throughput=None, ratio=None, is_baseline=False,
             extra=dict(ratio=0.5), time_utc="t", job="train", mode="quick")
  (tmp_path / "benchmarks.jsonl").write_text(json.dumps(old) + "\n")
  state = dict(commands=[], jobs=dict(train=dict(benchmark="train", rows=1, mode="quick")))
  (row,) = suite.collect(str(tmp_path), state)
  assert (row["n"], row["batch"], row["steps"], row["ratio"]) == (16, 16, 100, 0.5)


def test_only_names_the_valid_choices(capsys):
  assert suite.parse_only(None) == suite.BENCHMARKS
  assert suite.parse_only("env,physics") == ("physics", "env")
  with pytest.raises(SystemExit) as exc:
    suite.main(["--only", "physics,rendering", "--dry-run"])
  assert exc.value.code == 2
  err = capsys.readouterr().err
  assert "'rendering'" in err and "choose from: " + ", ".join(suite.BENCHMARKS) in err
  with pytest.raises(SystemExit):
    suite.main(["--timeout", "0", "--dry-run"])
  assert suite.parse_only("env-exact,physics") == ("physics", "env-exact")
  assert [j.name for j in suite.plan("full", ["env-exact", "augment"])] == [
      "env-exact", "augment", "augment-b64", "augment-b1024"]
  with pytest.raises(ValueError, match="env-fastest, env-exact, env-target"):
    suite.parse_only("env-slow")
  with pytest.raises(ValueError, match="'env-exact' in --only"):
    suite.parse_only("env-exact", "quick")  # quick mode runs env as one job


def test_plans_cover_every_benchmark(tmp_path, capsys):
  for mode in suite.MODES:
    jobs = suite.plan(mode, cpus=16)
    assert {j.benchmark for j in jobs} == set(suite.BENCHMARKS)
    assert len({j.name for j in jobs}) == len(jobs)
    for j in jobs:
      assert j.argv[-2:] == ("--out", suite.OUT_PLACEHOLDER)
      assert j.timeout_s == suite.DEFAULT_TIMEOUT_S[mode]
  full = {j.name: " ".join(j.argv) for j in suite.plan("full", cpus=16)}
  assert "--sizes 1,64,1024,8192" in full["physics"] and "--workers 16" in full["render"]
  assert "--sizes 1024,256,16,1" in full["env-fastest"]
  assert "--renderers pool,jax" in full["env-target"] and "--ls-iterations 4" in full["env-target"]
  assert "--agents 1,8" in full["learner"] and "--batch 256" in full["learner"]
  assert "--algos curl,sac_ae" in full["learner-algos"]
  assert "--sizes 1024" in full["step_profile"]
  assert [j.timeout_s for j in suite.plan("quick", ["env"], timeout_s=5)] == [5.0]
  assert suite.main(["--quick", "--only", "env", "--dry-run", "--out", str(tmp_path)]) == 0
  assert str(tmp_path / "raw" / "env.jsonl") in capsys.readouterr().out


def test_step_profile_breakdown_and_training_threshold():
  from dmcr_jax.benchmarks.step_profile import breakdown
  b = breakdown(dict(physics=60.0, render=40.0, act=10.0, update=900.0), num_envs=1000)
  assert b["total_ms"] == pytest.approx(1010.0)
  assert b["env_agent_steps_per_s"] == pytest.approx(10_000.0)
  assert b["collect_agent_steps_per_s"] == pytest.approx(1000 / 0.11)
  assert b["train_agent_steps_per_s"] == pytest.approx(1000 / 1.01)
  assert sum(b["shares"].values()) == pytest.approx(1.0)
  log = [dict(step="100", wall_s="5", episode_return="300"),
         dict(step="300", wall_s="9", episode_return="950"),
         dict(step="200", wall_s="7", episode_return="920")]
  assert first_reaching(log, 900) == dict(step=200, wall_s=7.0, episode_return=920.0)
  assert first_reaching(log, 990) is None


def test_the_steady_rate_is_between_episode_ends_else_over_the_summarys_window():
  from dmcr_jax.benchmarks.training import steady_rate
  log = [dict(step="100", wall_s="5"), dict(step="300", wall_s="9"),
         dict(step="200", wall_s="7")]
  window = dict(steps=2016, wall_s=4.0)
  assert steady_rate(log, 50, window) == pytest.approx(200 / 4)    # ends at 100 and 300
  assert steady_rate(log, 250, window) == pytest.approx(2016 / 4)  # one end past 250
  assert steady_rate(log, 250) is None
  assert steady_rate(log, 250, dict(steps=0, wall_s=0.0)) is None


def test_training_rows_break_a_steady_vector_step_down():
  from dmcr_jax.benchmarks.training import markdown, vector_step_ms
  steady = dict(steps=16000, wall_s=50.0,
                host_seconds=dict(act=3.0, env_step_async=1.0, env_step_wait=44.0, store=1.5),
                env_seconds=dict(physics=32.0, render=12.0))
  r = dict(num_envs=32, utd=1.0, learner_updates_per_s=400.0, steady=steady)
  ms = vector_step_ms(r)   # 500 vector steps of 32 envs
  assert ms == pytest.approx(dict(step=100.0, act=6.0, env=90.0, store=3.0, physics=64.0,
                                  frames=24.0, updates=80.0))
  assert vector_step_ms(dict(num_envs=32)) is None   # the device driver: no breakdown
  assert "100.0: act 6.0, env 90.0 (physics 64.0, frames 24.0), store 3.0; updates alone 80.0" \
      in markdown([dict(r, device="d", task="t", agents=1, steps=24000, dtype="bfloat16",
                        quality="exact", wall_s=1.0, process_s=2.0, transitions_per_s=3.0,
                        threshold=900.0, time_utc="2026-11-28T19:15:33")])


def test_beside_one_trains_the_first_agent_alone_then_the_run(monkeypatch, tmp_path, capsys):
  from dmcr_jax.benchmarks import training
  from dmcr_jax.train import __main__ as train_cli
  argv = ["--seeds", "3,4", "--aug", "drq,cj+drq", "--visual-seeds", "levels:10,100"]
  cfg, _ = train_cli.parse(argv)
  one = training.first_agent_args(cfg)
  alone, _ = train_cli.parse(argv + one)
  assert alone.agents() == cfg.agents()[:1] == [(3, "drq")]
  assert alone.agent_looks() == cfg.agent_looks()[:1]
  assert training.first_agent_args(alone) == []
  runs = []

  def fake_run(train_argv, threshold, run_dir, baseline=True, devices=None):
    k = len(train_cli.parse(train_argv)[0].agents())
    runs.append(k)
    return dict(total_transitions_per_s=100.0 * (1 + k), agents=k, num_envs=4, task="t",
                device="d", renderer="jax", dtype="bfloat16", transitions_per_s=1.0,
                wall_s=1.0, process_s=2.0, steps=10, threshold=900.0,
                time_utc="2026-12-02T15:00:00")
  monkeypatch.setattr(training, "run", fake_run)
  out = str(tmp_path / "t.jsonl")
  training.main(argv + ["--beside-one", "--no-baseline", "--out", out])
  rows = training.R.read(out)
  assert runs == [1, 8]                            # the one agent first, then all 8
  assert "beside_one" not in rows[0] and rows[1]["beside_one"] == pytest.approx(900 / 200)
  for bad, why in ((["--seeds", "0"], "the run trains one agent"),
                   (argv + ["--devices", "1"], "give one of them")):
    with pytest.raises(SystemExit):
      training.main(bad + ["--beside-one"])
    assert why in capsys.readouterr().err
  assert runs == [1, 8]                            # refused before anything trains
