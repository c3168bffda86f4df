"""Tests of `dmcr_jax.benchmarks.paper_table` on synthetic `evaluate` results."""

import json

import numpy as np
import pytest

from dmcr_jax.benchmarks import paper_table
from dmcr_jax.train import paper_results

COLS = paper_results.COLUMNS


def eval_json(path, task, agents, renderer="pool", training=None):
  """A minimal eval.json: agents as (seed, aug, train return, {condition: return})."""
  result = dict(
      task=task, checkpoint_step=250_000, action_repeat=2, device="GPU X",
      training=training, wall_s=400.0,
      config=dict(visual_seeds=100, dynamics_seeds=3, train_episodes=100, quality="exact",
                  renderer=renderer),
      agents=[dict(agent=i, seed=seed, aug=aug, algo="sac_aug",
                   method=paper_results.method_name("sac_aug", aug),
                   train=dict(mean=train),
                   conditions={c: dict(mean=v) for c, v in conds.items()})
              for i, (seed, aug, train, conds) in enumerate(agents)])
  with open(path, "w") as f:
    json.dump(result, f)
  return str(path)


def returns(base):
  return {c: base - 10.0 * i for i, c in enumerate(COLS)}


def test_rows_average_seeds_and_stand_beside_the_papers(tmp_path, capsys):
  pool = eval_json(tmp_path / "w.json", "walker-walk",
                   [(0, "drq", 900.0, returns(800.0)), (1, "drq", 920.0, returns(820.0)),
                    (0, "cj+drq", 910.0, returns(850.0))],
                   training=dict(wall_s=1234.0, devices=["GPU X"], num_envs=16))
  ray = eval_json(tmp_path / "wj.json", "walker-walk",
                  [(0, "drq", 905.0, returns(790.0)), (1, "drq", 915.0, returns(830.0))],
                  renderer="jax")
  rows = paper_table.collect([ray, pool])
  assert [(r["method"], r["renderer"]) for r in rows] == [
      ("SAC+AUG", "jax"), ("SAC+AUG", "pool"), ("SAC+CJ+AUG", "pool")]
  aug = rows[1]
  assert aug["seeds"] == [0, 1] and aug["train"] == pytest.approx(910.0)
  want = {c: np.mean([800.0 - 10 * i, 820.0 - 10 * i]) for i, c in enumerate(COLS)}
  assert aug["conditions"] == pytest.approx(want)
  assert aug["e_g_all"] == pytest.approx((910.0 - want["all"]) / 910.0)
  assert aug["train_wall_s"] == 1234.0 and aug["train_devices"] == ["GPU X"]

  paper_table.main([pool, ray, "--out", str(tmp_path / "t" / "table.md")])
  text = (tmp_path / "t" / "table.md").read_text()
  paper_all = paper_results.table4("walker-walk", "SAC+AUG")["all"]
  assert f"{want['all'] - paper_all:,.1f}" in text      # our "all" minus the paper's
  assert "| | paper | | 5 | 919.3 |" in text              # the paper's row under ours
  # Ray caster minus pool, seed by seed: (+5, −10 per condition) and (−5, +10): means 0.
  assert "| walker-walk | SAC+AUG | 0, 1 | 0.0 | " + " | ".join(["0.0"] * len(COLS)) + " |" in text
  assert "SAC+CJ+AUG on walker-walk" not in text.split("Still missing")[1]
  assert "SAC+AUG on cheetah-run" in text.split("Still missing")[1]
  saved = json.loads((tmp_path / "t" / "table.json").read_text())
  assert len(saved["rows"]) == 3 and ["walker-walk", "SAC+AUG"] not in saved["missing"]
  capsys.readouterr()


def test_results_before_evaluate_recorded_the_method_still_name_it(tmp_path):
  path = eval_json(tmp_path / "c.json", "cartpole-balance", [(0, "drq", 966.0, returns(900.0))])
  result = json.loads(open(path).read())
  for agent in result["agents"]:
    del agent["method"], agent["algo"]
  del result["training"], result["device"]
  with open(path, "w") as f:
    json.dump(result, f)
  (row,) = paper_table.collect([path])
  assert row["method"] == "SAC+AUG" and row["train_devices"] == [] and row["eval_device"] is None


def test_what_is_not_an_evaluate_result_is_refused(tmp_path, capsys):
  bad = tmp_path / "bad.json"
  bad.write_text(json.dumps({"rows": []}))
  for path in (str(bad), str(tmp_path / "missing.json")):
    with pytest.raises(SystemExit):
      paper_table.main([path])
  err = capsys.readouterr().err
  assert "not an evaluate result" in err and "cannot read" in err


def test_a_run_at_the_default_action_repeat_reports_the_tasks_value(tmp_path):
  # Older eval.json files record None for a run trained at the task's default repeat.
  path = eval_json(tmp_path / "c.json", "cartpole-balance", [(0, "drq", 900.0, returns(800.0))])
  with open(path) as f:
    result = json.load(f)
  result["action_repeat"] = None
  with open(path, "w") as f:
    json.dump(result, f)
  [row] = paper_table.collect([path])
  assert row["action_repeat"] == 8   # the paper's Table 4 value for cartpole


