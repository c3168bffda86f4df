"""`dmcr-train --logger`: names checked before anything is built, a missing package named
with its extra, and the TensorBoard event files and offline W&B runs that a run's
reports write, read back with TensorBoard's own reader and from the `.wandb` record
file, equal to log.csv (and kept apart per agent, and continued on resume).

`read_tensorboard` and `read_wandb` are shared with test_eval_curve, whose tiny run
logs to both."""

import csv
import glob
import json
import os
import struct

import numpy as np
import pytest

from dmcr_jax.train import loggers, loop, runlog
from dmcr_jax.train.__main__ import parse


def read_tensorboard(folder: str) -> dict:
  """{tag: [(step, value)]} of the event files in `folder` (TensorBoard's own
  EventAccumulator, which also applies a resumed writer's purge), and "_hparams"
  → {name: value} from the HParams plugin's session-start record."""
  from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
  from tensorboard.plugins.hparams import plugin_data_pb2
  acc = EventAccumulator(folder, size_guidance={"scalars": 0})
  acc.Reload()
  out = {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}
  content = acc.PluginTagToContent("hparams").get("_hparams_/session_start_info")
  if content is not None:
    data = plugin_data_pb2.HParamsPluginData.FromString(content)
    out["_hparams"] = {k: v.WhichOneof("kind") and getattr(v, v.WhichOneof("kind"))
                       for k, v in data.session_start_info.hparams.items()}
  return out


def wandb_records(path: str):
  """The `wandb_internal_pb2.Record`s of a `.wandb` file: LevelDB's log format (32 KiB
  blocks of chunks, each with a 7-byte header: CRC, length, type full/first/middle/
  last) after W&B's 7-byte file header (":W&B", magic, version)."""
  from wandb.proto import wandb_internal_pb2 as pb
  with open(path, "rb") as f:
    data = f.read()
  assert data[:4] == b":W&B"
  pos, block, parts = 7, 32768, b""
  while pos + 7 <= len(data):
    left = block - pos % block
    if left < 7:
      pos += left
      continue
    _, n, kind = struct.unpack("<IHB", data[pos:pos + 7])
    if kind == 0 and n == 0:
      pos += left
      continue
    chunk, pos = data[pos + 7:pos + 7 + n], pos + 7 + n
    if kind in (1, 4):
      record = pb.Record()
      record.ParseFromString(parts + chunk if kind == 4 else chunk)
      yield record
      parts = b""
    else:
      parts = chunk if kind == 2 else parts + chunk


def read_wandb(out_dir: str) -> dict:
  """{run id: {"name", "group", "config", "history": [{key: value}]}} of the offline W&B
  runs under `<out_dir>/wandb` (a resumed run's files joined under its id)."""
  runs = {}
  # In the order they were written: a segment that resumes a run within the second it
  # was made gets the folder name with a "-1" suffix, which sorts before the first's.
  paths = glob.glob(os.path.join(out_dir, "wandb", "offline-run-*", "*.wandb"))
  for path in sorted(paths, key=os.path.getmtime):
    for r in wandb_records(path):
      kind = r.WhichOneof("record_type")
      if kind == "run":
        run = runs.setdefault(r.run.run_id, dict(history=[], config={}))
        run.update(name=r.run.display_name, group=r.run.run_group)
        run["config"].update({i.key: json.loads(i.value_json) for i in r.run.config.update})
        current = run
      elif kind == "history":
        items = {i.key or "/".join(i.nested_key): json.loads(i.value_json)
                 for i in r.history.item}  # "a/b" keys come as nested keys
        current["history"].append({k: v for k, v in items.items() if not k.startswith("_")})
  return runs


def read_csv(path):
  with open(path, newline="") as f:
    return list(csv.DictReader(f))


@pytest.mark.parametrize("argv, match", [
    (["--logger", "tb"], "logger 'tb' unknown; valid: csv, tensorboard, wandb"),
    (["--logger", "csv,mlflow"], "logger 'mlflow' unknown; valid: csv, tensorboard, wandb"),
])
def test_unknown_loggers_fail_naming_the_valid_ones(argv, match, capsys, tmp_path):
  with pytest.raises(SystemExit):
    parse(argv + ["--out", str(tmp_path / "run")])
  assert match in capsys.readouterr().err
  assert not os.path.exists(tmp_path / "run")


