"""Few-shot training across visual seeds: `dmcr-train --visual-seeds levels:1,10,…` trains
one agent per training-look range, each agent's envs drawing their looks from its own
range (both renderers), a seed's look is the same in every range, bad specs are refused
before anything is built, and `evaluate` draws the generalisation curve.

Tiny sizes: pendulum / cartpole at action repeat 100 (10 agent steps per episode),
16 px frames, 1 or 2 envs per agent.
"""

import csv
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dmcr_jax
from dmcr_jax import jax_env, protocol
from dmcr_jax.visuals.levels import TEST_SEEDS, TRAIN_SEEDS, EnvRanges, levels
from dmcr_jax.train import evaluate as ev
from dmcr_jax.train import loop, sac
from dmcr_jax.train.__main__ import parse

# One worker runs the module, so its module-scoped training run is made once; with
# test_evaluate (group "train"), whose protocol env and policy its evaluation shares
# (cartpole, two agents of four envs each, the same networks), and test_train, whose
# interrupted run trains learners of the training run's sizes (two agents of one env).
pytestmark = pytest.mark.xdist_group("train")

TINY = sac.SACConfig(batch_size=8, conv_channels=4, feature_dim=8, hidden_dim=16)
SMALL = dict(action_repeat=100, image_size=16, num_envs=2, quality="fastest", workers=1,
             buffer_capacity=200, warmup_steps=5, log_every=5, sac=TINY)
EPISODE = 10


@pytest.mark.parametrize("spec, why", [
    ("levels:0", "levels:0 holds no seed"),
    ("levels:1,0", "levels:0 holds no seed"),
    (f"levels:{2**30 + 1}", "reaches past the training range"),
    ("levels:10,2147483647", "into the held-out test range"),
    ("7,levels:10", "a fixed seed cannot be mixed with levels"),
    ("levels:10,levels:100", "give levels: once"),
    ("levels:10,10", "a count appears twice"),
    ("levels:all,1073741824", "a count appears twice"),
    ("levels:1.5", "'1.5' is not an integer count"),
    ("levels:ten", "'ten' is not an integer count"),
    ("levels:", "'' is not an integer count"),
])
def test_bad_level_specs_are_refused_naming_the_valid_form(spec, why, capsys, monkeypatch):
  built = []
  monkeypatch.setattr(dmcr_jax, "make", lambda *a, **k: built.append(1))
  with pytest.raises(SystemExit):
    parse(["--visual-seeds", spec, "--renderer", "jax"])
  err = capsys.readouterr().err
  assert why in err and "valid: an int in [0, 2**31 - 1]" in err
  assert "'levels:<n>[,<n>...]'" in err and "levels:1 = seed 0 only" in err
  assert not built


def test_levels_multiply_with_augmentations_and_seeds():
  cfg, _ = parse(["--visual-seeds", "levels:1, 10,all", "--aug", "drq,cj+drq",
                  "--seeds", "0,1"])
  assert len(cfg.agents()) == 3 * 2 * 2
  assert cfg.agents()[:4] == [(0, "drq"), (1, "drq"), (0, "cj+drq"), (1, "cj+drq")]
  assert cfg.agents()[4:8] == cfg.agents()[:4]              # same inits in every range
  looks = cfg.agent_looks()
  assert looks == [levels(1)] * 4 + [levels(10)] * 4 + [TRAIN_SEEDS] * 4
  assert [loop.look_label(x) for x in looks[::4]] == ["levels:1", "levels:10", "levels:all"]
  assert not any(x.overlaps(TEST_SEEDS) for x in looks)
  # One range or a fixed seed: one look group, as before.
  assert loop.parse_visual_seeds("levels:5") == (levels(5),)
  assert loop.parse_visual_seeds(0) == (0,)


