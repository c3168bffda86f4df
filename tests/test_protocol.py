"""`dmcr_jax.protocol`: the paper's protocol for any policy.

Its returns equal those of `dmcr_jax.make`'s env stepped episode by episode from the
host (the path `dmcr-evaluate` took before), for the ray caster and the pool; a pass
is deterministic and compiles once; K agents in one pass equal K single passes; bad
policies and options are refused before anything compiles, bad actions after the pass.

Tiny sizes: cartpole-balance at action repeat 100 (10 agent steps an episode), 16 px
frames, 2 held-out looks × 2 initial states; the ray caster's passes and the env they
are checked against draw without shadows and reflections (`RAY`: smaller programs,
the same looks). The test policy reads four pixels of its
own observation with elementwise arithmetic (no matrix product, whose rounding on a
CPU depends on the batch size), so returns can be compared exactly across batch
layouts.
"""

import contextlib
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dmcr_jax
from dmcr_jax import protocol as P
from dmcr_jax import protocol_pool, protocol_report
from tests.host_episodes import host_episode_returns

# One worker runs the module, so that its module fixtures (each a compiled pass) are
# built once and not in each xdist worker that gets one of their tests.
pytestmark = pytest.mark.xdist_group("protocol")

TASK = "cartpole-balance"
OPTS = dict(visual_seeds=2, dynamics_seeds=2, train_episodes=3,
            conditions=("none", "floor", "all"), train_look=5, image_size=16,
            action_repeat=100, seed=0)
RAY = dict(shadows=False, reflection=False)
"""The ray caster's options of the passes and the host-stepped env they are checked against."""
MOVING = ("moving-camera@0.5", "moving-all@0.3", "moving-camera@0")
"""Moving conditions the one-agent pass (`single`) also holds, for test_protocol_moving
(same group): a factor moving alone, every factor moving, a factor at intensity 0."""


def pixel_policy(params, obs, key):
  """tanh of a weighted sum of four pixels (+ optional key noise), scaled and shifted:
  scale 1 and shift 0 keep actions in [−1, 1]; the tests break them on purpose."""
  x = obs.astype(jnp.float32) / 255.0
  w = params["w"]
  z = (params["b"] + w[0] * x[:, 2, 3, 0] + w[1] * x[:, 8, 8, 4] + w[2] * x[:, 12, 5, 8]
       + w[3] * x[:, 5, 12, 7])
  z = z + params["noise"] * jax.random.normal(key, z.shape)
  return params["scale"] * jnp.tanh(z)[:, None] + params["shift"]


def make_params(seed=0, noise=0.0, scale=1.0, shift=0.0):
  w = jax.random.normal(jax.random.key(seed), (4,)) * 4.0
  f = lambda v: jnp.float32(v)
  return dict(w=w, b=f(-0.5), noise=f(noise), scale=f(scale), shift=f(shift))


def old_path(params, renderer="jax", copies=1, **render):
  """The protocol as `dmcr-evaluate` ran it: one `dmcr_jax.make` env, a condition at a
  time (`set_visuals`), a host round trip and a NumPy action every step. With
  `copies` > 1 the env holds that many copies of the episodes side by side (an env of
  another size); each copy's returns are the same, and the first copy's are returned."""
  per_env = np.repeat(P.held_out_seeds(OPTS["visual_seeds"], OPTS["seed"]),
                      OPTS["dynamics_seeds"])
  n = per_env.size
  resets = P.reset_seeds(n, OPTS["seed"])
  policy = jax.jit(lambda obs: pixel_policy(params, obs, jax.random.key(0)))
  tile = lambda x: np.tile(x, copies)
  env = dmcr_jax.make(TASK, num_envs=n * copies, visual_seeds=tile(per_env), vary="none",
                      frame_skip=OPTS["action_repeat"], image_size=OPTS["image_size"],
                      seed=OPTS["seed"], renderer=renderer, **render)

  def run_episodes():
    returns = host_episode_returns(env, policy, tile(resets)).reshape(copies, n)
    for again in returns[1:]:
      np.testing.assert_allclose(again, returns[0], rtol=1e-6)
    return returns[0]

  out = {}
  with env:
    for c in OPTS["conditions"]:
      env.set_visuals(tile(per_env), vary=c)
      out[c] = run_episodes()
    env.set_visuals(tile(P.train_look_seeds(OPTS["train_look"], n, OPTS["seed"])), vary="all")
    out["train"] = run_episodes()[:OPTS["train_episodes"]]
  return out


