"""Evaluation during training (`dmcr-train --eval-every`): the curve's rows and plot,
its returns equal to the protocol run directly on the checkpointed agents, bad
options refused before anything is built, and a resumed run's rows past its
checkpoint dropped."""

import csv
import dataclasses
import os

import jax
import pytest

from dmcr_jax import protocol
from dmcr_jax.train import checkpoint, config, eval_curve, loop
from dmcr_jax.train.__main__ import parse
from dmcr_jax.train.evaluate import greedy_policy, policy_params

# test_train's group: the tiny run shares the drivers' compilations.
pytestmark = pytest.mark.xdist_group("train")

EVAL = dict(eval_every=20, eval_looks=2, eval_dynamics=1, eval_train_episodes=2,
            eval_conditions=("none", "all"))
"""A tiny reduced protocol: 2 held-out looks × 1 state for none and all, 2 train
episodes at each agent's training looks."""


def tiny_config(out, **changes) -> loop.TrainConfig:
  """test_run_folder's tiny run (2 envs, the ray caster's device driver, 48 steps in
  chunks of 12, checkpoints at 24 and 48) on cartpole-balance (whose returns are not
  0 from the start, as pendulum-swingup's are), evaluated every 20 steps: at the
  chunks that cross 20 and 40 (steps 24 and 48; 48 is also the end)."""
  import dataclasses
  from tests.test_run_folder import tiny_config as run_folder_config
  return dataclasses.replace(run_folder_config(out, task="cartpole-balance", **EVAL),
                             **changes)


def read(path):
  with open(path, newline="") as f:
    return list(csv.DictReader(f))


def offline_wandb(mp, tmp):
  """No W&B key, mode or netrc in the environment (`mp`: a MonkeyPatch): offline."""
  for var in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_PROJECT", "WANDB_RUN_GROUP"):
    mp.delenv(var, raising=False)
  mp.setenv("NETRC", os.path.join(str(tmp), "no-netrc"))


@pytest.fixture(scope="module")
def eval_run(tmp_path_factory):
  """A finished tiny run with evaluations, logged to TensorBoard and an offline W&B
  run too; its config and summary."""
  out = tmp_path_factory.mktemp("eval") / "run"
  cfg = tiny_config(out, loggers=("csv", "tensorboard", "wandb"))
  with pytest.MonkeyPatch.context() as mp:
    offline_wandb(mp, out.parent)
    summary = loop.train(cfg, progress=False)
  return cfg, summary


@pytest.mark.slow
def test_a_run_writes_its_eval_curve_at_every_multiple_and_at_the_end(eval_run):
  cfg, summary = eval_run
  rows = read(os.path.join(cfg.out_dir, eval_curve.CSV))
  assert tuple(rows[0]) == eval_curve.FIELDS
  assert [(int(r["step"]), r["agent"], r["condition"]) for r in rows] == [
      (24, "0", "none"), (24, "0", "all"), (48, "0", "none"), (48, "0", "all")]
  assert all(r["label"] == "seed 0" and float(r["eval_s"]) > 0 for r in rows)
  # The train return is the agent's, E_G follows from it and the condition's mean.
  for r in rows:
    train, test = float(r["train_return"]), float(r["mean_return"])
    if r["e_g"]:
      assert float(r["e_g"]) == pytest.approx((train - test) / train, abs=1e-3)
  evals = {int(r["step"]): float(r["eval_s"]) for r in rows}
  assert summary["eval_seconds"] == pytest.approx(sum(evals.values()), abs=0.01)
  # The training benchmark's row field: the evaluations' share of the loop's time.
  from dmcr_jax.benchmarks.training import eval_share
  assert 0 < eval_share(summary) == summary["eval_seconds"] / summary["wall_s"] < 1
  assert eval_share(dict(wall_s=10.0)) is None
  assert os.path.getsize(os.path.join(cfg.out_dir, eval_curve.PNG)) > 0


