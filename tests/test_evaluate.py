"""The zero-shot evaluation (train/evaluate.py) on a tiny, untrained checkpoint."""

import dataclasses
import json
import os

import jax
import numpy as np
import pytest

import dmcr_jax
from dmcr_jax import protocol
from dmcr_jax import protocol_report as report
from dmcr_jax.train import evaluate as ev
from dmcr_jax.train import loop, sac

# test_demo's and test_train's group: the JAX-renderer evaluation here is sized as the
# demo's (test_demo.py), so one worker compiles that env and policy once for both.
pytestmark = pytest.mark.xdist_group("train")

# Cartpole at action repeat 100: 10 agent steps per episode.
CFG = loop.TrainConfig(task="cartpole-balance", action_repeat=100, image_size=16, seeds=(0, 1), num_envs=1,
                       quality="fastest", workers=1,
                       sac=sac.SACConfig(batch_size=8, conv_channels=4, feature_dim=8,
                                         hidden_dim=16))
TINY = ev.EvalConfig(visual_seeds=2, dynamics_seeds=2, train_episodes=3, quality="fastest",
                     workers=1)


def _untrained_run(out: str, cfg: loop.TrainConfig) -> str:
  """`out` made a `train`-style folder of `cfg`'s freshly initialised agents (no
  training), checkpointed at step 3."""
  cfg = loop.TrainConfig(**{**cfg.__dict__, "out_dir": out})
  os.makedirs(out, exist_ok=True)
  loop.save_config(cfg, out)
  task = dmcr_jax.load(cfg.task)
  agents = loop.init_agents(cfg, (16, 16, 9), task.action_size)
  loop._save(loop._checkpointer(out), 3, agents, jax.random.key(0))
  return out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
  """A `train`-style folder holding two freshly initialised agents (no training)."""
  return _untrained_run(str(tmp_path_factory.mktemp("run")), CFG)


def test_conditions_follow_the_papers_factor_table():
  assert ev.conditions_for("cartpole-balance") == (
      "none", "light", "camera", "body", "floor", "background", "all")
  assert ev.conditions_for("fish-swim") == ("none", "light", "camera", "body", "floor",
                                            "target", "all")
  assert "reflectance" in ev.conditions_for("cheetah-run")


def test_generalization_error():
  assert ev.generalization_error(900.0, 450.0) == pytest.approx(0.5)
  assert ev.generalization_error(500.0, 600.0) == pytest.approx(-0.2)
  assert np.isnan(ev.generalization_error(0.0, 10.0))


def test_held_out_seeds_never_touch_a_training_range():
  seeds = ev.held_out_seeds(100, seed=0)
  assert len(np.unique(seeds)) == 100
  assert (seeds >= dmcr_jax.TEST_SEEDS.start).all() and (seeds < dmcr_jax.TEST_SEEDS.stop).all()
  assert not ((seeds >= dmcr_jax.TRAIN_SEEDS.start) & (seeds < dmcr_jax.TRAIN_SEEDS.stop)).any()
  np.testing.assert_array_equal(seeds, ev.held_out_seeds(100, seed=0))
  assert not np.array_equal(seeds, ev.held_out_seeds(100, seed=1))
  protocol.check_disjoint(seeds, dmcr_jax.levels(1000))
  with pytest.raises(RuntimeError, match="training looks"):
    protocol.check_disjoint(np.array([5, 2**30 + 1]), dmcr_jax.levels(10))


