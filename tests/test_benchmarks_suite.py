"""The benchmark suite's plumbing (`python -m benchmarks`), without running a benchmark.

Row normalisation for every benchmark's raw rows, the headline, summary and plot
from synthetic rows, a suite run of fake child commands (one fails, one runs past
its limit, the others still run and are collected), merging runs into one folder,
and the command line's errors.
"""

import json
import os
import sys

import pytest

from benchmarks import suite
from benchmarks.training import first_reaching

PY = sys.executable

RAW = {
    "physics": [dict(bench="physics", device="cpu", platform="cpu", task="walker-walk",
                     num_envs=n, control_steps=20, n_sub_steps=5, solver_iterations=100,
                     ls_iterations=16, compile_s=10.0, run_s=0.5,
                     physics_steps_per_s=1000.0 * n, bare_compile_s=9.0, bare_run_s=0.4,
                     bare_physics_steps_per_s=1250.0 * n, wrapper_speed_ratio=0.8,
                     time_utc="2026-11-23T10:00:00Z") for n in (1, 64)],
    "render": [dict(bench="render", device="none", task="walker-walk", size=84,
                    baseline_fps=60.0, vary="all", batch=b, workers=2, quality="fast",
                    gl="egl", start_s=3.0, run_s=b / 240.0, frames_per_s=240.0,
                    reference_equal=None, speedup=4.0) for b in (256, 1024)],
    "env": [dict(bench="env", device="cpu", platform="cpu", task="walker-walk", frame_skip=2,
                 image_size=84, kind="original", step_ms=20.0, rebuild_ms=100.0,
                 agent_steps_per_s=40.0, agent_steps_per_s_no_rebuild=50.0,
                 time_utc="2026-11-23T10:00:00Z"),
            dict(bench="env", device="cpu", platform="cpu", task="walker-walk", frame_skip=2,
                 image_size=84, kind="env", num_envs=16, quality="fastest", workers=2,
                 steps=10, copy_obs=True, ls_iterations="default", start_s=2.0,
                 warmup_s=12.0, step_ms=80.0, agent_steps_per_s=200.0, other_ms=1.0,
                 physics_ms=30.0, transfer_ms=1.0, render_ms=45.0, copy_ms=3.0,
                 original_agent_steps_per_s=40.0, speedup=5.0,
                 time_utc="2026-11-23T10:00:00Z")],
    "jax_render": [dict(bench="jax_render", device="cpu", backend="cpu", task="walker-walk",
                        size=84, vary="all", batch=1024, chunk=1024, shadows=True,
                        reflection=True, objects=8, compile_s=39.0, run_s=0.02,
                        frames_per_s=51200.0),
                   dict(bench="jax_env", device="cpu", backend="cpu", task="walker-walk",
                        size=84, vary="all", batch=1024, chunk=1024, shadows=True,
                        reflection=False, frame_skip=2, frame_stack=3, objects=8,
                        compile_s=68.0, scan_compile_s=49.0, step_s=0.125, scan_step_s=0.1,
                        agent_steps_per_s=8192.0, scan_agent_steps_per_s=10240.0)],
    "augment": [dict(name="drq", device_kind="cpu", platform="cpu", batch=256,
                     shape=[256, 84, 84, 9], compile_s=1.0, median_ms=40.0, p10_ms=39.0,
                     p90_ms=45.0, pair_median_ms=75.0, time_utc="2026-11-23T10:00:00Z")],
    "learner": [dict(kind="python_loop", agents=1, dtype="float32", agent_loop="-",
                     batch=256, pairs_per_call=0, compile_s=5.0, ms_per_call=10.0,
                     updates_per_s_per_agent=100.0, agent_updates_per_s=100.0,
                     device_kind="cpu", platform="cpu", size=84, stack=3,
                     time_utc="2026-11-23T10:00:00Z"),
                dict(kind="scanned", agents=8, dtype="bfloat16", agent_loop="map", batch=256,
                     pairs_per_call=25, compile_s=12.0, ms_per_call=1000.0,
                     updates_per_s_per_agent=50.0, agent_updates_per_s=400.0,
                     x_baseline=4.0, device_kind="cpu", platform="cpu", size=84, stack=3,
                     time_utc="2026-11-23T10:00:00Z")],
    "step_profile": [dict(bench="step_profile", device="cpu", platform="cpu",
                          task="walker-walk", num_envs=1024, quality="fastest", workers=16,
                          frame_skip=2, batch=256, utd=1.0, dtype="float32", compile_s=50.0,
                          parts_ms=dict(physics=60.0, render=60.0, update=4000.0),
                          shares=dict(physics=0.015, render=0.015, update=0.97),
                          per_update_ms=3.9, updates_per_agent_step=1024, total_ms=4120.0,
                          env_agent_steps_per_s=8533.0, collect_agent_steps_per_s=8000.0,
                          train_agent_steps_per_s=248.5, stack_one_process_ms=10.0,
                          time_utc="2026-11-23T10:00:00Z")],
    "train": [dict(bench="train", device="cpu", platform="cpu", task="cartpole-balance",
                   steps=50000, agents=1, num_envs=16, quality="exact", dtype="bfloat16",
                   batch_size=256, wall_s=367.0, process_s=380.0, transitions_per_s=136.2,
                   final_return=956.8, threshold=900.0, step_at_threshold=6032,
                   time_to_threshold_s=112.0, time_utc="2026-11-23T10:00:00Z")],
}


