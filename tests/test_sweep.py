"""`dmcr-sweep` (train/sweep.py): a spec's errors refused before anything runs, its
expansion into runs with stable folders, a tiny sweep of two runs trained, evaluated
and merged into the paper table's rows, skipped on a rerun, and the same spec as
Ray tasks on a local instance."""

import glob
import json
import os
import shutil

import pytest

from dmcr_jax.benchmarks import paper_table
from dmcr_jax.train import checkpoint
from dmcr_jax.train import sweep as sw

# test_train's group: the runs are test_train's host-driver size.
pytestmark = pytest.mark.xdist_group("train")

TINY = """
tasks = ["pendulum-swingup"]
seeds = [0, 1]
[train]
steps = 20
num-envs = 1
action_repeat = 100
image_size = 16
buffer_capacity = 200
warmup_steps = 5
quality = "fastest"
workers = 1
batch_size = 8
log_every = 5
checkpoint_every = 10
[evaluate]
visual_seeds = 2
dynamics_seeds = 1
train_episodes = 1
conditions = ["none", "all"]
renderer = "pool"
quality = "fastest"
workers = 1
"""
"""Two runs (seeds 0 and 1 apart) of pendulum at action repeat 100 (10 steps an
episode), 20 steps each, and a 2-look evaluation with the pool."""


def write(tmp_path, text, name="spec.toml"):
  path = tmp_path / name
  path.write_text(text)
  return str(path)


def plan_of(tmp_path, text):
  return sw.plan(sw.load(write(tmp_path, text)), str(tmp_path / "sweep"))


@pytest.mark.parametrize("text, match", [
    ('tasks = ["pendulum-swingup"]\nseed = [0]', "unknown key 'seed'; valid: out, tasks, seeds"),
    ('seeds = [0]', "'tasks' is missing"),
    ('tasks = ["pendulum-swingup"]\n[train]\nnum_env = 4',
     "[train] has an unknown key 'num_env'; valid: action_repeat, agent_loop"),
    ('tasks = ["pendulum-swingup"]\n[train]\nseeds = "0"', "[train] may not set 'seeds'"),
    ('tasks = ["pendulum-swingup"]\n[evaluate]\nlooks = 3',
     "[evaluate] has an unknown key 'looks'; valid: visual_seeds, dynamics_seeds"),
    ('tasks = ["pendulum-swingup"]\ntogether = ["tasks"]',
     "'together' names 'tasks'; valid: seeds, augs"),
    ('tasks = ["pendulum-swingup"]\nlooks = ["levels:1,10"]', "names several ranges"),
    ('tasks = ["pendulum-swingup"]\nlooks = ["levels:0"]', "levels:0 holds no seed"),
    ('tasks = ["walker-fly"]', "run walker-fly: "),
    ('tasks = ["pendulum-swingup"]\naugs = ["blur"]', "valid names"),
    ('tasks = ["pendulum-swingup"]\n[train]\nsteps = 0', "steps must be a positive int"),
    ('tasks = ["pendulum-swingup"]\n[evaluate]\nconditions = ["target"]',
     "[evaluate] for pendulum-swingup: conditions ['target'] are not valid"),
    ('tasks = ["pendulum-swingup"]\n[per_task.walker-walk]\nsteps = 5',
     "[per_task] names 'walker-walk', not one of tasks"),
    ('tasks = ["pendulum-swingup"]\nseeds = "0,x"', "'seeds' takes ints"),
    ('tasks = ["pendulum-swingup"]\n[ray]\ngpus = 2', "[ray] has an unknown key 'gpus'"),
    ('tasks = "pendulum-swingup', "not valid TOML"),
])
def test_a_bad_spec_is_refused_naming_the_key(tmp_path, text, match, capsys):
  path = write(tmp_path, text)
  with pytest.raises(SystemExit) as e:
    sw.main([path, "--out", str(tmp_path / "sweep")])
  assert e.value.code == 2
  err = capsys.readouterr().err
  assert match in err, err
  assert not os.path.exists(tmp_path / "sweep")


