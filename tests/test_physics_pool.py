"""PhysicsPool: the workers' physics equals the in-process physics_env step, across
episode ends, seed kinds, slices, a killed worker and an external state."""

import os
import signal
import threading

import jax
import numpy as np
import pytest

import dmcr_jax
from dmcr_jax import env_base
from dmcr_jax import models, physics_env, physics_pool
from dmcr_jax.physics_pool import PhysicsPool, _Stepper
from dmcr_jax.visuals.levels import EnvRanges, SeedRange

# test_env's task and sizes (pendulum-swingup, frame skip 100: 10 agent steps per
# episode; 3 envs), in its xdist group: the in-process physics compiles once.
TASK, N, SKIP, EPISODE = "pendulum-swingup", 3, 100, 10
pytestmark = pytest.mark.xdist_group("env")


def in_process():
  """The env's own jitted (init, step) for N envs on the CPU."""
  return env_base._physics_fns(models.load(TASK), N, SKIP, False)


def plain(tree):
  """Leaves as NumPy (keys as key data), for comparison."""
  return [np.asarray(jax.random.key_data(x) if jax.dtypes.issubdtype(
      x.dtype, jax.dtypes.prng_key) else x) for x in jax.tree.leaves(tree)]


def assert_close(a, b):
  for x, y in zip(plain(a), plain(b), strict=True):
    if x.dtype.kind in "biu":
      np.testing.assert_array_equal(x, y)
    else:
      np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5)