def _seed_history(env, steps: int, seed: int) -> np.ndarray:
  """Every env's visual seed at reset and after each of `steps` steps, (steps + 1, N)."""
  _, info = env.reset(seed=seed)
  out = [info["visual_seed"]]
  for _ in range(steps):
    *_, info = env.step(np.zeros((env.num_envs, env.task.action_size), np.float32))
    out.append(info["visual_seed"])
  return np.stack(out)


@pytest.mark.slow
def test_each_agents_envs_draw_only_from_its_range_deterministically():
  cfg = loop.TrainConfig(task="pendulum-swingup", visual_seeds="levels:1,3,all", **SMALL)
  steps = 4 * (EPISODE + 1)                                  # four episodes per env
  with loop.make_env(cfg) as env:
    seeds = _seed_history(env, steps, 11)
    again = _seed_history(env, steps, 11)
    other = _seed_history(env, steps, 12)
  np.testing.assert_array_equal(seeds, again)               # same command, same looks
  assert not np.array_equal(seeds, other)
  per_env = [r for r in cfg.agent_looks() for _ in range(cfg.num_envs)]
  assert EnvRanges(tuple(per_env)).contains_all(seeds)
  assert (seeds[:, :2] == 0).all()                           # levels:1: dm_control's look
  assert set(np.unique(seeds[:, 2:4])) == {0, 1, 2}          # levels:3 drew its whole range
  assert len(np.unique(seeds[:, 4:])) > 4                    # new looks at every reset
  assert not np.isin(seeds, np.arange(TEST_SEEDS.start, TEST_SEEDS.start + 1)).any()
  assert (seeds < TEST_SEEDS.start).all()                    # never a test look
  # The same env on the JAX renderer draws the same seeds (same keys).
  jcfg = loop.TrainConfig(**{**cfg.__dict__, "renderer": "jax", "quality": "exact",
                             "workers": None})
  with loop.make_env(jcfg) as env:
    np.testing.assert_array_equal(_seed_history(env, steps, 11), seeds)
    # ... and each env's look is the look of its current seed.
    want = jax_env.make_looks(env.functional.maker, jnp.asarray(seeds[-1]))
    for a, b in zip(jax.tree.leaves(env.pixel_state.look), jax.tree.leaves(want)):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow
def test_a_seeds_look_is_the_same_in_every_range_and_batch():
  task = dmcr_jax.load("pendulum-swingup")
  make = lambda seeds, n: jax_env.make_env(task, n, seeds, "all", 100, 3, 16, 16)
  small, large = make(levels(10), 2), make(EnvRanges((levels(1000), TRAIN_SEEDS)), 2)
  # Ranges are data (`SeedBounds`): one compilation of the env's jitted functions
  # serves both (same pytree structure and the same shapes).
  shapes = lambda env: [(x.shape, x.dtype) for x in jax.tree.leaves(env)]
  assert jax.tree.structure(small) == jax.tree.structure(large)
  assert shapes(small) == shapes(large)
  fixed = make(np.array([3, 7, 0], np.int32), 3)
  seeds = jnp.asarray([3, 7], jnp.int32)
  looks_of = jax.jit(lambda env, seeds: env.looks_of(seeds))   # as inside the env's step
  for got in (looks_of(large, seeds), jax.tree.map(lambda x: x[:2], fixed.looks)):
    for a, b in zip(jax.tree.leaves(looks_of(small, seeds)), jax.tree.leaves(got)):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  # A look does not depend on the batch it is made in; seed 0 is dm_control's default.
  alone = looks_of(small, jnp.asarray([7], jnp.int32))
  for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(looks_of(small, seeds))):
    np.testing.assert_array_equal(np.asarray(a)[0], np.asarray(b)[1])
  default = jax.tree.map(lambda x: x[2], fixed.looks)
  assert not np.array_equal(np.asarray(default.cam_pos), np.asarray(fixed.looks.cam_pos[0]))
  np.testing.assert_array_equal(np.asarray(default.floor), 0)


