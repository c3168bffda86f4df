"""Tests of `dmcr_jax.train.curves` (learning curves compared at equal transition counts),
against NumPy recomputations on synthetic train logs."""

import csv
import json
import os

import numpy as np
import pytest

from dmcr_jax.train import curves


def write_log(folder, agent_returns, steps):
  """A train-style log.csv: agent a's episode ending at steps[i] returned agent_returns[a][i]."""
  os.makedirs(folder, exist_ok=True)
  with open(os.path.join(folder, "log.csv"), "w", newline="") as f:
    w = csv.writer(f)
    w.writerow(["step", "agent", "seed", "episode_return", "wall_s"])
    for a, returns in enumerate(agent_returns):
      for s, r in zip(steps, returns):
        w.writerow([s, a, a, r, 1.0])
  return str(folder)


STEPS = np.arange(100, 1001, 100)          # an episode end every 100 steps, to 1,000


def test_window_means_and_noise_match_numpy(tmp_path):
  rng = np.random.default_rng(0)
  old = [np.linspace(0, 900, 10) + rng.normal(0, 30, 10) for _ in range(2)]
  new = [np.linspace(0, 900, 10) + rng.normal(0, 30, 10) for _ in range(2)]
  runs = {"old": [curves.read_log(write_log(tmp_path / "old", old, STEPS))],
          "new": [curves.read_log(write_log(tmp_path / "new", new, STEPS))]}
  result = curves.compare(runs, bins=5)
  np.testing.assert_allclose(result["edges"], np.linspace(100, 1000, 6))
  # Window i is (e_i, e_i+1], the first also taking e_0: [100, 280] holds the
  # episodes ending at 100 and 200, (280, 460] those at 300 and 400, …
  e = np.linspace(100, 1000, 6)
  masks = [((STEPS > e[i]) | (i == 0) & (STEPS == e[0])) & (STEPS <= e[i + 1])
           for i in range(5)]
  assert [int(m.sum()) for m in masks] == [2, 2, 2, 2, 2]
  for label, returns in (("old", old), ("new", new)):
    per_agent = np.array([[np.mean(r[m]) for m in masks] for r in returns])
    np.testing.assert_allclose(result["labels"][label]["agents"], per_agent)
    np.testing.assert_allclose(result["labels"][label]["mean"], per_agent.mean(0))
    np.testing.assert_allclose(result["labels"][label]["spread"],
                               per_agent.max(0) - per_agent.min(0))
  delta = (np.array(result["labels"]["new"]["mean"])
           - np.array(result["labels"]["old"]["mean"]))
  np.testing.assert_allclose(result["diff"]["new"]["delta"], delta)
  noise = np.maximum(result["labels"]["new"]["spread"], result["labels"]["old"]["spread"])
  assert result["diff"]["new"]["within_noise"] == list(np.abs(delta) <= noise)


def test_a_curve_that_learns_slower_is_flagged_and_seeds_in_separate_runs_pool(tmp_path):
  good = [np.linspace(0, 900, 10) + d for d in (-20, 20)]
  slow = [np.linspace(0, 300, 10) + d for d in (-20, 20)]
  # The slow setting's two seeds were trained apart: one run each, one label.
  runs = {"old": [curves.read_log(write_log(tmp_path / "old", good, STEPS))],
          "new": [curves.read_log(write_log(tmp_path / f"new{i}", [c], STEPS))
                  for i, c in enumerate(slow)]}
  result = curves.compare(runs, bins=5)
  assert len(result["labels"]["new"]["agents"]) == 2
  flags = result["diff"]["new"]["within_noise"]
  assert flags[0] and not any(flags[2:])   # equal at the start, apart later
  assert "outside" in curves.markdown(result)
  assert "One seed" not in curves.markdown(result)


def test_one_seed_per_label_is_said_to_have_no_noise_estimate(tmp_path):
  runs = {"old": [curves.read_log(write_log(tmp_path / "old", [np.linspace(0, 900, 10)], STEPS))],
          "new": [curves.read_log(write_log(tmp_path / "new", [np.linspace(0, 800, 10)], STEPS))]}
  table = curves.markdown(curves.compare(runs, bins=5))
  assert "One seed for old and new: no spread" in table


def test_windows_without_an_episode_are_counted_not_shown(tmp_path):
  # Episodes of all envs end together every 400 steps: 3 of 10 windows hold one.
  steps = np.array([400, 800, 1200])
  runs = {label: [curves.read_log(write_log(tmp_path / label, [[1.0, 2.0, 3.0],
                                                               [1.5, 2.5, 3.5]], steps))]
          for label in ("old", "new")}
  result = curves.compare(runs, bins=10)
  shown = [i for i, m in enumerate(result["labels"]["old"]["mean"]) if np.isfinite(m)]
  assert shown == [0, 4, 9]
  table = curves.markdown(result)
  rows = [l for l in table.splitlines() if l.startswith("| ") and "–" in l.split("|")[1]]
  e = result["edges"]
  assert [r.split("|")[1].strip() for r in rows] == [f"{e[i]:,.0f}–{e[i + 1]:,.0f}"
                                                      for i in shown]
  assert "7 of 10 windows, in which no run ended an episode, are not shown" in table
  assert "3 of 3 windows within seed noise" in table


def test_windows_end_at_the_shortest_run(tmp_path):
  runs = {"a": [curves.read_log(write_log(tmp_path / "a", [np.arange(10.0)], STEPS))],
          "b": [curves.read_log(write_log(tmp_path / "b", [np.arange(5.0)], STEPS[:5]))]}
  result = curves.compare(runs, bins=4)
  assert result["edges"][-1] == 500


def test_command_line_writes_table_plot_and_json_and_refuses_bad_input(tmp_path, capsys):
  a = write_log(tmp_path / "a", [np.arange(10.0), np.arange(10.0) + 1], STEPS)
  b = write_log(tmp_path / "b", [np.arange(10.0) + 0.5, np.arange(10.0) + 1.5], STEPS)
  out = tmp_path / "cmp"
  curves.main([f"old={a}", f"new={b}", "--bins", "3", "--out", str(out)])
  assert "3 of 3 windows within seed noise" in capsys.readouterr().out
  assert {"curves.png", "curves.json", "curves.md"} <= set(os.listdir(out))
  assert json.load(open(out / "curves.json"))["runs"] == {"old": [a], "new": [b]}
  for bad in ([a], [f"old={tmp_path / 'missing'}"], [f"old={a}", "--bins", "0"]):
    with pytest.raises(SystemExit):
      curves.main(bad)
  err = capsys.readouterr().err
  assert "LABEL=RUN_DIR" in err and "no log.csv" in err and "--bins" in err