def test_a_spec_expands_to_runs_with_stable_folders(tmp_path, capsys):
  text = """
tasks = ["cartpole-balance", "walker-walk"]
seeds = "0,1,2"
augs = ["drq", "cj+drq"]
looks = [0, "levels:10"]
together = ["seeds"]
[train]
steps = 1000
logger = ["csv", "tensorboard"]
[per_task.walker-walk]
steps = 2000
"""
  out, runs = plan_of(tmp_path, text)
  assert out == str(tmp_path / "sweep")
  assert [r.name for r in runs[:4]] == [
      "cartpole-balance-drq-s0_1_2-v0", "cartpole-balance-cj+drq-s0_1_2-v0",
      "cartpole-balance-drq-s0_1_2-levels10", "cartpole-balance-cj+drq-s0_1_2-levels10"]
  assert len(runs) == 8 and all(r.state() == "new" for r in runs)
  assert plan_of(tmp_path, text)[1] == runs  # the same spec, the same runs
  cfgs = [sw.parse_train(r) for r in runs]
  assert {c.steps for c, r in zip(cfgs, runs) if r.task == "walker-walk"} == {2000}
  assert {c.steps for c, r in zip(cfgs, runs) if r.task == "cartpole-balance"} == {1000}
  assert all(c.seeds == (0, 1, 2) and c.out_dir == r.out_dir for c, r in zip(cfgs, runs))
  assert cfgs[2].visual_seeds == "levels:10" and cfgs[0].loggers == ("csv", "tensorboard")
  assert runs[2].group == "sweep/cartpole-balance-drq-levels10"  # W&B: seeds apart, one group
  sw.main([write(tmp_path, text), "--out", out, "--dry-run"])
  lines = capsys.readouterr().out.splitlines()
  assert lines[0].startswith("cartpole-balance-drq-s0_1_2-v0 [new]: dmcr-train --task "
                             "cartpole-balance --seeds 0,1,2 --visual-seeds 0 --steps 1000")
  assert lines[-1] == f"8 runs in {out}" and not os.path.exists(out)


SPECS = sorted(glob.glob(os.path.join(os.path.dirname(os.path.dirname(__file__)),
                                      "benchmarks", "sweeps", "*.toml")))


@pytest.mark.parametrize("path", SPECS, ids=os.path.basename)
def test_the_committed_specs_plan_as_dmcr_train_parses_them(path, tmp_path):
  out, runs = sw.plan(sw.load(path), str(tmp_path / "sweep"))
  assert runs and all(r.state() == "new" for r in runs)
  assert all(sw.parse_train(r).task == r.task for r in runs)


def test_only_runs_the_runs_it_names_and_refuses_a_pattern_of_none(tmp_path, monkeypatch,
                                                                  capsys):
  text = 'tasks = ["cartpole-balance", "pendulum-swingup"]\nseeds = [0, 1]\n[train]\nsteps = 10\n'
  spec = write(tmp_path, text)
  out, runs = plan_of(tmp_path, text)
  names = [r.name for r in runs]
  assert sw.select(runs, "pendulum-*,cartpole-balance-drq-s1-v0") == {
      "pendulum-swingup-drq-s0-v0", "pendulum-swingup-drq-s1-v0",
      "cartpole-balance-drq-s1-v0"}
  ran = []
  monkeypatch.setattr(sw, "run_one", lambda run, progress=False: ran.append(run.name) or dict(
      name=run.name, state=run.state(), eval_json=None, interrupted=False))
  result = sw.sweep(out, runs, only={"pendulum-swingup-drq-s1-v0"})
  assert ran == ["pendulum-swingup-drq-s1-v0"]
  assert [r["name"] for r in result["runs"]] == names    # every run listed, as it stands
  assert {r["name"]: r["state"] for r in result["runs"]} == dict.fromkeys(names, "new")
  assert "cartpole-balance-drq-s0-v0: new, not in --only" in capsys.readouterr().err
  sw.main([spec, "--out", out, "--only", "cartpole-*", "--dry-run"])
  lines = capsys.readouterr().out.splitlines()
  assert [l.split(" ")[0] for l in lines[:-1]] == names[:2]
  assert lines[-1] == f"2 of 4 runs in {out} (--only)"
  with pytest.raises(SystemExit) as e:
    sw.main([spec, "--out", out, "--only", "cartpole-*,walker-*"])
  assert e.value.code == 2
  err = capsys.readouterr().err
  assert "--only 'walker-*' matches none of the spec's runs: " + ", ".join(names) in err
  assert ran == ["pendulum-swingup-drq-s1-v0"]


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory):
  """The TINY sweep run to the end in this process; its folder, runs and result."""
  tmp = tmp_path_factory.mktemp("sweep")
  out, runs = sw.plan(sw.load(write(tmp, TINY)), str(tmp / "sweep"))
  return out, runs, sw.sweep(out, runs)