def test_bad_protocols_are_rejected():
  with pytest.raises(ValueError, match="valid: none, light"):
    ev.check_eval_config(ev.EvalConfig(conditions=("fog",)), "cartpole-balance")
  with pytest.raises(ValueError, match="at most"):
    ev.check_eval_config(ev.EvalConfig(visual_seeds=2, dynamics_seeds=3), "cartpole-balance")
  with pytest.raises(ValueError, match="positive int"):
    ev.check_eval_config(ev.EvalConfig(visual_seeds=0), "cartpole-balance")
  with pytest.raises(ValueError, match="pool, jax"):
    ev.check_eval_config(ev.EvalConfig(renderer="opengl"), "cartpole-balance")
  with pytest.raises(ValueError, match="only to renderer 'pool'"):
    ev.check_eval_config(ev.EvalConfig(renderer="jax", workers=2), "cartpole-balance")
  with pytest.raises(ValueError, match="max_envs must be a positive int"):
    ev.check_eval_config(ev.EvalConfig(max_envs=0), "cartpole-balance")
  with pytest.raises(SystemExit):
    ev.main(["/nonexistent/run"])


@pytest.mark.slow
def test_the_jax_renderer_runs_the_same_protocol(tmp_path, capsys):
  # The same protocol rendered by the JAX ray caster: the table has the same shape,
  # and says which renderer drew it. `dmcr-demo`'s evaluation in test_demo.py (its
  # task, training looks, networks and evaluation config; same group and worker), so
  # the block program is the one the demo compiled.
  from tests.test_demo import TINY as DEMO
  run_dir = _untrained_run(str(tmp_path / "run"), loop.TrainConfig(
      **{**CFG.__dict__, "task": DEMO.task, "sac": DEMO.sac,
         "visual_seeds": f"levels:{DEMO.train_looks}"}))
  cfg = DEMO.eval_config()
  assert cfg.renderer == "jax"
  summary = ev.evaluate(run_dir, cfg, out_dir=str(tmp_path / "eval"), agents=[0],
                        progress=False)
  row = summary["agents"][0]
  assert len(row["train"]["episodes"]) == cfg.train_episodes
  assert summary["conditions"] == list(ev.conditions_for(DEMO.task))
  for c in summary["conditions"]:
    assert len(row["conditions"][c]["episodes"]) == cfg.visual_seeds * cfg.dynamics_seeds
    assert np.isfinite(row["conditions"][c]["mean"])
  with open(tmp_path / "eval" / "eval.md") as f:
    assert "rendered by the JAX ray caster" in f.read()
  # Without a progress bar, a line per block (every episode, the training looks'
  # too, runs in one block).
  lines = [l for l in capsys.readouterr().err.splitlines() if l.startswith("evaluate: ")]
  assert [l.split(",")[0] for l in lines] == ["evaluate: block 1/1 done"], lines


@pytest.mark.slow
def test_protocol_table_arithmetic_and_determinism(run_dir, tmp_path):
  first = ev.evaluate(run_dir, TINY, out_dir=str(tmp_path / "a"), progress=False)
  conditions = list(ev.conditions_for("cartpole-balance"))
  assert first["conditions"] == conditions and first["checkpoint_step"] == 3
  assert first["action_repeat"] == 100 and first["device"] == jax.devices()[0].device_kind
  assert first["training"] is None  # the fixture's run has no summary.json
  assert len(first["agents"]) == 2
  for row in first["agents"]:
    assert len(row["train"]["episodes"]) == TINY.train_episodes
    for c in conditions:
      cell = row["conditions"][c]
      assert len(cell["episodes"]) == TINY.visual_seeds * TINY.dynamics_seeds
      assert cell["mean"] == pytest.approx(np.mean(cell["episodes"]))
      assert cell["e_g"] == pytest.approx(
          (row["train"]["mean"] - cell["mean"]) / row["train"]["mean"])
  mean = first["mean"]
  assert mean["train"] == pytest.approx(np.mean([r["train"]["mean"] for r in first["agents"]]))
  # No test look in the training range [0, 2**30).
  assert min(first["test_visual_seeds"]) >= 2**30

  with open(tmp_path / "a" / "eval.md") as f:
    table = f.read()
  header = next(line for line in table.splitlines() if line.startswith("| agent"))
  assert header == "| agent | train | " + " | ".join(conditions) + " | E_G (all) |"
  assert table.count("| seed ") == 2 and "**mean**" in table
  assert os.path.getsize(tmp_path / "a" / "eval.png") > 0

  # The same checkpoint and seeds give the same episodes, return for return, with
  # the agents in another order (each agent's episodes move to other envs). Two
  # agents and every condition, as above: the same program, nothing compiles again.
  some = conditions
  again = ev.evaluate(run_dir, TINY, out_dir=str(tmp_path / "b"), agents=[1, 0],
                      progress=False)
  for i, a in enumerate((1, 0)):
    assert again["agents"][i]["train"]["episodes"] == first["agents"][a]["train"]["episodes"]
    for c in some:
      assert (again["agents"][i]["conditions"][c]["episodes"]
              == first["agents"][a]["conditions"][c]["episodes"])
  with open(tmp_path / "b" / "eval.json") as f:
    assert [r["agent"] for r in json.load(f)["agents"]] == [1, 0]


