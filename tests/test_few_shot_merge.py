"""The few-shot curve with its seed spread and across runs: `few_shot_rows`' min / max
against NumPy, the "mean (min–max)" table cells and the plot's bands, several runs'
evaluations merged into the rows of one run holding the same agents, other
protocols refused naming the option, and `dmcr-sweep` writing the curve of a spec with
two look ranges.

The summaries are built as `evaluate` builds them (`protocol.Results.summary` of
random returns, each agent extended with its seed, augmentation, method and looks);
nothing is trained.
"""

import dataclasses
import json
import os
import re

import numpy as np
import pytest

from dmcr_jax import protocol, protocol_report
from dmcr_jax.benchmarks import few_shot
from dmcr_jax.train import evaluate as ev
from dmcr_jax.train import loop, paper_results
from dmcr_jax.train import sweep as sw
from dmcr_jax.visuals.levels import TRAIN_SEEDS, levels

CONDITIONS = ("none", "floor", "all")
CONFIG = ev.EvalConfig(visual_seeds=2, dynamics_seeds=2, train_episodes=3, conditions=CONDITIONS,
                       quality="fastest", workers=1)


def eval_summary(run_dir, looks, seeds, aug="drq", rng=None, cfg=CONFIG,
                 task="cartpole-balance"):
  """An eval.json summary as `evaluate` writes it for a run of one agent per
  (look, seed) (`looks`: range sizes, 0 for the fixed seed 0), random returns."""
  rng = rng or np.random.default_rng(0)
  specs = [(n, s) for n in looks for s in seeds]
  train_looks = tuple(loop.look_label(levels(n) if n else 0) for n, _ in specs)
  res = protocol.Results(
      task=task, conditions=cfg.conditions, train=rng.uniform(0, 1000, (len(specs), 3)),
      returns={c: rng.uniform(0, 1000, (len(specs), 4)) for c in cfg.conditions},
      test_visual_seeds=np.arange(2), train_looks=train_looks, config={},
      labels=tuple(f"agent {k}" for k in range(len(specs))), device="cpu", wall_s=1.0,
      compile_s=None, agent_steps=0)
  summary = res.summary()
  for k, (row, (n, s)) in enumerate(zip(summary["agents"], specs)):
    row.pop("label")
    row.update(agent=k, seed=s, aug=aug, algo="sac_aug",
               method=paper_results.method_name("sac_aug", aug), train_look=train_looks[k],
               looks=loop.num_looks(levels(n) if n else 0))
  summary = dict(run_dir=run_dir, task=task, checkpoint_step=20,
                 config=json.loads(json.dumps(dataclasses.asdict(cfg))),
                 conditions=list(cfg.conditions), train_look=",".join(train_looks),
                 agents=summary["agents"], wall_s=1.0, mean=summary["mean"])
  summary["augs"] = protocol_report.aug_groups(summary)
  return json.loads(json.dumps(protocol_report.json_safe(summary)))


def split_by_look(summary: dict) -> list[dict]:
  """`summary`'s agents as the summaries of one run per training look (as runs trained
  apart write them: agents numbered from 0, the run's own train look)."""
  out = []
  for look in dict.fromkeys(r["train_look"] for r in summary["agents"]):
    agents = [dict(r, agent=k) for k, r in
              enumerate(r for r in summary["agents"] if r["train_look"] == look)]
    out.append(dict(summary, run_dir=f"{summary['run_dir']}-{look}", train_look=look,
                    agents=agents))
  return out


def test_rows_give_the_mean_and_min_max_over_seeds():
  summary = eval_summary("runs/a", [1, 10], [0, 1, 2])
  rows = protocol_report.few_shot_rows(summary)
  assert [(r["looks"], r["seeds"]) for r in rows] == [(1, [0, 1, 2]), (10, [0, 1, 2])]
  table = protocol_report.few_shot_markdown(summary, rows)
  for row in rows:
    mine = [r for r in summary["agents"] if r["train_look"] == row["train_look"]]
    train = np.array([np.mean(r["train"]["episodes"]) for r in mine])
    assert (row["train"], row["train_min"], row["train_max"]) == pytest.approx(
        (train.mean(), train.min(), train.max()))
    for c in CONDITIONS:
      per = np.array([np.mean(r["conditions"][c]["episodes"]) for r in mine])
      assert row["conditions"][c] == pytest.approx(per.mean())
      assert row["conditions_min"][c] == pytest.approx(per.min())
      assert row["conditions_max"][c] == pytest.approx(per.max())
    all_ = np.array([np.mean(r["conditions"]["all"]["episodes"]) for r in mine])
    assert row["all_std"] == pytest.approx(all_.std())
    cell = f"{all_.mean():.1f} ({all_.min():.1f}–{all_.max():.1f})"
    assert f"| {cell} |" in table
  # One seed: the cells as before, no spread.
  one = eval_summary("runs/b", [1, 10], [0])
  rows = protocol_report.few_shot_rows(one)
  table = protocol_report.few_shot_markdown(one, rows)
  assert not re.search(r"\(\d+\.\d–", table) and "min–max" not in table
  assert f"| {rows[1]['conditions']['all']:.1f} |" in table
  # Every training seed: named "all", not counted.
  every = eval_summary("runs/c", [TRAIN_SEEDS.stop], [0])
  table = protocol_report.few_shot_markdown(every, protocol_report.few_shot_rows(every))
  assert "| SAC+AUG | all (levels:all) | 1 |" in table