def test_csv_is_always_written_and_names_are_kept_once():
  assert parse([])[0].loggers == ("csv",)
  assert parse(["--logger", "tensorboard"])[0].loggers == ("csv", "tensorboard")
  assert loggers.parse_loggers("wandb,csv,wandb,tensorboard") == ("csv", "wandb", "tensorboard")
  with pytest.raises(ValueError, match="tuple of names"):
    loggers.check_loggers("tensorboard")


@pytest.mark.parametrize("name, module", [("tensorboard", "tensorboardX"), ("wandb", "wandb")])
def test_a_missing_package_names_its_extra_before_anything_is_built(name, module, monkeypatch,
                                                                     tmp_path):
  import importlib.util
  real = importlib.util.find_spec
  monkeypatch.setattr(importlib.util, "find_spec",
                      lambda m, *a: None if m == module else real(m, *a))
  cfg = loop.TrainConfig(out_dir=str(tmp_path / "run"), loggers=("csv", name))
  with pytest.raises(ValueError, match=rf"needs the {module} package, which is not "
                                       rf"installed: pip install 'dmcr-jax\[{name}\]'"):
    loop.train(cfg, progress=False)
  assert not os.path.exists(tmp_path / "run")


def test_wandb_is_offline_without_a_key_unless_told(tmp_path):
  none = str(tmp_path / "netrc")
  assert loggers.wandb_mode({}, none) == "offline"
  assert loggers.wandb_mode({"WANDB_API_KEY": "x" * 40}, none) == "online"
  assert loggers.wandb_mode({"WANDB_API_KEY": "x", "WANDB_MODE": "offline"}, none) == "offline"
  with open(none, "w") as f:
    f.write("machine api.wandb.ai\n  login user\n  password abc\n")
  assert loggers.wandb_mode({}, none) == "online"


def offline_wandb(monkeypatch, tmp_path):
  """No API key and no netrc: `wandb_mode` picks offline."""
  for var in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_PROJECT", "WANDB_RUN_GROUP"):
    monkeypatch.delenv(var, raising=False)
  monkeypatch.setenv("NETRC", str(tmp_path / "no-netrc"))


def report(log, episodes_by_step):
  """Feeds `log` synthetic driver reports: {step: [(agent, return)]}, with update
  metrics that differ per agent and step (critic_loss NaN before any update)."""
  before = log.start
  for step, ended in episodes_by_step.items():
    k = len(log.specs)
    metrics = {name: np.arange(k, dtype=np.float32) + step / 100 + i
               for i, name in enumerate(("critic_loss", "actor_loss", "alpha", "q",
                                         "entropy", "alpha_loss"))}
    if step < 20:
      metrics["critic_loss"] = np.full(k, np.nan, np.float32)
    log.report(before, step, [(step, a, r, metrics) for a, r in ended])
    before = step