@pytest.mark.slow
def test_invariance_is_zero_without_visual_change_and_positive_with_floors(run_dir, tmp_path):
  from dmcr_jax.train import analysis
  # 27 held-out looks + the training look: 28 envs, the size of the protocol test's
  # pool envs (2 agents × 14 episodes), whose physics compilation this reuses.
  result = analysis.encoder_invariance(run_dir, str(tmp_path), looks=27, steps=2,
                                       vary=("none", "floor"), quality="fastest", workers=1)
  assert result["physical_state_equal"] == {"none": True, "floor": True}
  assert result["looks_differing"] == {"none": 0, "floor": 26}
  # Same state, same look: identical pixels, features equal up to float rounding
  # (batch rows may take different vector paths); other floors move them.
  assert max(result["std"]["none"]) < 1e-6
  assert max(result["std"]["floor"]) > 1e-3
  assert result["std"]["floor"] == sorted(result["std"]["floor"])
  assert os.path.getsize(tmp_path / "invariance.png") > 0


def test_conv_activations_match_a_numpy_convolution():
  from dmcr_jax.train import analysis
  # The fixture run's first agent, as `loop.init_agents` makes it (one jitted
  # initialiser, compiled already for the run directories).
  agent = jax.tree.map(lambda x: x[0], loop.init_agents(CFG, (16, 16, 9), 1))
  obs = np.random.default_rng(0).integers(0, 256, (2, 16, 16, 9), dtype=np.uint8)
  maps = analysis.conv_activations(agent.networks.encoder, agent.params["encoder"], obs)
  assert [m.shape for m in maps] == [(2, 7, 7), (2, 5, 5), (2, 3, 3), (2, 1, 1)]
  p = agent.params["encoder"]["params"]["conv0"]
  x = obs.astype(np.float64) / 255.0
  out = np.zeros((2, 7, 7, p["kernel"].shape[-1]))
  for i in range(7):
    for j in range(7):
      patch = x[:, 2 * i:2 * i + 3, 2 * j:2 * j + 3, :]
      out[:, i, j] = np.einsum("bhwc,hwco->bo", patch, np.asarray(p["kernel"])) + p["bias"]
  np.testing.assert_allclose(maps[0], np.maximum(out, 0).mean(-1), rtol=1e-4, atol=1e-5)


@pytest.mark.slow
def test_episode_video_tiles_the_looks_frame_by_frame(run_dir, tmp_path):
  import imageio.v2 as imageio
  from dmcr_jax.train import analysis
  # 28 looks: 28 envs, as the protocol and invariance tests' envs, whose physics
  # compilation this reuses.
  path = analysis.episode_video(run_dir, str(tmp_path), looks=28, quality="fastest",
                                workers=1, scale=2)
  assert os.path.basename(path) in ("episode.mp4", "episode.gif")
  frames = imageio.mimread(path) if path.endswith(".gif") else list(imageio.get_reader(path))
  # One frame per agent step (10 per episode at action repeat 100); 28 16 px looks
  # side by side, doubled.
  assert len(frames) == 10
  assert np.asarray(frames[0]).shape[:2] == (32, 28 * 32)