@pytest.mark.slow
def test_eval_curve_returns_equal_the_protocol_on_the_checkpointed_agents(eval_run):
  cfg, _ = eval_run
  rows = read(os.path.join(cfg.out_dir, eval_curve.CSV))
  for step in (24, 48):
    _, agents, at = checkpoint.load_run(cfg.out_dir, step)
    assert at == step
    # On the device, as the learner's agents are (committed there): the protocol then
    # lowers to the curve's program, which the run compiled already.
    agents = jax.device_put(agents, jax.devices()[0])
    result = protocol.evaluate(
        cfg.task, greedy_policy, policy_params(agents, [0]), agents=1, renderer="jax",
        visual_seeds=2, dynamics_seeds=1, train_episodes=2, conditions=("none", "all"),
        train_look=cfg.agent_looks(), train_vary=cfg.vary, seed=cfg.seeds[0],
        image_size=cfg.image_size, frame_stack=cfg.frame_stack,
        action_repeat=cfg.action_repeat)
    mine = {r["condition"]: r for r in rows if int(r["step"]) == step}
    assert all(float(r["mean_return"]) > 0 for r in mine.values())
    for c in ("none", "all"):
      assert float(mine[c]["mean_return"]) == pytest.approx(float(result.mean(c)[0]),
                                                           abs=1e-3)
      assert float(mine[c]["train_return"]) == pytest.approx(float(result.train_mean[0]),
                                                            abs=1e-3)


@pytest.mark.slow
def test_the_runs_tensorboard_and_wandb_curves_equal_its_csvs(eval_run):
  from dmcr_jax.train import loggers
  from tests.test_loggers import read_tensorboard, read_wandb
  cfg, _ = eval_run
  episodes = read(os.path.join(cfg.out_dir, "log.csv"))
  evals = read(os.path.join(cfg.out_dir, eval_curve.CSV))
  assert episodes and evals
  steps = sorted({int(r["step"]) for r in episodes})
  returns = [sum(float(r["episode_return"]) for r in episodes if int(r["step"]) == s)
             / sum(int(r["step"]) == s for r in episodes) for s in steps]
  tb = read_tensorboard(os.path.join(cfg.out_dir, loggers.TENSORBOARD_DIR, "agent_0-seed_0-drq"))
  assert [s for s, _ in tb["episode/return"]] == steps
  assert [v for _, v in tb["episode/return"]] == pytest.approx(returns, rel=1e-6)
  q = {int(r["step"]): float(r["q"]) for r in episodes if r["q"]}
  # At episode ends the update metrics are log.csv's; between them (every
  # `log_every` steps: here every chunk) they are logged too.
  tb_q = dict(tb["train/q"])
  assert q and {s: tb_q[s] for s in q} == pytest.approx(q, rel=1e-6)
  assert set(tb_q) > set(q)
  assert "train/entropy" in tb and "train/alpha_loss" in tb  # beyond log.csv's columns
  for c in ("none", "all"):
    want = [(int(r["step"]), float(r["mean_return"])) for r in evals if r["condition"] == c]
    assert tb[f"eval/{c}"] == [(s, pytest.approx(v, rel=1e-6)) for s, v in want]
  assert tb["_hparams"]["task"] == "cartpole-balance" and tb["_hparams"]["eval_every"] == 20
  (run,) = read_wandb(cfg.out_dir).values()
  history = [h for h in run["history"] if "episode/return" in h]
  assert [(h["step"], h["episode/return"]) for h in history] == pytest.approx(
      list(zip(steps, returns)))
  assert [(h["step"], h["eval/all"]) for h in run["history"] if "eval/all" in h] == [
      (int(r["step"]), pytest.approx(float(r["mean_return"]))) for r in evals
      if r["condition"] == "all"]
  assert run["config"]["task"] == "cartpole-balance"