def _all_rows():
  return [r for bench, raw in RAW.items() for r in suite.normalise(bench, raw)]


def test_normalise_every_benchmark_has_the_common_keys():
  rows = _all_rows()
  assert {r["benchmark"] for r in rows} == set(RAW)
  for r in rows:
    assert set(suite.ROW_KEYS) <= set(r), r
    assert r["device"] == "cpu"  # render's "none" (no NVIDIA GPU) included
    assert r["throughput"] > 0 and r["unit"]
    if r["baseline"]:
      assert r["ratio"] == pytest.approx(r["throughput"] / r["baseline_throughput"])


def test_normalise_baselines_and_ratios():
  physics = suite.normalise("physics", RAW["physics"])
  assert [r["is_baseline"] for r in physics] == [False, True, False, True]
  assert physics[0]["ratio"] == pytest.approx(0.8)
  assert physics[1]["variant"] == "walker-walk bare MJX" and physics[1]["compile_s"] == 9.0
  render = suite.normalise("render", RAW["render"])
  base = [r for r in render if r["is_baseline"]]
  assert len(base) == 1 and base[0]["throughput"] == 60.0  # one naive loop per run
  assert [r["ratio"] for r in render if not r["is_baseline"]] == [4.0, 4.0]
  env = suite.normalise("env", RAW["env"])
  assert env[0]["is_baseline"] and env[0]["variant"] == "original DMCR pipeline"
  assert env[1]["ratio"] == 5.0 and env[1]["compile_s"] == pytest.approx(10.0)
  assert env[1]["extra"]["parts_ms"]["render"] == 45.0
  (aug,) = suite.normalise("augment", RAW["augment"])
  assert aug["throughput"] == pytest.approx(256 / 0.04) and aug["baseline"] is None
  frames, step, scanned = suite.normalise("jax_render", RAW["jax_render"])
  assert frames["variant"] == "frames (shadows, reflection)" and frames["unit"] == "frames/s"
  assert (step["variant"], step["throughput"], step["compile_s"]) == (
      "env, env.step (shadows)", 8192.0, 68.0)
  assert (scanned["unit"], scanned["run_s"], scanned["compile_s"]) == (
      "agent-steps/s", 0.1, 49.0)
  learner = suite.normalise("learner", RAW["learner"])
  assert learner[0]["is_baseline"] and learner[1]["baseline_throughput"] == 100.0
  assert learner[1]["variant"] == "K=8 bfloat16 map" and learner[1]["ratio"] == 4.0
  sharded = suite.normalise("learner", [dict(RAW["learner"][1], devices=2)])
  assert sharded[0]["variant"] == "K=8 bfloat16 map on 2 devices"


def test_normalise_drops_bad_rows_and_passes_normalised_ones(capsys):
  rows = suite.normalise("physics", RAW["physics"] + [{"task": "walker-walk"}])
  assert len(rows) == 4
  assert "dropped a physics row" in capsys.readouterr().err
  done = suite.make_row("physics", "x", device="cpu", batch=4, throughput=8.0, unit="u/s",
                        baseline_throughput=2.0)
  assert suite.normalise("physics", [done])[0]["ratio"] == 4.0
  with pytest.raises(ValueError, match="choose from: physics, render"):
    suite.normalise("nope", [])