def prepare_single():
  """The planned protocol of one agent: `OPTS`' conditions and the `MOVING` ones in one
  block program, which test_protocol_moving's pass (same group and worker) reuses."""
  return P.prepare(TASK, pixel_policy, **RAY,
                   **{**OPTS, "conditions": OPTS["conditions"] + MOVING})


@pytest.fixture(scope="module")
def single():
  """The planned protocol of one agent and its pass with `make_params()`."""
  proto = prepare_single()
  return proto, proto(make_params())


def test_the_plan_gives_every_condition_the_same_initial_states_and_keys():
  plan = P.prepare(TASK, pixel_policy, agents=2, **{**OPTS, "train_look": [0, 5]}).plan
  names = [s.name for s in plan.segments]
  assert names == ["none", "floor", "all", "train"]
  n, t = 4, 3
  np.testing.assert_array_equal(plan.reset_seed, np.concatenate([P.reset_seeds(n, 0)] * 3
                                                               + [P.reset_seeds(n, 0)[:t]]))
  np.testing.assert_array_equal(plan.index, np.concatenate([np.arange(n)] * 3 + [np.arange(t)]))
  test = np.repeat(P.held_out_seeds(2, 0), 2)
  for k in range(2):
    np.testing.assert_array_equal(plan.visual_seed[k, :3 * n], np.tile(test, 3))
  # Agent 0 trained on seed 0: its train episodes are "none"'s; agent 1's are at seed 5.
  assert plan.shares == (True, False)
  assert (plan.visual_seed[1, 3 * n:] == 5).all()
  from dmcr_jax.visuals.params import factor_mask
  for s in plan.segments:
    assert (plan.mask[:, s.start:s.start + s.size] == factor_mask("cartpole", s.vary)).all()
  # Only dm_control's look to train on, and "none" run: no train episodes of their own.
  shared = P.prepare(TASK, pixel_policy, **{**OPTS, "train_look": 0}).plan
  assert [s.name for s in shared.segments] == ["none", "floor", "all"]


def _no_compile(monkeypatch):
  def fail(*a, **k):
    raise AssertionError("compiled before the input was checked")
  monkeypatch.setattr(P, "_ray_block_jit", fail)


@pytest.mark.parametrize("policy, params, agents, match", [
    (lambda p, o, k: jnp.zeros((o.shape[0], 2)), make_params(), None,
     r"actions of shape \(batch, action_size\) = \(2, 1\).*got \(2, 2\)"),
    (lambda p, o, k: jnp.zeros((o.shape[0],)), make_params(), None,
     r"actions of shape \(batch, action_size\) = \(2, 1\).*got \(2,\)"),
    (lambda p, o, k: jnp.asarray(np.tanh(np.asarray(o, np.float32)[:, :1, 0, 0])), make_params(),
     None, r"policy must be a pure JAX function of \(params, obs, key\)"),
    (lambda p, o, k: jnp.ones((o.shape[0], 1)) * (1 if o.mean() > 0 else -1), make_params(),
     None, r"policy must be a pure JAX function of \(params, obs, key\)"),
    (lambda p, o, k: jnp.zeros((o.shape[0], 1), jnp.int32), make_params(), None,
     "float actions"),
    (lambda p, o, k: p["missing"], make_params(), None, r"failed when traced.*KeyError"),
    (pixel_policy, make_params(), 2, "leading axis of 2 agents"),
])
def test_bad_policies_are_refused_before_anything_compiles(policy, params, agents, match,
                                                           monkeypatch):
  _no_compile(monkeypatch)
  with pytest.raises(ValueError, match=match):
    P.evaluate(TASK, policy, params, agents=agents, **OPTS)