def test_reports_reach_tensorboard_and_wandb_as_log_csv_holds_them(tmp_path, monkeypatch):
  offline_wandb(monkeypatch, tmp_path)
  out = str(tmp_path / "run")
  os.makedirs(out)
  cfg = loop.TrainConfig(out_dir=out, steps=40, seeds=(0, 1), log_every=10,
                         loggers=("csv", "tensorboard", "wandb"))
  specs = cfg.agents()
  episodes = {10: [(0, 1.0), (0, 3.0), (1, 5.0)], 20: [(1, 7.0)], 30: [(0, 2.5), (1, 4.5)],
              40: [(0, 9.0)]}
  with runlog.RunLog(cfg, specs, None, 0, False, progress=False) as log:
    import signal
    assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL  # RunLog's, not W&B's
    report(log, {s: e for s, e in episodes.items() if s <= 30})
    log.evaluated([dict(step=30, agent=a, label="", condition=c, mean_return=10.0 * a + i,
                        train_return=20.0 + a, e_g="" if c == "none" else 0.5, eval_s=1.0)
                   for a in (0, 1) for i, c in enumerate(("none", "all"))])
  rows = read_csv(os.path.join(out, "log.csv"))
  names = loggers.run_names(specs)
  assert names == ["agent_0-seed_0-drq", "agent_1-seed_1-drq"]
  wandb_runs = read_wandb(out)
  with open(os.path.join(out, loggers.WANDB_RUNS)) as f:
    ids = json.load(f)
  assert set(wandb_runs) == set(ids.values())
  for a, name in enumerate(names):
    tb = read_tensorboard(os.path.join(out, loggers.TENSORBOARD_DIR, name))
    mine = [r for r in rows if int(r["agent"]) == a]
    steps = sorted({int(r["step"]) for r in mine})
    want = [(s, np.mean([float(r["episode_return"]) for r in mine if int(r["step"]) == s]))
            for s in steps]
    assert [s for s, _ in tb["episode/return"]] == steps
    np.testing.assert_allclose([v for _, v in tb["episode/return"]], [v for _, v in want],
                               rtol=1e-6)
    for name_, tag in (("critic_loss", "train/critic_loss"), ("q", "train/q"),
                       ("agent_steps_per_s", "perf/transitions_per_s")):
      got = dict(tb[tag])
      csv_values = {int(r["step"]): float(r[name_]) for r in mine if r[name_] != ""}
      assert got.keys() == csv_values.keys()  # no critic loss before an update ran
      np.testing.assert_allclose([got[s] for s in sorted(got)],
                                 [csv_values[s] for s in sorted(got)], rtol=1e-6)
    assert dict(tb["train/entropy"])[30] == pytest.approx(a + 0.3 + 4)
    assert tb["eval/all"] == [(30, 10.0 * a + 1)] and tb["eval/train"] == [(30, 20.0 + a)]
    assert tb["eval/e_g/all"] == [(30, 0.5)] and "eval/e_g/none" not in tb
    assert tb["_hparams"]["agent.seed"] == a and tb["_hparams"]["sac.aug"] == "drq"
    assert tb["_hparams"]["steps"] == 40
    # The agent's W&B run: the same values against its step metric, its config.
    run = wandb_runs[ids[str(a)]]
    assert run["group"] == "run" and run["name"] == f"run/{name}"
    assert run["config"]["agent.seed"] == a and run["config"]["num_envs"] == cfg.num_envs
    history = [h for h in run["history"] if "episode/return" in h]
    assert [(h["step"], h["episode/return"]) for h in history] == pytest.approx(want)
    assert [h for h in run["history"] if "eval/all" in h][0]["eval/all"] == 10.0 * a + 1

  # Resumed from step 20: TensorBoard drops the events past it, W&B continues the runs.
  with runlog.RunLog(cfg, specs, None, 20, True, progress=False) as log:
    report(log, {30: [(0, 6.0)], 40: [(0, 8.0)]})
  tb = read_tensorboard(os.path.join(out, loggers.TENSORBOARD_DIR, names[0]))
  assert tb["episode/return"] == [(10, 2.0), (30, 6.0), (40, 8.0)]
  assert tb["eval/all"] == []  # step 30's evaluation belonged to the dropped past
  other = read_tensorboard(os.path.join(out, loggers.TENSORBOARD_DIR, names[1]))
  assert other["episode/return"] == [(10, 5.0), (20, 7.0)]  # the checkpoint's step is kept
  with open(os.path.join(out, loggers.WANDB_RUNS)) as f:
    assert json.load(f) == ids
  resumed = read_wandb(out)[ids["0"]]
  assert [h["episode/return"] for h in resumed["history"] if "episode/return" in h][-2:] == [
      6.0, 8.0]


