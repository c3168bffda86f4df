"""Several runs' eval curves drawn together (`dmcr_jax.benchmarks.eval_curves`, and
`dmcr-sweep`'s eval_curves_<task> files): each group's mean and min–max over its seeds
at the steps all of them were evaluated at, as NumPy computes them; runs of other
protocols, a seed given twice, or a run without --eval-every refused naming why."""

import csv
import dataclasses
import json
import os

import numpy as np
import pytest

from dmcr_jax.benchmarks import eval_curves
from dmcr_jax.train import config, eval_curve
from dmcr_jax.train import sweep as sw

SPEC = """
tasks = ["pendulum-swingup"]
seeds = [0, 1]
looks = ["0", "levels:2"]
together = ["seeds"]
[train]
steps = 30
eval_every = 10
eval_conditions = ["none", "all"]
"""
"""Two runs (look 0 and levels:2), seeds 0 and 1 as the two agents of each, evaluated
every 10 steps."""

STEPS = (10, 20, 30)


def fake_runs(tmp_path, rng):
  """The spec's runs with config.json and an eval_curve.csv of random returns (agent 1
  of the levels:2 run also evaluated at step 40); {(run index, agent): {(step, panel):
  return}}."""
  spec = tmp_path / "spec.toml"
  spec.write_text(SPEC)
  out, runs = sw.plan(sw.load(str(spec)), str(tmp_path / "sweep"))
  values = {}
  for i, run in enumerate(runs):
    os.makedirs(run.out_dir)
    config.save_config(sw.parse_train(run), run.out_dir)
    with open(os.path.join(run.out_dir, eval_curve.CSV), "w", newline="") as f:
      w = csv.DictWriter(f, fieldnames=eval_curve.FIELDS)
      w.writeheader()
      for step in STEPS + ((40,) if i == 1 else ()):
        for agent in (0, 1):
          if step == 40 and agent == 0:
            continue
          train = float(rng.uniform(0, 1000))
          values[(i, agent)] = values.get((i, agent), {})
          values[(i, agent)][(step, eval_curves.TRAIN)] = train
          for c in ("none", "all"):
            ret = float(rng.uniform(0, 1000))
            values[(i, agent)][(step, c)] = ret
            w.writerow(dict(step=step, agent=agent, label=f"seed {agent}", condition=c,
                            mean_return=ret, train_return=train, e_g="", eval_s=1.0))
  return spec, out, runs, values


def test_groups_give_each_steps_mean_and_min_max_over_seeds(tmp_path, capsys):
  spec, out, runs, values = fake_runs(tmp_path, np.random.default_rng(0))
  sw.main([str(spec), "--dry-run", "--out", out])
  assert (f"eval curves of pendulum-swingup's 2 runs evaluated during training: "
          f"{out}/eval_curves_pendulum-swingup.md" in capsys.readouterr().out)
  assert sw.eval_curves(out, runs) == [os.path.join(out, "eval_curves_pendulum-swingup.md")]
  with open(os.path.join(out, "eval_curves_pendulum-swingup.json")) as f:
    groups = json.load(f)["groups"]
  assert [(g["looks"], g["num_looks"], g["seeds"]) for g in groups] == [
      ("seed 0", 1, [0, 1]), ("levels:2", 2, [0, 1])]
  for i, g in enumerate(groups):
    assert g["steps"] == list(STEPS)   # step 40: only one of the seeds
    assert list(g["series"]) == [eval_curves.TRAIN, "none", "all"]
    for panel, s in g["series"].items():
      table = np.array([[values[(i, a)][(step, panel)] for step in STEPS] for a in (0, 1)])
      np.testing.assert_allclose(s["mean"], table.mean(0))
      np.testing.assert_allclose(s["min"], table.min(0))
      np.testing.assert_allclose(s["max"], table.max(0))
  with open(os.path.join(out, "eval_curves_pendulum-swingup.md")) as f:
    md = f.read()
  first = groups[1]["series"]["all"]
  assert (f"| 10 | " in md and f"{first['mean'][0]:.1f} ({first['min'][0]:.1f}–"
          f"{first['max'][0]:.1f})" in md)
  assert os.path.getsize(os.path.join(out, "eval_curves_pendulum-swingup.png")) > 0


def test_other_protocols_a_seed_twice_or_no_curve_are_refused_naming_why(tmp_path, capsys):
  _, out, runs, _ = fake_runs(tmp_path, np.random.default_rng(1))
  a, b = (r.out_dir for r in runs)
  plain = tmp_path / "plain"
  plain.mkdir()
  config.save_config(config.load_config(a), str(plain))
  with pytest.raises(ValueError, match="no eval_curve.csv; it was trained without --eval-every"):
    eval_curves.curves([a, str(plain)], out)
  with pytest.raises(ValueError, match="is .* a `train` output folder"):
    eval_curves.curves([a, out], out)
  with pytest.raises(ValueError, match="seed 0 of drq on seed 0 comes twice"):
    eval_curves.curves([a, a], out)
  cfg = config.load_config(b)
  config.save_config(dataclasses.replace(cfg, eval_looks=cfg.eval_looks + 1), b)
  with pytest.raises(ValueError, match=f"{b} evaluated during training with eval_looks="):
    eval_curves.curves([a, b], out)
  # The sweep says so on stderr and goes on without the picture.
  assert sw.eval_curves(out, runs) == []
  assert "eval curves of pendulum-swingup not drawn together" in capsys.readouterr().err
  config.save_config(cfg, b)
  with open(os.path.join(b, eval_curve.CSV)) as f:
    rows = [r for r in csv.DictReader(f) if r["condition"] == "all"]
  with open(os.path.join(b, eval_curve.CSV), "w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=eval_curve.FIELDS)
    w.writeheader()
    w.writerows(rows)
  with pytest.raises(ValueError, match="evaluated conditions all, .* none, all"):
    eval_curves.curves([a, b], out)


def test_the_command_draws_two_groups_and_refuses_one(tmp_path, capsys):
  _, out, runs, _ = fake_runs(tmp_path, np.random.default_rng(2))
  dest = str(tmp_path / "pictures")
  eval_curves.main([r.out_dir for r in runs] + ["--out", dest])
  assert f"wrote {dest}/eval_curves_pendulum-swingup.md, .json and .png" in capsys.readouterr().out
  with pytest.raises(SystemExit):
    eval_curves.main([runs[0].out_dir, "--out", dest])
  assert "the picture compares at least two" in capsys.readouterr().err