@pytest.mark.parametrize("options, match", [
    (dict(renderer="opengl"), "valid: pool, jax"),
    (dict(conditions=("fog",)), "valid: none, light"),
    (dict(train_episodes=5), "at most visual_seeds"),
    (dict(visual_seeds=0), "visual_seeds must be a positive int"),
    (dict(quality="fast"), "apply only to renderer='pool'"),
    (dict(renderer="pool", shadows=False), "apply only to renderer='jax'"),
    (dict(physics_workers=2), "apply only to renderer='pool'"),
    (dict(renderer="pool", physics_workers=-1), "physics_workers must be None, 0 or"),
    (dict(colour=1), "unknown option colour"),
    (dict(train_look=[0, 1]), "one per agent"),
    (dict(train_look=dmcr_jax.TEST_SEEDS), "lie in the training looks"),
    (dict(max_envs=0), "max_envs must be a positive int"),
    (dict(agents=0), "agents must be a positive int"),
])
def test_bad_options_are_refused_naming_the_valid_ones(options, match, monkeypatch):
  _no_compile(monkeypatch)
  with pytest.raises((ValueError, RuntimeError), match=match):
    P.evaluate(TASK, pixel_policy, make_params(), **{**OPTS, **options})


@pytest.mark.slow
def test_returns_equal_the_host_stepped_env(single):
  _, result = single
  want = old_path(make_params(), **RAY)
  np.testing.assert_allclose(result.train[0], want["train"], rtol=1e-6)
  for c in OPTS["conditions"]:
    np.testing.assert_allclose(result.returns[c][0], want[c], rtol=1e-6)
  # The looks matter: the conditions' returns are not all the same.
  assert len({float(result.mean(c)[0]) for c in OPTS["conditions"]}) > 1
  for c in OPTS["conditions"]:
    assert result.e_g(c)[0] == pytest.approx(
        (result.train_mean[0] - result.mean(c)[0]) / result.train_mean[0])


@pytest.mark.slow
def test_a_pass_is_deterministic_and_new_params_compile_nothing(single):
  proto, first = single
  compiled = P._ray_block_jit()._cache_size()
  noisy = make_params(seed=3, noise=0.5)
  a, b = proto(noisy), proto(noisy)
  assert P._ray_block_jit()._cache_size() == compiled
  for c in OPTS["conditions"]:
    np.testing.assert_array_equal(a.returns[c], b.returns[c])
    assert not np.array_equal(a.returns[c], first.returns[c])
  np.testing.assert_array_equal(a.train, b.train)


@pytest.mark.slow
def test_actions_out_of_range_or_nan_stop_the_pass_with_a_clear_message(single):
  proto, _ = single  # same program: params only
  with pytest.raises(ValueError, match=r"actions outside \[-1, 1\] \(agents \[0\], largest "
                                       r"\|action\| 3"):
    proto(make_params(scale=3.0))
  with pytest.raises(ValueError, match=r"NaN actions \(agents \[0\]\).*not clipped"):
    proto(make_params(shift=float("nan")))


@pytest.fixture(scope="module")
def two_agents():
  """Two agents' params and their pass as one, its renders in padded chunks of 4 envs
  (30 envs a block: 2 pad); one compilation serves the K-agent and the padding test."""
  params = [make_params(seed=s, noise=0.3) for s in (1, 2)]
  stacked = jax.tree.map(lambda *x: jnp.stack(x), *params)
  proto = P.prepare(TASK, pixel_policy, agents=2, render_chunk=4, **RAY, **OPTS)
  return params, proto, proto(stacked)


@pytest.mark.slow
def test_k_agents_in_one_pass_equal_k_single_passes(single, two_agents):
  proto, _ = single
  params, _, both = two_agents
  assert both.train.shape == (2, 3) and both.returns["all"].shape == (2, 4)
  for k, p in enumerate(params):
    one = proto(p)
    np.testing.assert_array_equal(both.train[k], one.train[0])
    for c in OPTS["conditions"]:
      np.testing.assert_array_equal(both.returns[c][k], one.returns[c][0])