def test_ray_caster_minus_pool_uses_only_the_seeds_evaluated_with_both(tmp_path):
  pool = eval_json(tmp_path / "p.json", "ball_in_cup-catch", [(0, "drq", 950.0, returns(600.0))])
  ray = eval_json(tmp_path / "j.json", "ball_in_cup-catch",
                  [(0, "drq", 960.0, returns(630.0)), (1, "drq", 100.0, returns(0.0))],
                  renderer="jax")
  text = paper_table.markdown(paper_table.collect([pool, ray]))
  # Seed 1 (jax only) would pull the means far down; the difference is seed 0's alone.
  assert "| ball_in_cup-catch | SAC+AUG | 0 | 10.0 | " + " | ".join(["30.0"] * len(COLS)) + " |" in text


def test_seeds_evaluated_apart_make_one_row_and_each_file_its_own_line(tmp_path):
  one = eval_json(tmp_path / "s0.json", "finger-spin", [(0, "drq", 600.0, returns(500.0))],
                  training=dict(wall_s=435.0, devices=["GPU X"]))
  two = eval_json(tmp_path / "s12.json", "finger-spin",
                  [(1, "drq", 900.0, returns(800.0)), (2, "drq", 930.0, returns(830.0))],
                  training=dict(wall_s=700.0, devices=["GPU Y"]))
  [row] = paper_table.merge(paper_table.collect([one, two]))
  assert row["seeds"] == [0, 1, 2] and row["sources"] == [one, two]
  assert row["train"] == pytest.approx(810.0)
  assert row["conditions"]["all"] == pytest.approx(np.mean([500.0, 800.0, 830.0]) - 10 * COLS.index("all"))
  assert row["e_g_all"] == pytest.approx((810.0 - row["conditions"]["all"]) / 810.0)
  text = paper_table.markdown(paper_table.collect([one, two]))
  assert "| finger-spin | SAC+AUG | pool | 3 | 810.0 |" in text
  # What each file ran stays apart: its seeds, wall time, device and name.
  assert "| 0 | 250,000 (100,000) |" in text and "| 435 | GPU X |" in text and f"`{one}`" in text
  assert "| 1, 2 | 250,000 (100,000) |" in text and "| 700 | GPU Y |" in text and f"`{two}`" in text


def test_files_that_cannot_make_one_row_are_refused_by_name(tmp_path, capsys):
  one = eval_json(tmp_path / "a.json", "finger-spin", [(0, "drq", 600.0, returns(500.0))])
  again = eval_json(tmp_path / "b.json", "finger-spin",
                    [(0, "drq", 610.0, returns(500.0)), (1, "drq", 900.0, returns(800.0))])
  with pytest.raises(SystemExit):
    paper_table.main([one, again])
  err = capsys.readouterr().err
  assert "seed 0 is in" in err and "a.json" in err and "b.json" in err
  other = tmp_path / "c.json"
  result = json.loads((tmp_path / "a.json").read_text())
  result["config"]["visual_seeds"] = 10
  result["agents"][0]["seed"] = 5
  other.write_text(json.dumps(result))
  with pytest.raises(ValueError, match="another protocol"):
    paper_table.merge(paper_table.collect([one, str(other)]))


def moving(base, factors=("camera", "all"), levels=(0.1, 0.2)):
  """Moving conditions as the protocol names them, `base` minus 100 × intensity
  minus 1 per factor."""
  return {f"moving-{f}@{i:g}": base - 100 * i - k for i in levels
          for k, f in enumerate(factors)}


def test_moving_conditions_get_their_own_table_beside_the_static_none(tmp_path):
  plain = eval_json(tmp_path / "p.json", "walker-walk", [(2, "drq", 900.0, returns(800.0))],
                    renderer="jax")
  assert "Under moving looks" not in paper_table.markdown(paper_table.collect([plain]))
  one = eval_json(tmp_path / "m.json", "walker-walk",
                  [(0, "drq", 900.0, {**returns(800.0), **moving(700.0)}),
                   (1, "drq", 920.0, {**returns(820.0), **moving(720.0)}),
                   (0, "cj+drq", 910.0, {**returns(850.0), **moving(750.0, ("body",))})],
                  renderer="jax")
  [aug, cj] = paper_table.merge(paper_table.collect([one]))
  assert aug["conditions"]["moving-all@0.2"] == pytest.approx(710.0 - 20 - 1)
  lines = paper_table.markdown(paper_table.collect([one])).splitlines()
  head = next(i for i, line in enumerate(lines)
              if line.startswith("| task | method | renderer | seeds | intensity"))
  assert lines[head] == ("| task | method | renderer | seeds | intensity | none | camera | "
                         "body | all | E_G (all) |")
  e_g = 100 * (910.0 - (710.0 - 10 - 1)) / 910.0
  aug_line = "| walker-walk | SAC+AUG | jax | 2 "
  assert lines[head + 2] == aug_line + f"| 0.1 | 810.0 | 700.0 | – | 699.0 | {e_g:.1f} % |"
  assert lines[head + 3].startswith(aug_line + "| 0.2 | 810.0 | 690.0 | – | 689.0 |")
  # A factor a row did not run is "–", and so is E_G without "all".
  assert lines[head + 4] == ("| walker-walk | SAC+CJ+AUG | jax | 1 | 0.1 | 850.0 | – | 740.0 "
                             "| – | – |")
  # A seed evaluated without moving conditions leaves its row's moving means out.
  [row] = paper_table.merge(paper_table.collect([plain, one])[:2])
  assert row["seeds"] == [0, 1, 2] and not any(c.startswith("moving-") for c in row["conditions"])