class FakeBlocks:
  """Stands in for `Protocol`'s runner: block i's episodes all return `value(i)`; no
  env is built or stepped (the bookkeeping is under test, not the episodes)."""

  def __init__(self, value=lambda i: 0.0, stop_at=None):
    self.value, self.stop_at, self.calls = value, stop_at, []

  def __call__(self, params, key):  # set on the class: called unbound
    fake = self

    class Ctx:
      def __enter__(self):
        def run_block(inputs):
          if len(fake.calls) == fake.stop_at:
            raise KeyboardInterrupt  # the machine taken back mid-evaluation
          fake.calls.append(1)
          return np.full(len(inputs["seeds"]), fake.value(len(fake.calls) - 1))
        return run_block

      def __exit__(self, *exc):
        return False
    return Ctx()


def test_eval_json_is_valid_json_when_e_g_is_undefined(run_dir, tmp_path, monkeypatch):
  # A train return of 0 leaves E_G undefined (NaN); eval.json held a literal NaN.
  monkeypatch.setattr(protocol.Protocol, "_pool_runner", FakeBlocks())
  summary = ev.evaluate(run_dir, ev.EvalConfig(**{**TINY.__dict__, "conditions": ("none",)}),
                        out_dir=str(tmp_path), agents=[0], progress=False)
  assert np.isnan(summary["agents"][0]["conditions"]["none"]["e_g"])
  with open(tmp_path / "eval.json") as f:
    saved = json.loads(f.read(), parse_constant=lambda c: pytest.fail(f"invalid JSON: {c}"))
  assert saved["agents"][0]["conditions"]["none"]["e_g"] is None
  assert saved["mean"]["e_g"]["none"] is None


def test_an_interrupted_evaluation_runs_only_the_missing_blocks_when_called_again(
    run_dir, tmp_path, monkeypatch):
  # Block i returns i in every episode, so the results show which block made them.
  # Three conditions of 2 × 2 episodes for each of 2 agents, 8 envs a block: one
  # condition a block.
  fake = FakeBlocks(value=float)
  monkeypatch.setattr(protocol.Protocol, "_pool_runner", fake)
  calls = fake.calls
  cfg = ev.EvalConfig(**{**TINY.__dict__, "conditions": ("none", "light", "all"),
                         "max_envs": 8})
  whole = ev.evaluate(run_dir, cfg, out_dir=str(tmp_path / "whole"), progress=False)
  assert [whole["agents"][0]["conditions"][c]["mean"] for c in cfg.conditions] == [0, 1, 2]

  calls.clear()
  fake.stop_at = 2
  with pytest.raises(KeyboardInterrupt):
    ev.evaluate(run_dir, cfg, out_dir=str(tmp_path / "cut"), progress=False)
  assert os.path.exists(tmp_path / "cut" / ev.PROGRESS_FILE)
  assert not os.path.exists(tmp_path / "cut" / "eval.json")
  fake.stop_at = None
  resumed = ev.evaluate(run_dir, cfg, out_dir=str(tmp_path / "cut"), progress=False)
  assert len(calls) == 3  # two blocks before the cut, only the last after it
  for a, b in zip(whole["agents"], resumed["agents"]):
    assert a["train"]["episodes"] == b["train"]["episodes"]
    for c in cfg.conditions:
      assert a["conditions"][c]["episodes"] == b["conditions"][c]["episodes"]
  assert not os.path.exists(tmp_path / "cut" / ev.PROGRESS_FILE)

  # Progress kept for another protocol (here other held-out looks) is not used.
  calls.clear()
  fake.stop_at = 1
  with pytest.raises(KeyboardInterrupt):
    ev.evaluate(run_dir, cfg, out_dir=str(tmp_path / "other"), progress=False)
  fake.stop_at = None
  other = ev.evaluate(run_dir, dataclasses.replace(cfg, seed=1), out_dir=str(tmp_path / "other"),
                      progress=False)
  assert len(calls) == 1 + 3 and other["agents"][0]["conditions"]["none"]["mean"] == 1.0