def test_a_block_renders_in_chunks_of_one_size():
  # The fewest chunks of at most RENDER_CHUNK envs, one size; a block that does not
  # fill its last chunk is padded (lax.map would compile a second render for it).
  from dmcr_jax import jax_env
  assert jax_env.RENDER_CHUNK == 256
  assert P.render_chunk(256) is None and P.render_chunk(2400) == 240
  assert P.render_chunk(257) == 129 and P.render_chunk(9600) == 253
  penv = lambda n, chunk, kernel=False: P._pixel_env(TASK, n, 100, 3, 16, 16, ()).replace(
      render_chunk=chunk, render_kernel=kernel)
  assert P.render_padding(penv(9600, 253)) == 14 and P.render_padding(penv(2400, 240)) == 0
  assert P.render_padding(penv(15, 4)) == 1 and P.render_padding(penv(15, None)) == 0
  assert P.render_padding(penv(15, 4, kernel=True)) == 0


@pytest.mark.slow
def test_padded_render_chunks_give_the_same_returns(single, two_agents):
  # The two agents' block rendered in padded chunks against each agent's own pass
  # rendered in one chunk.
  proto, _ = single
  params, padded, got = two_agents
  assert P.render_padding(padded.pixel_env()) == 2 and P.render_padding(proto.pixel_env()) == 0
  for k, p in enumerate(params):
    want = proto(p)
    np.testing.assert_array_equal(got.train[k], want.train[0])
    for c in OPTS["conditions"]:
      np.testing.assert_array_equal(got.returns[c][k], want.returns[c][0])


@pytest.mark.slow
def test_the_pool_runs_every_condition_in_one_batch_with_the_same_returns(monkeypatch):
  # The pool env of every condition's looks (a vary per env) against the pool env
  # swept one condition at a time; inside `with`, the passes share one opening of the
  # pool's envs and workers, a failed pass drops it (the next opens new ones), and the
  # block's end closes it. The swept env holds two copies of the episodes: 8 envs, the
  # size of the pass's pool envs (15 episodes in two pipelined groups), whose physics
  # compilation it shares.
  render = dict(quality="fastest", workers=1)
  opened, closed = [], []

  @contextlib.contextmanager
  def counted(proto):
    with real(proto) as penvs:
      opened.append(penvs)
      yield penvs
    closed.append(penvs)
  real = P.pool_envs
  monkeypatch.setattr(P, "pool_envs", counted)
  want = old_path(make_params(), renderer="pool", copies=2, **render)
  with P.prepare(TASK, pixel_policy, renderer="pool", **render, **OPTS) as proto:
    got = proto(make_params())
    again = proto(make_params())
    assert len(opened) == 1 and not closed
    with pytest.raises(ValueError, match="outside"):
      proto(make_params(shift=2.0))
    assert closed == opened
    third = proto(make_params())
    assert len(opened) == 2
  assert closed == opened
  for r in (got, again, third):
    np.testing.assert_allclose(r.train[0], want["train"], rtol=1e-6)
    for c in OPTS["conditions"]:
      np.testing.assert_allclose(r.returns[c][0], want[c], rtol=1e-6)
  assert "render quality fastest" in got.markdown()
  # (A pass outside `with` opens and closes its own: test_protocol_moving's pool pass.)


def test_the_pool_pass_leaves_software_gl_every_core_and_else_steps_the_physics_on_them():
  from dmcr_jax.protocol_pool import POOL_RENDER_WORKERS, pass_workers
  from dmcr_jax.visuals.render_pool import default_workers
  assert pass_workers(2, 16, software_gl=True) == (default_workers(), 0)
  # An accelerator draws: a few render workers, the other cores (one kept) step the
  # physics, an equal share per pool env, at most 4 (none: in this process).
  assert pass_workers(2, 16, software_gl=False) == (POOL_RENDER_WORKERS, 4)
  assert pass_workers(2, 12, software_gl=False) == (POOL_RENDER_WORKERS, 3)
  assert pass_workers(8, 16, software_gl=False) == (POOL_RENDER_WORKERS, 1)
  assert pass_workers(19, 16, software_gl=False) == (POOL_RENDER_WORKERS, 0)
  assert pass_workers(1, 2, software_gl=False) == (2, 0)
  assert pass_workers(2, 16, False, workers=8, physics_workers=1) == (8, 1)   # kept
  # A pass's own options reach its pool envs (the pass makes them with these).
  proto = P.prepare(TASK, pixel_policy, renderer="pool", workers=1, physics_workers=3, **OPTS)
  assert protocol_pool.workers_for(proto) == (1, 3)
  assert "physics_workers" not in proto.config     # the returns do not depend on it