def run_both(pool, seeds, steps, es_ref, es, seed=0):
  """Steps the pool and the in-process physics alike, with the seed source `seeds`
  (fixed seeds or ranges); returns both states."""
  _, step = in_process()
  rng = np.random.default_rng(seed)
  cpu = jax.devices("cpu")[0]
  seed_arg = physics_env.seed_argument(seeds, N)
  for _ in range(steps):
    a = rng.uniform(-1, 1, (N, models.load(TASK).action_size)).astype(np.float32)
    es_ref, r_ref, t_ref = step(es_ref, jax.device_put(a, cpu), jax.device_put(seed_arg, cpu))
    es, r, t = pool.step(es, a, seed_arg).result()
    np.testing.assert_allclose(r, r_ref, rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(t, t_ref)
  return es_ref, es


def init_both(pool, seeds, key_seed: int):
  """Both physics started with the seed source `seeds` (fixed seeds or ranges) from
  one key; (in-process, pool) states."""
  init, _ = in_process()
  key = jax.random.key(key_seed)
  seed_arg = physics_env.seed_argument(seeds, N)
  es_ref = init(key, jax.device_put(seed_arg, jax.devices("cpu")[0]))
  es = pool.init(key, seed_arg)
  assert_close(es, es_ref)
  return es_ref, es


@pytest.fixture(scope="module")
def pool():
  """Two physics workers for the N envs; every test's seeds, fixed or ranges, go
  through the same pool."""
  with PhysicsPool(models.load(TASK), N, SKIP, workers=2) as pool:
    yield pool


@pytest.mark.slow
def test_fixed_seeds_match_in_process_across_an_episode_end(pool):
  seeds = np.array([3, 7, 9], np.int32)
  es_ref, es = init_both(pool, seeds, 5)
  es_ref, es = run_both(pool, seeds, EPISODE + 2, es_ref, es)
  assert_close(es, es_ref)
  np.testing.assert_array_equal(es.episode, [1] * N)
  np.testing.assert_array_equal(es.visual_seed, seeds)


@pytest.mark.slow
def test_a_changed_state_is_loaded_into_the_workers(pool):
  seeds = np.zeros(N, np.int32)
  es_ref, es = init_both(pool, seeds, 6)
  moved = lambda e: e.replace(task=e.task.replace(
      data=e.task.data.replace(qvel=np.asarray(e.task.data.qvel) + 1.0)))
  es_ref, es = run_both(pool, seeds, 2, moved(es_ref), moved(es))
  assert_close(es, es_ref)


@pytest.mark.slow
def test_killed_worker_loses_no_state(pool):
  seeds = np.zeros(N, np.int32)
  es_ref, es = init_both(pool, seeds, 9)
  es_ref, es = run_both(pool, seeds, 2, es_ref, es)
  restarts = pool.restarts
  os.kill(pool.pids[1], signal.SIGKILL)
  es_ref, es = run_both(pool, seeds, 3, es_ref, es, seed=2)
  assert pool.restarts == restarts + 1
  assert_close(es, es_ref)


@pytest.mark.slow
def test_per_env_ranges_draw_as_in_process_in_every_slice(pool):
  ranges = EnvRanges((SeedRange(0, 10), SeedRange(20, 30), SeedRange(40, 50)))
  assert [b - a for a, b in pool._pool.slices(N)] == [2, 1]  # offsets matter
  es_ref, es = init_both(pool, ranges, 2)
  es_ref, es = run_both(pool, ranges, EPISODE + 1, es_ref, es)
  assert_close(es, es_ref)
  assert ranges.contains_all(es.visual_seed)
  np.testing.assert_array_equal(es.episode, [1] * N)
  # Another range, the same workers: drawn from it alone.
  other = SeedRange(100, 103)
  es_ref, es = init_both(pool, other, 3)
  es_ref, es = run_both(pool, other, EPISODE + 1, es_ref, es)
  assert_close(es, es_ref)
  assert other.contains_all(es.visual_seed)


@pytest.mark.slow
def test_a_worker_compiles_its_slice_as_it_starts_and_its_calls_reuse_it():
  # A worker compiles init and step in the background when it is built; the calls
  # then run the programs compiled there (no second compilation) and give the
  # in-process physics.
  task = models.load(TASK)
  stepper = _Stepper(TASK, task.solver_iterations, task.ls_iterations, SKIP, (N,), False)
  stepper._warming.join()
  assert (stepper._init._cache_size(), stepper._step._cache_size()) == (1, 1)
  seeds = np.array([3, 7, 9], np.int32)
  key = jax.random.key(5)
  init, step = in_process()
  cpu = jax.devices("cpu")[0]
  es_ref = init(key, jax.device_put(seeds, cpu))
  inputs = {"key": np.asarray(jax.random.key_data(jax.random.split(key, N))),
            "action": np.full((N, task.action_size), 0.5, np.float32),
            "seed": seeds, "start": np.zeros(N, np.int32), "stop": np.zeros(N, np.int32),
            "ranged": np.zeros(N, bool)}
  records = [np.zeros(N, stepper.record), np.zeros(N, stepper.record)]
  stepper(dict(inputs, init=np.ones(N, bool)), records[0], records[1])
  stepper(dict(inputs, init=np.zeros(N, bool)), records[1], records[0])
  assert (stepper._init._cache_size(), stepper._step._cache_size()) == (1, 1)
  es_ref, reward, _ = step(es_ref, jax.device_put(inputs["action"], cpu),
                           jax.device_put(seeds, cpu))
  np.testing.assert_allclose(records[1]["reward"], reward, rtol=1e-4, atol=1e-5)
  assert_close(physics_pool._unpack(records[1], stepper.treedef, stepper.key_leaf, True), es_ref)


@pytest.mark.slow
def test_workers_compile_after_the_first_one_from_a_cache_the_pool_removes(monkeypatch):
  # Worker 0 compiles first and sets the event; the others wait for it before they
  # compile (then from the shared cache): a follower compiles nothing until then.
  task = models.load(TASK)
  args = (TASK, task.solver_iterations, task.ls_iterations, SKIP, (N,), False)
  compiled = threading.Event()
  follower = _Stepper(*args, compiled, False)
  follower._warming.join(timeout=2.0)
  assert follower._warming.is_alive() and follower._step._cache_size() == 0
  first = _Stepper(*args, compiled, True)
  first._warming.join()
  assert compiled.is_set() and first._step._cache_size() == 1
  follower._warming.join()
  assert follower._step._cache_size() == 1
  # The pool's own cache (when the user set none) holds what the workers compiled
  # while the pool is open, and goes with it.
  monkeypatch.setattr(physics_pool, "_user_cache_dir", lambda: None)
  with PhysicsPool(task, 2 * N, SKIP, workers=2) as pool:
    cache = pool._own_cache
    pool.init(jax.random.key(0), np.zeros(2 * N, np.int32))
    assert os.listdir(cache)
  assert not os.path.exists(cache)


@pytest.mark.slow
def test_env_with_physics_workers_matches_in_process_env():
  kw = dict(visual_seeds=[0, 1, 2], frame_skip=SKIP, image_size=32, workers=1,
            physics_device="cpu")
  runs = []
  for physics_workers in (0, 2):
    with dmcr_jax.make(TASK, N, physics_workers=physics_workers, **kw) as env:
      obs, _ = env.reset(seed=4)
      rng = np.random.default_rng(0)
      steps = [(obs, None)]
      for _ in range(5):
        obs, reward, _, truncated, info = env.step(rng.uniform(-1, 1, (N, 1)))
        steps.append((obs, reward))
      # As the protocol's pool pass drives it: looks of their own, a reset seed per env.
      env.set_looks([5, 6, 7], ["all", "none", "floor"])
      obs, _ = env.reset(seed=[9, 4, 9])
      steps.append((obs, None))
      for _ in range(3):
        obs, reward, _, truncated, info = env.step(rng.uniform(-1, 1, (N, 1)))
        steps.append((obs, reward))
      runs.append((steps, env.state))
  for (obs_a, r_a), (obs_b, r_b) in zip(*(r[0] for r in runs)):
    np.testing.assert_array_equal(obs_a, obs_b)
    if r_a is not None:
      np.testing.assert_allclose(r_a, r_b, rtol=1e-4, atol=1e-5)
  assert_close(runs[0][1], runs[1][1])


@pytest.mark.slow
def test_ray_caster_env_with_physics_workers_matches_its_fused_step():
  # With the physics in workers the JAX env renders in a call of its own, which
  # `step_wait` does not wait for when the observations stay on the device: they
  # are still the fused in-process step's, across an episode end.
  kw = dict(visual_seeds=[0, 1, 2], frame_skip=SKIP, image_size=16, renderer="jax",
            physics_device="cpu")
  runs = []
  for extra in ({}, dict(physics_workers=2, obs_on_device=True)):
    with dmcr_jax.make(TASK, N, **kw, **extra) as env:
      obs, _ = env.reset(seed=4)
      rng = np.random.default_rng(0)
      steps = [(np.asarray(obs), None, None)]
      for _ in range(EPISODE + 2):
        obs, reward, _, truncated, _ = env.step(rng.uniform(-1, 1, (N, 1)))
        steps.append((np.asarray(obs), reward, truncated))
      runs.append(steps)
  assert any(t.any() for _, _, t in runs[0][1:])  # an episode ended
  for (obs_a, r_a, t_a), (obs_b, r_b, t_b) in zip(*runs, strict=True):
    np.testing.assert_array_equal(obs_a, obs_b)
    if r_a is not None:
      np.testing.assert_allclose(r_a, r_b, rtol=1e-4, atol=1e-5)
      np.testing.assert_array_equal(t_a, t_b)


@pytest.mark.parametrize("workers,device,why", [
    (2, None, "needs physics_device='cpu'"), (-1, "cpu", "positive int"),
    (True, "cpu", "positive int")])
def test_bad_physics_workers_are_refused_before_anything_starts(workers, device, why):
  with pytest.raises(ValueError, match=why):
    dmcr_jax.make(TASK, N, physics_device=device, physics_workers=workers, workers=1)