def test_episode_length_and_updates_per_s_reach_log_csv_and_tensorboard(tmp_path):
  out = str(tmp_path / "run")
  os.makedirs(out)
  cfg = loop.TrainConfig(out_dir=out, steps=40, seeds=(0, 1), loggers=("csv", "tensorboard"))
  specs = cfg.agents()
  with runlog.RunLog(cfg, specs, None, 0, False, progress=False, episode_length=125) as log:
    log.wall = lambda: 4.0  # this segment's seconds, fixed: updates/s = updates / 4
    log.report(0, 10, [(10, 0, 1.0, {}), (10, 1, 2.0, {})], updates=0)  # the warm-up
    log.report(10, 20, [(20, 0, 3.0, {})], updates=200)
    log.report(20, 30, [(30, 1, 4.0, {})])  # a driver that counts no updates
  rows = read_csv(os.path.join(out, "log.csv"))
  assert [(r["episode_length"], r["updates_per_s"]) for r in rows] == [
      ("125", "0.0"), ("125", "0.0"), ("125", "50.0"), ("125", "")]
  names = loggers.run_names(specs)
  tb = [read_tensorboard(os.path.join(out, loggers.TENSORBOARD_DIR, n)) for n in names]
  assert tb[0]["episode/length"] == [(10, 125.0), (20, 125.0)]
  assert tb[1]["episode/length"] == [(10, 125.0), (30, 125.0)]
  assert tb[0]["perf/updates_per_s"] == [(10, 0.0), (20, 50.0)]
  assert tb[1]["perf/updates_per_s"] == [(10, 0.0)]  # none where the count is not known


def test_a_log_csv_written_before_the_length_and_updates_columns_resumes_with_them(tmp_path):
  out = str(tmp_path / "run")
  os.makedirs(out)
  old = ["step", "agent", "seed", "aug", "episode_return", "wall_s", "agent_steps_per_s",
         "critic_loss", "actor_loss", "alpha", "q"]
  with open(os.path.join(out, "log.csv"), "w", newline="") as f:
    writer = csv.writer(f)
    writer.writerow(old)
    writer.writerows([[10, 0, 0, "drq", 1.5, 2.0, 5.0, "", "", "", ""],
                      [30, 0, 0, "drq", 9.0, 6.0, 5.0, 0.1, 0.2, 0.3, 0.4]])
  cfg = loop.TrainConfig(out_dir=out, steps=40)
  with runlog.RunLog(cfg, cfg.agents(), None, 20, True, progress=False,
                     episode_length=125) as log:
    log.report(20, 40, [(40, 0, 7.0, {})], updates=100)
  rows = read_csv(os.path.join(out, "log.csv"))
  assert list(rows[0]) == log.fields and {"episode_length", "updates_per_s"} <= set(log.fields)
  assert [(r["step"], r["episode_return"], r["wall_s"], r["episode_length"]) for r in rows] == [
      ("10", "1.5", "2.0", ""), ("40", "7.0", rows[1]["wall_s"], "125")]
  assert float(rows[1]["updates_per_s"]) > 0 and rows[0]["agent_steps_per_s"] == "5.0"


def test_update_metrics_reach_the_sinks_every_log_every_steps_between_episodes(tmp_path):
  out = str(tmp_path / "run")
  os.makedirs(out)
  cfg = loop.TrainConfig(out_dir=out, steps=400, seeds=(0, 1), loggers=("csv", "tensorboard"))
  specs = cfg.agents()
  metrics = {"critic_loss": np.array([0.5, 1.5], np.float32),
             "q": np.array([2.0, np.nan], np.float32)}
  with runlog.RunLog(cfg, specs, None, 0, False, progress=False, episode_length=125) as log:
    log.wall = lambda: 4.0
    every = log.every
    assert 1 < every < cfg.steps
    log.report(0, every - 1, [], metrics=None)               # not due: nothing logged
    log.report(every - 1, every, [], updates=80, metrics=metrics)  # due, no episode ended
    log.report(every, 2 * every, [(2 * every, 0, 3.0, metrics)], updates=160,
               metrics=metrics)                             # due: agent 0's episode row
  names = loggers.run_names(specs)
  tb = [read_tensorboard(os.path.join(out, loggers.TENSORBOARD_DIR, n)) for n in names]
  assert tb[0]["train/critic_loss"] == [(every, 0.5), (2 * every, 0.5)]
  assert tb[1]["train/critic_loss"] == [(every, 1.5), (2 * every, 1.5)]
  assert "train/q" not in tb[1] and tb[0]["train/q"] == [(every, 2.0), (2 * every, 2.0)]
  assert tb[0]["perf/updates_per_s"] == [(every, 20.0), (2 * every, 40.0)]
  assert tb[1]["perf/transitions_per_s"] == [(every, every * 2 / 4.0),
                                             (2 * every, 2 * every * 2 / 4.0)]
  assert tb[0]["episode/return"] == [(2 * every, 3.0)]      # episodes only where they end