@pytest.mark.slow
def test_a_sweep_trains_evaluates_and_merges_its_runs(tiny_sweep, tmp_path):
  out, runs, result = tiny_sweep
  assert [r.name for r in runs] == ["pendulum-swingup-drq-s0-v0", "pendulum-swingup-drq-s1-v0"]
  assert [r["state"] for r in result["runs"]] == ["new", "new"]
  assert all(r.state() == "done" for r in runs)
  assert result["few_shot"] == []  # one training look: no few-shot curve
  for r in runs:
    assert checkpoint.steps(r.out_dir)[-1] == 20
    with open(r.eval_json) as f:
      assert json.load(f)["checkpoint_step"] == 20
  # The merged table is paper_table's, from the runs' eval.json: one row of both seeds.
  with open(os.path.join(out, "table.json")) as f:
    (rows,) = [v["rows"] for v in json.load(f).values()]
  want = paper_table.merge(paper_table.collect([r.eval_json for r in runs]))
  assert rows == json.loads(json.dumps(want))
  assert len(rows) == 1 and rows[0]["seeds"] == [0, 1]
  with open(os.path.join(out, "table.md")) as f:
    assert f.read() == paper_table.markdown(paper_table.collect([r.eval_json for r in runs]))
  with open(os.path.join(out, "runs.json")) as f:
    assert [r["name"] for r in json.load(f)] == [r.name for r in runs]


@pytest.mark.slow
def test_a_rerun_skips_done_runs_and_resumes_an_interrupted_one(tiny_sweep, tmp_path, capsys):
  out, runs, _ = tiny_sweep
  copy = str(tmp_path / "sweep")
  shutil.copytree(out, copy)
  spec = write(tmp_path, f'out = "{copy}"\n' + TINY)
  _, moved = sw.plan(sw.load(spec), copy)
  # Run 1 as if killed after its checkpoint at 10, before the end and its evaluation.
  shutil.rmtree(os.path.join(checkpoint.folder(moved[1].out_dir), "20"))
  shutil.rmtree(os.path.join(moved[1].out_dir, "eval"))
  assert [r.state() for r in moved] == ["done", "resume"]
  sw.main([spec])
  err = capsys.readouterr().err
  assert f"sweep: {moved[0].name}: done, skipped" in err
  assert f"sweep: {moved[1].name}: done" in err
  assert [r.state() for r in moved] == ["done", "done"]
  assert checkpoint.steps(moved[1].out_dir)[-1] == 20
  with open(os.path.join(moved[0].out_dir, "eval", "eval.json")) as f, \
      open(runs[0].eval_json) as g:
    assert json.load(f) == json.load(g)  # not evaluated again


@pytest.mark.slow
def test_the_same_spec_runs_as_ray_tasks_on_a_local_instance(tiny_sweep, tmp_path):
  ray = pytest.importorskip("ray")
  out, runs, _ = tiny_sweep
  copy = str(tmp_path / "sweep")
  shutil.copytree(out, copy)
  _, moved = sw.plan(sw.load(write(tmp_path, TINY)), copy)
  for r in moved:  # both trained, neither evaluated: the Ray tasks evaluate them
    shutil.rmtree(os.path.join(r.out_dir, "eval"))
  os.remove(os.path.join(copy, "table.json"))
  ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
  try:
    result = sw.sweep(copy, moved, backend="ray")
  finally:
    ray.shutdown()
  assert [r["state"] for r in result["runs"]] == ["evaluate", "evaluate"]
  assert not any("error" in r for r in result["runs"]), result["runs"]
  with open(os.path.join(copy, "table.json")) as f:
    (rows,) = [v["rows"] for v in json.load(f).values()]
  assert rows[0]["seeds"] == [0, 1]