def test_pool_groups_split_each_agent_s_episodes_into_pipelined_halves():
  # K = 2 agents × B = 5 episodes, agent-major: two groups of 3 episodes per agent,
  # the second padded with its first episode; every real env in exactly one group.
  groups = P.pool_groups(2, 5)
  assert [rows.tolist() for rows, _ in groups] == [[0, 1, 2, 5, 6, 7], [3, 4, 3, 8, 9, 8]]
  assert [real.tolist() for _, real in groups] == [[True] * 6, [True, True, False] * 2]
  real_rows = np.concatenate([rows[real] for rows, real in groups])
  assert sorted(real_rows.tolist()) == list(range(10))
  assert [r.tolist() for r, _ in P.pool_groups(3, 1)] == [[0, 1, 2]]  # one episode each


def test_progress_into_a_redirected_stderr_is_lines_not_a_bar(single, capsys):
  # tqdm wrote its redraws into a redirected stderr (a log file); without a
  # terminal, progress=True prints a line per block.
  proto, _ = single
  assert not sys.stderr.isatty()
  proto(make_params(), progress=True)
  err = capsys.readouterr().err
  assert "\r" not in err and "block/s" not in err and "it/s" not in err
  assert [line.split(",")[0] for line in err.splitlines()
          if line.startswith("evaluate:")] == ["evaluate: block 1/1 done"]


def _results(train, returns):
  conditions = tuple(returns)
  return P.Results(
      task=TASK, conditions=conditions, train=np.asarray(train, np.float64),
      returns={c: np.asarray(v, np.float64) for c, v in returns.items()},
      test_visual_seeds=np.array([2**30 + 1, 2**30 + 2]), train_looks=("seed 0", "seed 0"),
      config=dict(visual_seeds=2, dynamics_seeds=1, train_episodes=2, renderer="jax"),
      labels=("mine", "theirs"), device="cpu", wall_s=1.5, compile_s=1.0, agent_steps=40)


def test_the_report_files_hold_the_returns_and_e_g(tmp_path):
  r = _results([[100, 300], [0, 0]], {"none": [[200, 200], [5, 5]], "all": [[50, 150], [1, 1]]})
  np.testing.assert_allclose(r.train_mean, [200, 0])
  np.testing.assert_allclose(r.e_g("all"), [0.5, np.nan])
  summary = r.write(str(tmp_path))
  assert sorted(os.listdir(tmp_path)) == ["eval.json", "eval.md", "eval.png"]
  saved = json.loads((tmp_path / "eval.json").read_text(),
                     parse_constant=lambda c: pytest.fail(f"invalid JSON: {c}"))
  assert saved == json.loads(r.to_json())
  mine, theirs = saved["agents"]
  assert mine["label"] == "mine" and mine["conditions"]["all"]["e_g"] == 0.5
  assert mine["conditions"]["none"]["episodes"] == [200, 200]
  assert theirs["conditions"]["all"]["e_g"] is None  # train 0: E_G undefined
  assert saved["mean"]["train"] == 100
  table = (tmp_path / "eval.md").read_text()
  assert table == r.markdown() == protocol_report.markdown(summary)
  assert "| agent | train | none | all | E_G (all) |" in table
  assert "| mine | 200.0 | 200.0 | 100.0 | 50.0 % |" in table
  assert "| theirs | 0.0 | 5.0 | 1.0 | – |" in table
  assert "| policy | train | none | all |" in table
  assert os.path.getsize(tmp_path / "eval.png") > 0