def test_the_plot_draws_a_min_max_band_around_all_and_train():
  import matplotlib.pyplot as plt
  summary = eval_summary("runs/a", [1, 10, 100], [0, 1])
  rows = protocol_report.few_shot_rows(summary)
  fig = protocol_report.few_shot_figure(summary, rows)
  ax = fig.axes[0]
  bands = {c.get_gid(): c for c in ax.collections if (c.get_gid() or "").startswith("band")}
  assert set(bands) == {"band all, SAC+AUG", "band train, SAC+AUG"}
  for gid, lo, hi in [("band all, SAC+AUG", [r["conditions_min"]["all"] for r in rows],
                       [r["conditions_max"]["all"] for r in rows]),
                      ("band train, SAC+AUG", [r["train_min"] for r in rows],
                       [r["train_max"] for r in rows])]:
    y = bands[gid].get_paths()[0].vertices[:, 1]
    assert y.min() == pytest.approx(min(lo)) and y.max() == pytest.approx(max(hi))
    for v in lo + hi:
      assert np.isclose(y, v).any()
  plt.close(fig)
  one = eval_summary("runs/b", [1, 10], [0])
  fig = protocol_report.few_shot_figure(one, protocol_report.few_shot_rows(one))
  assert not [c for c in fig.axes[0].collections if (c.get_gid() or "").startswith("band")]
  plt.close(fig)


def test_merged_runs_give_the_rows_of_one_run_holding_the_same_agents():
  rng = np.random.default_rng(1)
  one = eval_summary("runs/x", [0, 1, 10], [0, 1], rng=rng)
  cj = eval_summary("runs/y", [1, 10], [0, 1], aug="cj+drq", rng=rng)
  both = dict(one, agents=one["agents"] + [dict(r, agent=6 + r["agent"]) for r in cj["agents"]])
  parts = split_by_look(one) + split_by_look(cj)
  merged = protocol_report.merge_summaries(parts)
  assert merged["runs"] == [p["run_dir"] for p in parts]
  assert [r["agent"] for r in merged["agents"]] == list(range(10))
  assert merged["checkpoint_step"] == 20 and merged["conditions"] == list(CONDITIONS)
  assert protocol_report.few_shot_rows(merged) == protocol_report.few_shot_rows(both)
  assert protocol_report.few_shot_rows(protocol_report.merge_summaries(split_by_look(one))) \
      == protocol_report.few_shot_rows(one)
  # Seeds of one look from two runs pool into one row.
  halves = [dict(one, run_dir=f"runs/s{s}", agents=[r for r in one["agents"] if r["seed"] == s])
            for s in (0, 1)]
  assert protocol_report.few_shot_rows(protocol_report.merge_summaries(halves)) \
      == protocol_report.few_shot_rows(one)
  assert "Runs: `runs/s0`, `runs/s1`." in protocol_report.few_shot_markdown(
      protocol_report.merge_summaries(halves), protocol_report.few_shot_rows(one))


@pytest.mark.parametrize("change, match", [
    (dict(config=dict(visual_seeds=3)), "runs/b was evaluated with visual_seeds = 3 and runs/a "
                                        "with 2; one curve needs one protocol"),
    (dict(config=dict(renderer="jax")), "with renderer = 'jax' and runs/a with 'pool'"),
    (dict(conditions=["none", "all"]), "with conditions = \\['none', 'all'\\]"),
    (dict(task="pendulum-swingup"), "runs/b evaluated pendulum-swingup and runs/a "
                                    "cartpole-balance; a few-shot curve is of one task"),
])
def test_merging_other_protocols_or_tasks_is_refused_naming_the_option(change, match):
  a, b = eval_summary("runs/a", [1], [0]), eval_summary("runs/b", [10], [0])
  b = dict(b, **{k: dict(b[k], **v) if isinstance(v, dict) else v for k, v in change.items()})
  with pytest.raises(ValueError, match=match):
    protocol_report.merge_summaries([a, b])
  # Options of how the protocol ran, not what it measured, may differ.
  c = dict(b, task=a["task"], conditions=a["conditions"],
           config=dict(a["config"], workers=4, max_envs=64))
  assert len(protocol_report.merge_summaries([a, c])["agents"]) == 2