def _summary(augs, seeds=(0, 1), task="cartpole-balance"):
  """A synthetic `evaluate` summary: agent returns 100·(agent + 1) − 10·condition."""
  from dmcr_jax.train import paper_results
  conditions = list(ev.conditions_for(task))
  agents = []
  for a, (aug, seed) in enumerate((aug, seed) for aug in augs for seed in seeds):
    train = 100.0 * (a + 1)
    cells = {c: dict(mean=train - 10 * k, e_g=ev.generalization_error(train, train - 10 * k))
             for k, c in enumerate(conditions)}
    agents.append(dict(agent=a, seed=seed, aug=aug, algo="sac_aug",
                       method=paper_results.method_name("sac_aug", aug),
                       train=dict(mean=train), conditions=cells))
  summary = dict(run_dir="runs/x", task=task, checkpoint_step=7, conditions=conditions,
                 config=dataclasses.asdict(TINY), train_look="0", agents=agents, wall_s=1.0)
  summary["mean"] = report.mean_row(agents, conditions)
  summary["augs"] = report.aug_groups(summary)
  return summary


def test_agents_of_different_training_look_ranges_are_not_averaged_together(tmp_path):
  # A few-shot run (one agent per range and seed): the summary's groups, the tables'
  # mean rows and the chart keep each range apart; the paper's row appears once.
  summary = _summary(("drq",))
  for r, look in zip(summary["agents"], ("levels:1", "levels:10")):
    r["train_look"] = look
  groups = report.aug_groups(summary)
  assert [g["label"] for g in groups] == ["drq, levels:1", "drq, levels:10"]
  assert [g["agents"] for g in groups] == [[0], [1]]
  assert groups[1]["train"] == pytest.approx(200.0)
  summary["augs"] = groups
  table = report.markdown(summary)
  assert "**mean**" not in table and table.count("| paper, SAC+AUG |") == 2  # both tables
  e_g_rows = table.split("| augmentation | train |")[1].strip().splitlines()[2:]
  assert [r.split(" | ")[0] for r in e_g_rows] == [
      "| drq, levels:1", "| drq, levels:10", "| paper, SAC+AUG"]
  report.plot(summary, str(tmp_path / "eval.png"))
  assert os.path.getsize(tmp_path / "eval.png") > 0