@pytest.mark.slow
def test_the_worked_example_evaluates_a_scripted_policy_reproducibly(tmp_path):
  from examples import evaluate_own_policy
  argv = ["--tiny", "--policy", "random", "--out", str(tmp_path / "a")]
  first = evaluate_own_policy.main(argv)
  again = evaluate_own_policy.main(argv[:-1] + [str(tmp_path / "b")])
  # Random actions from the protocol's keys: the same in every pass.
  np.testing.assert_array_equal(first.returns["all"], again.returns["all"])
  saved = json.loads((tmp_path / "a" / "eval.json").read_text())
  assert saved["agents"][0]["conditions"]["all"]["episodes"] == first.returns["all"][0].tolist()


@pytest.mark.slow
def test_the_benchmark_rows_put_the_protocol_beside_the_env(tmp_path, capsys, monkeypatch):
  from dmcr_jax.benchmarks import evaluate as bench
  from dmcr_jax.benchmarks import rows as R
  out = str(tmp_path / "evaluate.jsonl")
  # K = 2 only: the one-agent pass is the same code with agents=1 (and costs another
  # two compilations, the protocol's and the baseline's of its batch). The baseline's
  # own scan is the env's `reset` and `step` (test_jax_env checks those); here only its
  # place beside the protocol's row, so it is a stand-in of known throughput.
  calls = []

  def baseline(task, n, steps, frame_skip, frame_stack, size):
    calls.append((task, n, steps, frame_skip, frame_stack, size))
    return dict(trace_s=0.0, xla_compile_s=0.0, compile_s=1.0, run_s=2.0,
                agent_steps_per_s=n * steps / 2.0)
  monkeypatch.setattr(bench, "env_baseline", baseline)
  sizes = ["--task", TASK, "--agents", "2", "--visual-seeds", "2", "--dynamics-seeds", "1",
           "--train-episodes", "2", "--conditions", "none,all", "--image-size", "16",
           "--action-repeat", "100", "--out", out]
  bench.main(sizes)
  rows = R.read(out)
  assert [r["variant"] for r in rows] == ["JAX env (zero actions)", "protocol K=2"]
  assert calls == [(TASK, 8, 10, 100, 3, 16)]    # the protocol's block, episode and sizes
  for base, r in zip(rows[::2], rows[1::2]):
    assert base["is_baseline"] and base["n"] == r["n"] == r["block_envs"]
    assert r["blocks"] == 1 and r["block_envs"] == 4 * r["agents"]  # 2 conditions × 2 looks
    assert r["agent_steps"] == r["block_envs"] * r["blocks"] * r["episode_length"] == r["n"] * 10
    assert r["throughput"] == pytest.approx(r["agent_steps"] / r["run_s"])
    assert r["baseline_throughput"] == base["throughput"]
    assert r["ratio"] == pytest.approx(r["throughput"] / base["throughput"])
  assert "| cartpole-balance | jax | protocol K=2 |" in (tmp_path / "evaluate.md").read_text()
  # One pass (the programs above serve it): the row's time is that pass's.
  bench.main(sizes + ["--passes", "1", "--no-baseline"])
  once = R.read(out)[-1]
  assert once["passes"] == 1 and once["run_s"] == once["first_pass_s"]
  assert once["throughput"] == pytest.approx(once["agent_steps"] / once["first_pass_s"])
  assert once["compile_s"] is None and 0 < once["first_block_s"] <= once["first_pass_s"]


def test_equal_batch_gives_each_of_k_agents_a_kth_of_the_looks(capsys):
  import types
  from dmcr_jax.benchmarks import evaluate as bench
  args = types.SimpleNamespace(equal_batch=True, visual_seeds=100, dynamics_seeds=3,
                               train_episodes=100)
  assert bench.sizes_for(1, args) == (100, 100)
  assert bench.sizes_for(4, args) == (25, 75)    # 4 × 25 looks × 3: the envs of one agent
  apart = types.SimpleNamespace(**dict(vars(args), equal_batch=False))
  assert bench.sizes_for(4, apart) == (100, 100)
  with pytest.raises(SystemExit):                # refused before anything is built
    bench.main(["--agents", "1,3", "--equal-batch"])
  assert "--visual-seeds (100) must divide by every K in --agents (1,3)" in capsys.readouterr().err