def test_headline_summary_and_plot(tmp_path):
  rows = _all_rows()
  picked = suite.headline(rows)
  physics = [r for r in picked if r["benchmark"] == "physics"]
  assert len(physics) == 1 and physics[0]["batch"] == 64  # the largest batch
  assert not any(r["is_baseline"] for r in picked)
  results = [dict(name="physics", benchmark="physics", argv=[], status="ok", returncode=0,
                  wall_s=1.0, rows=2, tail=[], time_utc=""),
             dict(name="render", benchmark="render", argv=[], status="failed", returncode=1,
                  wall_s=1.0, rows=0, tail=["Traceback", "RuntimeError: no GL | here"],
                  time_utc="")]
  meta = dict(commands=[dict(command="python -m benchmarks --quick", mode="quick",
                             time_utc="2026-11-23T10:00:00+00:00", wall_s=12.0, cpus=2,
                             host="h")])
  md = suite.summary_markdown(rows, results, meta)
  for text in ("## Headline", "physics steps/s", "frames/s", "agent-steps/s with pixels",
               "updates/s", "end-to-end training", "367 s for 50,000 steps",
               "≥ 900 after 112 s", "one agent step", "## Jobs", "RuntimeError: no GL \\| here",
               "## step_profile", "Time per agent step", "python -m benchmarks --quick"):
    assert text in md, text
  png = tmp_path / "t.png"
  assert suite.plot_throughput(rows, str(png))
  assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
  assert not suite.plot_throughput([], str(tmp_path / "none.png"))


def _writer(row: dict) -> tuple:
  """A fake benchmark: appends `row` to its --out path and prints a line."""
  code = ("import json, sys; open(sys.argv[1], 'a').write(json.dumps(%r) + '\\n'); "
          "print('wrote a row')" % (row,))
  return (PY, "-c", code, suite.OUT_PLACEHOLDER)


def test_failing_and_hanging_children_are_reported_and_others_run(tmp_path):
  jobs = [suite.Job("physics", "physics", (PY, "-c", "import sys; print('boom'); sys.exit(3)"),
                    30),
          suite.Job("render", "render", (PY, "-c", "import time; time.sleep(60)"), 1.5),
          suite.Job("augment", "augment", _writer(RAW["augment"][0]), 30),
          suite.Job("learner", "learner", (PY, "-c", "pass"), 30)]
  state = suite.run_suite(jobs, str(tmp_path), "quick", "test", progress=False)
  status = {n: (r["status"], r["returncode"], r["rows"]) for n, r in state["jobs"].items()}
  assert status == {"physics": ("failed", 3, 0), "render": ("timeout", None, 0),
                    "augment": ("ok", 0, 1), "learner": ("no rows", 0, 0)}
  assert state["jobs"]["physics"]["tail"][-1] == "boom"
  assert state["jobs"]["render"]["wall_s"] < 20
  rows = suite.read_jsonl(str(tmp_path / "benchmarks.jsonl"))
  assert [(r["benchmark"], r["job"], r["mode"]) for r in rows] == [("augment", "augment", "quick")]
  md = (tmp_path / "summary.md").read_text()
  assert "| physics | failed | 3 |" in md and "`boom`" in md and "| render | timeout |" in md
  assert (tmp_path / "throughput.png").exists()
  assert "boom" in (tmp_path / "logs" / "physics.log").read_text()

  # A second run into the same folder replaces its jobs and keeps the others.
  again = [suite.Job("physics", "physics", _writer(RAW["physics"][0]), 30)]
  state = suite.run_suite(again, str(tmp_path), "quick", "test 2", progress=False)
  assert state["jobs"]["physics"]["status"] == "ok" and "augment" in state["jobs"]
  assert len(state["commands"]) == 2
  benches = {r["benchmark"] for r in suite.read_jsonl(str(tmp_path / "benchmarks.jsonl"))}
  assert benches == {"physics", "augment"}

  # Outputs rebuilt without a job's raw rows (a folder copied without raw/) keep
  # its rows; a re-run of that job that writes none drops them.
  os.remove(suite.raw_path(str(tmp_path), "augment"))
  suite.write_outputs(str(tmp_path), state)
  jobs_of = lambda: {r["job"] for r in suite.read_jsonl(str(tmp_path / "benchmarks.jsonl"))}
  assert jobs_of() == {"physics", "augment"}
  suite.run_suite([suite.Job("augment", "augment", (PY, "-c", "pass"), 30)], str(tmp_path),
                  "quick", "test 3", progress=False)
  assert jobs_of() == {"physics"}


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
  assert suite.device_slug("NVIDIA H100 80GB HBM3") == "h100" and suite.device_slug(None) == "cpu"


def test_step_profile_breakdown_and_training_threshold():
  from benchmarks.step_profile import breakdown
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