def test_several_augmentations_are_compared_side_by_side_with_the_papers_rows(tmp_path):
  mine = "examples.augmentations:hue_rotation+drq"
  summary = _summary(("drq", "cj+drq", mine))
  groups = summary["augs"]
  assert [g["label"] for g in groups] == ["drq", "cj+drq", mine]
  assert [g["agents"] for g in groups] == [[0, 1], [2, 3], [4, 5]]
  # Means over each augmentation's seeds; E_G of those means.
  assert groups[1]["train"] == pytest.approx(350.0)
  assert groups[1]["conditions"]["all"] == pytest.approx(350.0 - 60)
  assert groups[1]["e_g"]["all"] == pytest.approx(60 / 350)
  # The paper's rows where it has the method: Table 4, "None" as its train return.
  assert groups[0]["method"] == "SAC+AUG" and groups[2]["paper"] is None
  paper = groups[1]["paper"]
  assert paper["returns"]["all"] == 358.6
  assert paper["e_g"]["all"] == pytest.approx((984.2 - 358.6) / 984.2)

  table = report.markdown(summary)
  assert table.count("| seed ") == 6 and "**mean**" not in table
  for g in groups:
    assert f"| **{g['label']}** (mean of 2) | {g['train']:.1f} |" in table
  assert "| paper, SAC+AUG | 987.4 | 987.4 |" in table
  assert "| paper, SAC+CJ+AUG | 984.2 | 984.2 |" in table
  e_g_head = "| augmentation | train | " + " | ".join(summary["conditions"]) + " |"
  e_g_rows = table.split(e_g_head)[1].strip().splitlines()[1:]
  assert [r.split(" | ")[0] for r in e_g_rows] == [
      "| drq", "| cj+drq", f"| {mine}", "| paper, SAC+AUG", "| paper, SAC+CJ+AUG"]
  assert e_g_rows[1].endswith(f"| {100 * 60 / 350:.1f} % |")
  report.plot(summary, str(tmp_path / "eval.png"))
  assert os.path.getsize(tmp_path / "eval.png") > 0
  # One augmentation: the mean row, and the paper row only for its method.
  single = report.markdown(_summary(("drq",)))
  assert "**mean**" in single and "SAC+CJ+AUG" not in single and "paper, SAC+AUG" in single
  # One seed per augmentation: the agent rows are the means; no mean over augmentations.
  one_seed = report.markdown(_summary(("drq", "cj+drq"), seeds=(0,)))
  assert "**" not in one_seed.split("Paper rows")[0]


def test_exported_agents_carry_how_they_trained_to_the_evaluation(run_dir, tmp_path):
  from dmcr_jax.benchmarks import export_params
  with open(os.path.join(run_dir, "config.json")) as f:
    config = f.read()
  summary = dict(num_envs=2, wall_s=5.0, train_wall_s=12.0,
                 segments=[dict(start=0, steps=2, wall_s=7.0, device="dev A"),
                           dict(start=2, steps=3, wall_s=5.0, device="dev B")])
  source = tmp_path / "source"
  source.mkdir()
  with open(source / "config.json", "w") as f:
    f.write(config)
  with open(source / "summary.json", "w") as f:
    json.dump(summary, f)
  ev_dir = str(tmp_path / "imported")
  # The fixture's checkpoint, exported beside the summary, then imported elsewhere.
  assert export_params.export(run_dir, str(tmp_path / "files")) == 2
  assert not os.path.exists(tmp_path / "files" / "summary.json")  # the fixture has none
  with open(tmp_path / "files" / "summary.json", "w") as f:
    json.dump(summary, f)
  assert export_params.import_run(str(tmp_path / "files"), ev_dir) == 2
  assert ev.training_record(ev_dir) == dict(wall_s=12.0, devices=["dev A", "dev B"],
                                            num_envs=2)
  # The imported policies are the exported ones.
  _, want, _ = loop.load_run(run_dir)
  _, got, step = loop.load_run(ev_dir)
  assert step == 3
  for name in ("encoder", "actor"):
    jax.tree.map(np.testing.assert_array_equal, got.params[name], want.params[name])
  assert ev.training_record(str(source)) == ev.training_record(ev_dir)
  assert ev.training_record(str(tmp_path)) is None


def test_an_export_cut_short_leaves_no_config_so_it_is_not_taken_for_done(run_dir, tmp_path,
                                                                           monkeypatch):
  from dmcr_jax.benchmarks import export_params
  real, calls = export_params.flax.serialization.to_bytes, []
  def dies_on_the_second_agent(tree):
    calls.append(1)
    if len(calls) == 2:
      raise KeyboardInterrupt  # the machine taken back mid-export
    return real(tree)
  monkeypatch.setattr(export_params.flax.serialization, "to_bytes", dies_on_the_second_agent)
  dest = tmp_path / "files"
  with pytest.raises(KeyboardInterrupt):
    export_params.export(run_dir, str(dest))
  # paper_runs.sh takes agents/config.json for a finished export.
  assert sorted(os.listdir(dest)) == ["agent0.msgpack"]
