"""`--devices` of `dmcr_jax.benchmarks.learner` and `dmcr_jax.benchmarks.training`: the agents sharded
over several local devices (forced host CPU devices), the scaling rows, and the
refusal of device counts that cannot shard the agents."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

from dmcr_jax.benchmarks import learner, training
from dmcr_jax.train import devices as devs

TINY_NETS = dict(conv_channels=4, feature_dim=8, hidden_dim=16)
"""Networks small enough to build and compile in seconds on a CPU (the subprocesses
patch `dmcr_jax.train.sac.SACConfig` with them)."""


def run_on_cpu_devices(script: str, devices: int = 2, timeout: int = 300) -> str:
  """`script` in a fresh Python with `devices` forced host CPU devices (the flag
  must be set before JAX starts; the session's compile flags are kept); its stdout,
  asserting it ended with "ok"."""
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}"
  env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=flags.strip(),
             PYTHONPATH=os.pathsep.join([root] + [p for p in [os.environ.get("PYTHONPATH")]
                                                  if p]))
  out = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True,
                       text=True, env=env, timeout=timeout, cwd=root)
  assert out.returncode == 0 and out.stdout.strip().endswith("ok"), (
      out.stdout[-2000:] + out.stderr[-3000:])
  return out.stdout


def test_device_counts_are_parsed_sorted_and_bad_ones_name_the_valid_choices():
  assert learner.device_counts("4,1,2,2", [8, 4], 8) == [1, 2, 4]
  assert devs.valid_device_counts(6, 8) == [1, 2, 3, 6]
  for text, agents, why in [
      ("16", [8], "16 devices: more than the local devices"),
      ("3", [8], "K = 8 agents is not a multiple of 3"),
      ("2", [1, 8], "K = 1 agents is not a multiple of 2"),
      ("0", [8], "'0' is not a positive device count"),
      ("two", [8], "'two' is not a positive device count")]:
    with pytest.raises(ValueError, match="valid counts for K = ") as e:
      learner.device_counts(text, agents, 8)
    assert why in str(e.value)
  with pytest.raises(ValueError) as e:
    learner.device_counts("2", [1, 8], 8)
  assert str(e.value).endswith("on 8 local devices: 1")
  with pytest.raises(ValueError, match="valid counts for 6 agents: 1, 2, 3, 6"):
    devs.check_devices(4, 6, 8)
  assert devs.mesh_devices(6, None, 4) == 1 and devs.mesh_devices(8, None, 4) == 4
  assert devs.mesh_devices(8, 2, 4) == 2


def test_train_says_why_it_uses_one_of_several_devices():
  assert "the 3 agents are not a multiple of 2" in devs.one_device_note(3, 2, None, False)
  assert "device driver" in devs.one_device_note(4, 2, None, True)
  assert devs.one_device_note(4, 2, None, False) is None   # sharded over both
  assert devs.one_device_note(3, 2, 1, False) is None      # one asked for
  assert devs.one_device_note(3, 1, None, False) is None   # one there


def test_train_says_how_to_draw_the_pools_frames_on_an_idle_gpu():
  note = devs.shared_frames_note("pool", None, "gpu", 2, 1)
  assert "--egl-devices 1" in note and "1 of the 2 GPUs stay idle" in note
  assert "--egl-devices 2" in devs.shared_frames_note("pool", None, "gpu", 4, 2)
  assert devs.shared_frames_note("pool", None, "gpu", 2, 2) is None    # learner on both
  assert devs.shared_frames_note("pool", (1,), "gpu", 2, 1) is None    # already chosen
  assert devs.shared_frames_note("jax", None, "gpu", 2, 1) is None     # no EGL frames
  assert devs.shared_frames_note("pool", None, "cpu", 2, 1) is None    # no learner GPU


def test_scaling_efficiency_is_the_rate_over_devices_times_the_one_device_rate():
  assert learner.scaling_efficiency(300.0, 100.0, 4) == 0.75
  assert learner.scaling_efficiency(100.0, 100.0, 1) == 1.0
  assert learner.scaling_efficiency(None, 100.0, 2) is None
  assert learner.scaling_efficiency(300.0, None, 2) is None


def test_more_devices_than_there_are_are_refused_before_anything_compiles(tmp_path, capsys):
  # The test process has one CPU device.
  with pytest.raises(SystemExit):
    learner.main(["--agents", "2", "--devices", "1,2", "--out", str(tmp_path / "l.jsonl")])
  err = capsys.readouterr().err
  assert "--devices: 2 devices: more than the local devices" in err
  assert "valid counts for K = 2 on 1 local device: 1" in err
  with pytest.raises(SystemExit):
    training.main(["--devices", "2", "--seeds", "0,1", "--out", str(tmp_path / "t.jsonl")])
  assert "more than the local devices" in capsys.readouterr().err
  assert not os.listdir(tmp_path)


def test_learner_measures_each_device_count_and_reports_scaling(tmp_path):
  out = tmp_path / "learner.jsonl"
  run_on_cpu_devices(f"""
      import contextlib, io
      import jax
      from dmcr_jax.benchmarks import learner
      assert jax.local_device_count() == 2

      def refused(argv, why):
          err = io.StringIO()
          with contextlib.redirect_stderr(err):
              try:
                  learner.main(argv + ["--out", {str(out)!r}])
              except SystemExit as e:
                  assert e.code == 2
              else:
                  raise AssertionError(argv)
          assert why in err.getvalue(), err.getvalue()

      def no_bench(*args, **kwargs):
          raise AssertionError("measured")
      learner.bench_scanned = learner.bench_python_loop = no_bench
      refused(["--agents", "1,2", "--devices", "1,2"], "--devices: 2 devices: K = 1 agents "
              "is not a multiple of 2 (each device takes K / 2 agents); valid counts for "
              "K = 1,2 on 2 local devices: 1")
      refused(["--agents", "2", "--devices", "4"], "--devices: 4 devices: more than the "
              "local devices; valid counts for K = 2 on 2 local devices: 1, 2")

      seen = []
      def fake_bench(k, dtype, agent_loop, *args, devices=1, **kwargs):
          seen.append((k, devices))
          rate = 100.0 * k * (1 if devices == 1 else 0.8 * devices)
          return dict(kind="scanned", algo="sac_aug", aug="drq", agents=k,
                      devices=devices, dtype=dtype, agent_loop=agent_loop,
                      batch=4, frame_side=16, pairs_per_call=1,
                      compile_s=0.1, reps=3, ms_per_call=1.0,
                      updates_per_s_per_agent=rate / k, agent_updates_per_s=rate)
      learner.bench_scanned = fake_bench
      learner.main(["--agents", "2,4", "--devices", "2,1", "--dtypes", "float32",
                    "--loops", "map", "--no-baseline", "--out", {str(out)!r}])
      assert seen == [(2, 1), (2, 2), (4, 1), (4, 2)], seen
      print("ok")
      """)
  rows = [json.loads(line) for line in out.read_text().splitlines()]
  assert [(r["agents"], r["devices"], r["scaling_efficiency"]) for r in rows] == [
      (2, 1, 1.0), (2, 2, 0.8), (4, 1, 1.0), (4, 2, 0.8)]
  md = (tmp_path / "learner.md").read_text()
  assert "| agents | devices |" in md and "| scaling |" in md
  assert "| 4 | 2 | float32 | map |" in md and "| 0.80 |" in md
  assert "--devices 2,1" in md


@pytest.mark.slow
def test_learner_runs_the_update_sharded_over_two_devices():
  run_on_cpu_devices(f"""
      import functools
      import jax
      from dmcr_jax.benchmarks import learner
      learner.sac.SACConfig = functools.partial(learner.sac.SACConfig, **{TINY_NETS!r})
      call, _, _ = learner.scanned_workload(2, "float32", "vmap", 4, 1, 16, 3, 2, 64,
                                            devices=2)
      leaf = jax.tree.leaves(call().params)[0]
      assert len(leaf.sharding.device_set) == 2, leaf.sharding
      print("ok")
      """)


def _fake_train_run(plan, progress=True):
  """Stands in for `dmcr_jax.train.loop.train` (given a plan): a log.csv whose steady
  rate is 100 transitions/s per agent on one device and 90 % per device more on
  several."""
  cfg, n = plan.cfg, plan.devices
  os.makedirs(cfg.out_dir, exist_ok=True)
  rate = 100.0 * (1 if n == 1 else 0.9 * n)
  with open(os.path.join(cfg.out_dir, "log.csv"), "w") as f:
    f.write("step,agent,episode_return,wall_s\n")
    for i, step in enumerate((1000, 2000, 3000)):
      f.write(f"{step},0,{100 * i},{10 + (step - 1000) / rate}\n")
  return dict(steps=cfg.steps, wall_s=30.0, final_return={"0": 200.0}, interrupted=False)


def test_training_refuses_device_counts_it_cannot_shard_the_agents_over(tmp_path):
  out = tmp_path / "t.jsonl"
  cases = [
      (["--seeds", "0,1", "--devices", "3"], "3 devices: more than the local devices"),
      (["--seeds", "0", "--devices", "1,2"], "K = 1 agents is not a multiple of 2"),
      (["--seeds", "0,1", "--renderer", "jax", "--physics", "device", "--devices", "2"],
       "the device driver (renderer 'jax' with the physics on the device) runs on one"),
  ]
  run_on_cpu_devices(f"""
      import io, contextlib
      from dmcr_jax.benchmarks import training
      from dmcr_jax.train import loop
      def no_training(*args, **kwargs):
          raise AssertionError("trained")
      loop.train = no_training
      for argv, why in {cases!r}:
          err = io.StringIO()
          with contextlib.redirect_stderr(err):
              try:
                  training.main(argv + ["--out", {str(out)!r}])
              except SystemExit as e:
                  assert e.code == 2
              else:
                  raise AssertionError(argv)
          assert why in err.getvalue() and "valid counts" in err.getvalue(), err.getvalue()
      print("ok")
      """)
  assert not out.exists()


def test_training_runs_once_per_device_count_with_scaling_rows(tmp_path):
  out, run_dir = tmp_path / "scaling.jsonl", tmp_path / "runs"
  run_on_cpu_devices(f"""
      from dmcr_jax.benchmarks import learner, training
      from dmcr_jax.train import loop
      from tests.test_benchmarks_devices import _fake_train_run
      alone = []
      def fake_bench(k, *args, devices=1, **kwargs):
          alone.append(devices)
          return dict(updates_per_s_per_agent=100.0 * (1 if devices == 1 else 0.95 * devices))
      learner.bench_scanned = fake_bench
      loop.train = _fake_train_run
      training.main(["--seeds", "0,1", "--devices", "1,2", "--run-dir", {str(run_dir)!r},
                     "--out", {str(out)!r}])
      assert alone == [1, 2], alone
      print("ok")
      """)
  rows = [json.loads(line) for line in out.read_text().splitlines()]
  assert [r["devices"] for r in rows] == [1, 2]
  assert [r["agents"] for r in rows] == [2, 2]
  assert rows[0]["total_transitions_per_s"] == pytest.approx(200.0)
  assert rows[1]["total_transitions_per_s"] == pytest.approx(360.0)
  assert [r["scaling_efficiency"] for r in rows] == [1.0, 0.9]
  assert sorted(os.listdir(run_dir)) == ["devices-1", "devices-2"]
  assert (tmp_path / "scaling_devices2_log.csv").exists()
  md = (tmp_path / "scaling.md").read_text()
  assert "| devices |" in md and "| total steady transitions/s | scaling |" in md
  assert "| 360.0 | 0.90 |" in md