@pytest.fixture(scope="module")
def levels_run(tmp_path_factory):
  """A tiny `train` run (host driver, pool renderer) of two agents: levels:1 and
  levels:2, one env each (test_train's interrupted run's learner sizes)."""
  out = str(tmp_path_factory.mktemp("levels"))
  cfg = loop.TrainConfig(task="cartpole-balance", visual_seeds="levels:1,2", steps=22,
                         checkpoint_every=0, out_dir=out, **{**SMALL, "num_envs": 1})
  summary = loop.train(cfg, progress=False)
  return out, summary


@pytest.mark.slow
def test_training_logs_each_agents_range(levels_run):
  out, summary = levels_run
  assert summary["looks"] == ["levels:1", "levels:2"]
  with open(os.path.join(out, "log.csv")) as f:
    rows = list(csv.DictReader(f))
  assert {(r["agent"], r["looks"]) for r in rows} == {("0", "levels:1"), ("1", "levels:2")}
  assert set(summary["final_return"]) == {"seed 0, levels:1", "seed 0, levels:2"}


@pytest.mark.slow
def test_evaluate_draws_the_curve_against_training_looks(levels_run, tmp_path):
  import matplotlib.image
  out, _ = levels_run
  # 28 episodes an agent (3 conditions × 3 looks × 3 states, 1 train) in two pipelined
  # groups of 14: pool envs of 28 (2 agents × 14), the size of test_evaluate's envs,
  # whose physics compilation this shares.
  cfg = ev.EvalConfig(visual_seeds=3, dynamics_seeds=3, train_episodes=1,
                      conditions=("none", "floor", "all"), quality="fastest", workers=1)
  summary = ev.evaluate(out, cfg, out_dir=str(tmp_path), progress=False)
  agents = summary["agents"]
  assert [(r["train_look"], r["looks"]) for r in agents] == [("levels:1", 1), ("levels:2", 2)]
  # Every agent met the same held-out looks (and initial states).
  assert all(s in TEST_SEEDS for s in summary["test_visual_seeds"])
  with open(tmp_path / "few_shot.json") as f:
    curve = json.load(f)
  assert [r["looks"] for r in curve["rows"]] == [1, 2]
  for row, agent in zip(curve["rows"], agents):
    assert row["train"] == pytest.approx(agent["train"]["mean"])
    for c in cfg.conditions:
      assert row["conditions"][c] == pytest.approx(agent["conditions"][c]["mean"])
    assert row["e_g"]["all"] == pytest.approx(agent["conditions"]["all"]["e_g"], nan_ok=True)
  assert curve["zero_shot"] == {"SAC+AUG": pytest.approx(agents[0]["conditions"]["all"]["mean"])}
  table = (tmp_path / "few_shot.md").read_text()
  assert "| SAC+AUG | 2 (levels:2) | 1 |" in table
  assert f"{agents[1]['conditions']['floor']['mean']:.1f}" in table
  assert matplotlib.image.imread(str(tmp_path / "few_shot.png")).shape[1] == 1000
  # The run as two runs of one range each (eval.json as written), merged: the same curve.
  from dmcr_jax import protocol_report
  from tests.test_few_shot_merge import split_by_look
  with open(tmp_path / "eval.json") as f:
    parts = split_by_look(json.load(f))
  assert [len(p["agents"]) for p in parts] == [1, 1]
  merged = protocol_report.few_shot_rows(protocol_report.merge_summaries(parts))
  assert json.loads(json.dumps(protocol_report.json_safe(merged))) == curve["rows"]


def test_train_looks_of_an_agent_come_from_its_range():
  seeds = protocol.train_look_seeds(levels(2), 50, 0)
  assert set(seeds) == {0, 1}
  np.testing.assert_array_equal(seeds, protocol.train_look_seeds(levels(2), 50, 0))
  assert (protocol.train_look_seeds(5, 3, 0) == 5).all()
  assert protocol.is_default_look(levels(1)) and protocol.is_default_look(0)
  assert not protocol.is_default_look(levels(2))