@pytest.mark.slow
def test_the_runs_episode_lengths_and_updates_per_s_reach_tensorboard_and_wandb(eval_run):
  import numpy as np
  from dmcr_jax import models
  from dmcr_jax.train import loggers
  from tests.test_loggers import read_tensorboard, read_wandb
  cfg, _ = eval_run
  rows = read(os.path.join(cfg.out_dir, "log.csv"))
  # Episodes end at the time limit: its control steps over the action repeat.
  length = -(-models.load(cfg.task).time_limit // cfg.action_repeat)
  assert length == 10 and {int(r["episode_length"]) for r in rows} == {length}
  learning = [r for r in rows if int(r["step"]) > cfg.warmup_steps]
  assert learning and all(float(r["updates_per_s"]) > 0 for r in learning)
  # The learner's own count: the last episodes are reported after the run's last
  # chunk, with every update of the run.
  _, agents, _ = checkpoint.load_run(cfg.out_dir, cfg.steps)
  last = rows[-1]
  assert float(last["updates_per_s"]) * float(last["wall_s"]) == pytest.approx(
      int(np.sum(agents.step)), rel=0.01)
  tb = read_tensorboard(os.path.join(cfg.out_dir, loggers.TENSORBOARD_DIR, "agent_0-seed_0-drq"))
  steps = sorted({int(r["step"]) for r in rows})
  assert tb["episode/length"] == [(s, length) for s in steps]
  per_s = {int(r["step"]): float(r["updates_per_s"]) for r in rows}
  tb_per_s = dict(tb["perf/updates_per_s"])   # also between episodes (every chunk here)
  assert {s: tb_per_s[s] for s in per_s} == pytest.approx(per_s, rel=1e-6)
  assert all(v > 0 for s, v in tb_per_s.items() if s > cfg.warmup_steps)
  (run,) = read_wandb(cfg.out_dir).values()
  history = [h for h in run["history"] if "episode/return" in h]
  assert [(h["step"], h["episode/length"]) for h in history] == [(s, length) for s in steps]
  assert {h["step"]: h["perf/updates_per_s"] for h in history} == pytest.approx(per_s)


@pytest.mark.parametrize("off", [0, None])
def test_no_eval_curve_without_eval_every(tmp_path, off):
  plan = config.resolve(tiny_config(tmp_path / "run", eval_every=off))
  os.makedirs(plan.cfg.out_dir)
  with eval_curve.EvalCurve(plan, 0, resume=False) as curve:
    assert not curve.due(0, 48) and curve.summary() == {}
  assert not os.path.exists(os.path.join(plan.cfg.out_dir, eval_curve.CSV))


def test_due_at_each_multiple_and_once_at_the_end(tmp_path):
  plan = config.resolve(tiny_config(tmp_path / "run", eval_every=40, steps=50))
  os.makedirs(plan.cfg.out_dir)
  with eval_curve.EvalCurve(plan, 0, resume=False) as curve:
    assert [curve.due(b, s) for b, s in ((0, 12), (24, 36), (36, 48))] == [False, False, True]
    assert curve.due(48, 60)      # the end, not a multiple
    curve.last = 60
    assert not curve.due(48, 60)  # already evaluated there


@pytest.mark.parametrize("argv, match", [
    (["--eval-every", "-1"], "eval_every must be an int >= 0"),
    (["--eval-looks", "0"], "eval_looks must be a positive int"),
    (["--eval-dynamics", "0"], "eval_dynamics must be a positive int"),
    (["--eval-train-episodes", "11"], "eval_train_episodes (11) must be at most "
                                      "eval_looks · eval_dynamics = 10"),
    (["--eval-conditions", "none,target"], "'target' not valid for cartpole-balance; "
                                           "valid: none, light, camera, body, floor, "
                                           "background, all"),
    (["--eval-conditions", "all,all"], "a condition named twice"),
    (["--eval-renderer", "mujoco"], "invalid choice: 'mujoco'"),
])
def test_bad_eval_options_fail_before_anything_is_built(argv, match, capsys, tmp_path):
  with pytest.raises(SystemExit):
    parse(argv + ["--out", str(tmp_path / "run")])
  assert match in capsys.readouterr().err
  assert not os.path.exists(tmp_path / "run")


def test_train_refuses_bad_eval_options_before_the_run_folder(tmp_path):
  cfg = tiny_config(tmp_path / "run", eval_conditions=("nope",))
  with pytest.raises(ValueError, match="eval_conditions 'nope': 'nope' not valid for "
                                       "cartpole-balance; valid: none"):
    loop.train(cfg, progress=False)
  assert not os.path.exists(tmp_path / "run")


def test_eval_options_may_change_on_resume():
  saved = loop.TrainConfig()
  config.check_resume(saved, loop.TrainConfig(eval_every=100, eval_looks=3,
                                              eval_conditions=("all",),
                                              eval_renderer="pool"))


def test_a_resumed_run_drops_the_eval_rows_past_its_checkpoint(tmp_path, capsys):
  plan = config.resolve(tiny_config(tmp_path / "run"))
  out = plan.cfg.out_dir
  os.makedirs(out)
  path = os.path.join(out, eval_curve.CSV)
  with open(path, "w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=eval_curve.FIELDS)
    w.writeheader()
    for step in (24, 48):
      w.writerow(dict(step=step, agent=0, label="seed 0", condition="none",
                      mean_return=1.0, train_return=2.0, e_g=0.5, eval_s=0.1))
  with eval_curve.EvalCurve(plan, 24, resume=True):
    assert "dropped the eval curve's rows past step 24" in capsys.readouterr().err
  assert [int(r["step"]) for r in read(path)] == [24]
  # A new run (not resumed) starts the curve afresh.
  with eval_curve.EvalCurve(plan, 0, resume=False):
    pass
  assert read(path) == []


def test_eval_options_survive_config_json(tmp_path):
  cfg = loop.TrainConfig(out_dir=str(tmp_path), eval_every=500, eval_conditions=("none", "all"),
                         eval_renderer="pool")
  config.save_config(cfg, str(tmp_path))
  assert config.load_config(str(tmp_path)) == cfg


@pytest.mark.slow
def test_a_run_resumed_from_an_earlier_checkpoint_evaluates_from_there_again(eval_run,
                                                                             tmp_path):
  import shutil
  cfg, _ = eval_run
  out = str(tmp_path / "run")
  shutil.copytree(cfg.out_dir, out)
  before = read(os.path.join(out, eval_curve.CSV))
  shutil.rmtree(os.path.join(checkpoint.folder(out), "48"))  # as if killed before it
  resumed = dataclasses.replace(cfg, out_dir=out)
  with pytest.MonkeyPatch.context() as mp:
    offline_wandb(mp, tmp_path)
    summary = loop.train(resumed, resume=True, progress=False)
  rows = read(os.path.join(out, eval_curve.CSV))
  assert [int(r["step"]) for r in rows] == [24, 24, 48, 48]  # 48 once, not twice
  assert rows[:2] == before[:2]
  # The same agents' evaluation at 24 is kept; 48's comes from the resumed training.
  assert summary["eval_seconds"] == pytest.approx(float(rows[-1]["eval_s"]), abs=0.01)
  # The event files continue in place, without the steps past 24 logged before.
  from dmcr_jax.train import loggers
  from tests.test_loggers import read_tensorboard
  tb = read_tensorboard(os.path.join(out, loggers.TENSORBOARD_DIR, "agent_0-seed_0-drq"))
  assert [s for s, _ in tb["eval/all"]] == [24, 48]
  assert [s for s, _ in tb["episode/return"]] == sorted(
      {int(r["step"]) for r in read(os.path.join(out, "log.csv"))})