def test_merging_a_seed_twice_is_refused():
  a = eval_summary("runs/a", [10], [0, 1])
  b = dict(a, run_dir="runs/b", agents=[r for r in a["agents"] if r["seed"] == 1])
  with pytest.raises(ValueError, match="seed 1 of SAC\\+AUG at levels:10 is in runs/a and in "
                                       "runs/b; pass one evaluation per seed"):
    protocol_report.merge_summaries([a, b])


def test_the_module_merges_eval_files_per_task(tmp_path, capsys):
  paths = []
  for k, s in enumerate([eval_summary("runs/a", [1], [0, 1]), eval_summary("runs/b", [10], [0, 1]),
                         eval_summary("runs/c", [1], [0], task="pendulum-swingup")]):
    paths.append(str(tmp_path / f"eval{k}.json"))
    with open(paths[-1], "w") as f:
      json.dump(s, f)
  few_shot.main(paths + ["--out", str(tmp_path / "out")])
  assert sorted(os.listdir(tmp_path / "out")) == [f"few_shot_cartpole-balance.{e}"
                                                  for e in ("json", "md", "png")]
  with open(tmp_path / "out" / "few_shot_cartpole-balance.json") as f:
    data = json.load(f)
  assert [r["looks"] for r in data["rows"]] == [1, 10] and data["runs"] == paths[:2]
  assert "few_shot_cartpole-balance.md, .json and .png" in capsys.readouterr().out
  with pytest.raises(SystemExit):
    few_shot.main(paths[2:] + ["--out", str(tmp_path / "none")])
  assert "more than one training-look range" in capsys.readouterr().err


SPEC = """
tasks = ["pendulum-swingup"]
seeds = [0, 1]
looks = [0, "levels:2"]
together = ["seeds"]
[evaluate]
visual_seeds = 2
dynamics_seeds = 2
train_episodes = 3
conditions = ["none", "floor", "all"]
quality = "fastest"
workers = 1
"""
"""A sweep of two runs (looks 0 and levels:2, seeds 0 and 1 as two agents each)."""


def test_the_sweep_writes_the_curve_of_a_task_whose_runs_differ_in_looks(tmp_path, capsys):
  spec = tmp_path / "spec.toml"
  spec.write_text(SPEC)
  out, runs = sw.plan(sw.load(str(spec)), str(tmp_path / "sweep"))
  sw.main([str(spec), "--dry-run", "--out", out])
  assert (f"few-shot curve of pendulum-swingup over looks 0, levels:2: "
          f"{out}/few_shot_pendulum-swingup.md, .json and .png, once its runs are evaluated"
          in capsys.readouterr().out)
  assert sw.few_shot_curves(out, runs) == []  # nothing evaluated yet
  rng = np.random.default_rng(2)
  summaries = [eval_summary(r.out_dir, [0 if r.look == "0" else 2], [0, 1], rng=rng,
                            cfg=r.eval_config(), task=r.task) for r in runs]
  for r, s in zip(runs, summaries):
    os.makedirs(os.path.dirname(r.eval_json))
    with open(r.eval_json, "w") as f:
      json.dump(s, f)
  assert sw.few_shot_curves(out, runs) == [os.path.join(out, "few_shot_pendulum-swingup.md")]
  with open(os.path.join(out, "few_shot_pendulum-swingup.json")) as f:
    data = json.load(f)
  want = protocol_report.few_shot_rows(protocol_report.merge_summaries(summaries))
  assert data["rows"] == json.loads(json.dumps(protocol_report.json_safe(want)))
  assert [(r["train_look"], r["seeds"]) for r in data["rows"]] == [("seed 0", [0, 1]),
                                                                   ("levels:2", [0, 1])]
  assert os.path.exists(os.path.join(out, "few_shot_pendulum-swingup.png"))
  # Runs of other protocols: the sweep says so and goes on.
  with open(runs[1].eval_json, "w") as f:
    json.dump(dict(summaries[1], config=dict(summaries[1]["config"], visual_seeds=5)), f)
  assert sw.few_shot_curves(out, runs) == []
  assert "few-shot curve of pendulum-swingup not drawn" in capsys.readouterr().err
