"""The training loop and `train` command: argument checks, checkpoints, kill and resume."""

import csv
import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax.train import checkpoint, config, loop, runlog, sac
from dmcr_jax.train.__main__ import parse

# With test_demo and test_evaluate, whose runs the drivers' tests share.
pytestmark = pytest.mark.xdist_group("train")

TINY = sac.SACConfig(batch_size=8, conv_channels=4, feature_dim=8, hidden_dim=16)
CFG = dict(task="pendulum-swingup", action_repeat=100, image_size=16, buffer_capacity=200, num_envs=1,
           warmup_steps=5, quality="fastest", workers=1, log_every=5, sac=TINY)


@pytest.mark.parametrize("argv, match", [
    (["--task", "walker-fly"], "Valid tasks"),
    (["--aug", "blur"], "valid names"),
    (["--seeds", "1,1"], "distinct"),
    (["--steps", "0"], "steps must be a positive int"),
    (["--utd", "0"], "utd must be > 0"),
    (["--quality", "best"], "valid: exact, fast, fastest"),
    (["--visual-seeds", "some"], "not a seed in [0, 2**31 - 1]; valid: an int in"),
    (["--visual-seeds", "-1"], "not a seed in [0, 2**31 - 1]; valid: an int in"),
    (["--visual-seeds", "levels:0"], "levels:0 holds no seed"),
    (["--vary", ""], "vary is empty"),
    (["--vary", "target"], "target do(es) not apply to cartpole"),
    (["--workers", "0"], "workers must be a positive int"),
    (["--seeds", "-1"], "seeds must be distinct ints in [0, 2**31)"),
    (["--image-size", "8"], "image_size must be >= 16"),
    (["--buffer-capacity", "3"], "buffer_capacity must be at least"),
    (["--dtype", "float16"], "float32, bfloat16"),
    (["--agent-loop", "pmap"], "vmap, map"),
    (["--aug", "drq,drq"], "distinct"),
    (["--seeds", "abc"], "argument --seeds: want distinct ints in [0, 2**31) separated by "
                         "commas, e.g. 0,1,2; got 'abc'"),
    (["--algo", "curl", "--aug", "drq"], "--algo curl takes no --aug (got 'drq')"),
    (["--log-every", "0"], "log_every must be a positive int"),
])
def test_bad_arguments_fail_before_anything_is_built(argv, match, capsys):
  with pytest.raises(SystemExit):
    parse(argv)
  err = capsys.readouterr().err
  assert match in err
  assert "beta" not in err and "invalid literal" not in err


def test_defaults_follow_the_paper():
  cfg, _ = parse([])
  assert cfg.task == "cartpole-balance" and cfg.steps == 50_000 and cfg.warmup_steps == 1000
  assert cfg.buffer_capacity == 100_000 and cfg.frame_stack == 3 and cfg.image_size == 84
  assert cfg.sac.batch_size == 256 and cfg.sac.aug == "drq" and cfg.action_repeat is None


def test_physics_steps_in_worker_processes_on_half_the_cores_beside_an_accelerator(
    monkeypatch):
  assert loop.default_physics_workers(16, "gpu") == 8
  assert loop.default_physics_workers(64, "gpu") == loop.PHYSICS_WORKERS_MAX
  assert loop.default_physics_workers(8, "gpu") == 4
  assert loop.default_physics_workers(3, "gpu") == 0  # one worker: the training process
  assert loop.default_physics_workers(16, "cpu") == 0  # the learner needs the cores
  # A plan's count: the default where the physics steps on the host CPU, what the
  # config says otherwise, none where the physics steps on the device.
  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  monkeypatch.setattr(os, "cpu_count", lambda: 16)
  assert parse([])[0].physics_workers is None
  plan = lambda **kw: config.resolve(loop.TrainConfig(**kw))
  assert plan().physics_workers == 8 and plan().physics_device == "cpu"  # 32 envs, "auto"
  assert not plan().device_driver and plan(renderer="jax").device_driver is False
  assert plan(physics_workers=0).physics_workers == 0
  assert plan(physics_workers=3).physics_workers == 3
  assert plan(physics="device").physics_workers == 0
  assert plan(physics="device", renderer="jax").device_driver
  assert plan(num_envs=65).physics_device is None  # "auto": past CPU_PHYSICS_MAX_ENVS


def demo_run(out, **changes) -> loop.TrainConfig:
  """test_demo's training run (tiny pendulum, 2 envs, the JAX renderer, levels:6) into
  `out`, with `changes`: sized alike, the runs share their compilations."""
  from tests.test_demo import TINY as DEMO
  return dataclasses.replace(DEMO.train_config(str(out)), out_dir=str(out), **changes)


def _saved_run(tmp_path):
  """A run folder holding config.json (and no checkpoint); its config and text."""
  out = str(tmp_path / "run")
  os.makedirs(out)
  cfg = loop.TrainConfig(steps=300, warmup_steps=20, out_dir=out, seeds=(3,),
                         **{k: v for k, v in CFG.items() if k != "warmup_steps"})
  loop.save_config(cfg, out)
  with open(os.path.join(out, "config.json")) as f:
    return cfg, f.read()


def test_resume_takes_every_setting_from_the_runs_config(tmp_path, capsys):
  cfg, text = _saved_run(tmp_path)
  resumed, _ = parse(["--out", cfg.out_dir, "--resume"])
  assert resumed == cfg  # not the command line's defaults (50,000 steps, image 84, ...)
  # Flags that may change are applied; equal ones are accepted.
  resumed, _ = parse(["--out", cfg.out_dir, "--resume", "--steps", "900", "--log-every",
                      "7", "--task", "pendulum-swingup", "--image-size", "16"])
  assert resumed == dataclasses.replace(cfg, steps=900, log_every=7)
  # Others are refused, naming them; nothing is written.
  with pytest.raises(SystemExit):
    parse(["--out", cfg.out_dir, "--resume", "--image-size", "32", "--warmup-steps", "1000"])
  err = capsys.readouterr().err
  assert "--image-size 32 (the run has 16)" in err and "--warmup-steps" in err
  with open(os.path.join(cfg.out_dir, "config.json")) as f:
    assert f.read() == text
  # A mistyped folder is refused and not created.
  with pytest.raises(SystemExit):
    parse(["--out", str(tmp_path / "rnu"), "--resume"])
  assert "no run" in capsys.readouterr().err and not os.path.exists(tmp_path / "rnu")


def test_open_run_checks_a_resumed_config_before_writing(tmp_path):
  cfg, text = _saved_run(tmp_path)
  with pytest.raises(ValueError, match=r"image_size \(32, the run has 16\)"):
    loop.open_run(dataclasses.replace(cfg, image_size=32), resume=True)
  with pytest.raises(FileNotFoundError, match="no checkpoint"):
    loop.open_run(dataclasses.replace(cfg, steps=600), resume=True)
  with open(os.path.join(cfg.out_dir, "config.json")) as f:
    assert f.read() == text
  assert os.listdir(cfg.out_dir) == ["config.json"]


@pytest.mark.slow
def test_checkpoint_round_trip(tmp_path):
  # Two agents as a run makes them (one jitted initialiser, shared with the group's
  # other tests; an eager vmap compiles each of its many operations).
  make = lambda s: loop.init_agents(loop.TrainConfig(seeds=(s, s + 1), sac=TINY), (16, 16, 9), 1)
  saved, key = make(0), jax.random.key(42)
  checkpoint.save(checkpoint.manager(str(tmp_path)), 7, saved, key)
  agents, key2, step = checkpoint.restore(str(tmp_path), make(1), jax.random.key(0))
  assert step == 7
  np.testing.assert_array_equal(jax.random.key_data(key2), jax.random.key_data(key))
  for a, b in zip(jax.tree.leaves(saved), jax.tree.leaves(agents)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  # Restored as fresh agents are (uncommitted): a jitted function lowers to the same
  # program for both, so a resumed run reuses the fresh run's compilations.
  program = lambda *tree: jax.jit(lambda *t: jax.tree.map(lambda x: x + 1, t)).lower(
      *tree).as_text()
  assert program(agents, jax.random.key_data(key2)) == program(saved, jax.random.key_data(key))


@pytest.mark.slow
def test_interrupted_run_resumes_where_it_stopped(tmp_path):
  out = str(tmp_path / "run")
  # The resumed run (in this process) reuses the interrupted one's compilations:
  # both use the session's compilation cache (conftest), or one of their own.
  own = jax.config.jax_compilation_cache_dir is None
  cache = str(tmp_path / "jax_cache") if own else jax.config.jax_compilation_cache_dir
  jax.config.update("jax_compilation_cache_dir", cache)
  script = textwrap.dedent(f"""
      from dmcr_jax.train import loop, sac
      cfg = loop.TrainConfig(steps=400, checkpoint_every=10, out_dir={out!r}, seeds=(0, 1),
                             **{ {k: v for k, v in CFG.items() if k != "sac"}!r},
                             sac=sac.SACConfig(batch_size=8, conv_channels=4, feature_dim=8,
                                               hidden_dim=16))
      print(loop.train(cfg, progress=False)["steps"], flush=True)
      """)
  proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True,
                          env=dict(os.environ, JAX_COMPILATION_CACHE_DIR=cache),
                          start_new_session=True)
  ckpt = os.path.join(out, "checkpoints")
  deadline = time.time() + 400
  while time.time() < deadline and proc.poll() is None:
    if os.path.isdir(ckpt) and any(d.isdigit() and int(d) >= 20 for d in os.listdir(ckpt)):
      break
    time.sleep(0.5)
  assert proc.poll() is None, proc.communicate()[1][-2000:]
  # As `timeout` and Ctrl-C do: the whole process group (render workers too).
  os.killpg(proc.pid, signal.SIGTERM)
  stdout, stderr = proc.communicate(timeout=120)
  assert proc.returncode == 0, stderr[-2000:]
  stopped = int(stdout.split()[-1])
  assert 20 <= stopped < 400
  saved = max(int(d) for d in os.listdir(ckpt) if d.isdigit())
  assert saved == stopped  # the signal's checkpoint, and where it is said
  assert (f"interrupted: saved checkpoint at step {stopped} in {ckpt}/{stopped}; resume "
          f"with dmcr-train --resume --out {out}") in stderr

  cfg = loop.TrainConfig(steps=stopped + 15, checkpoint_every=0, out_dir=out, seeds=(0, 1),
                         **{k: v for k, v in CFG.items()})
  updates_at_stop = np.asarray(loop.load_run(out)[1].step)
  summary = loop.train(cfg, resume=True, progress=False)
  assert summary["steps"] == stopped + 15 and not summary["interrupted"]
  # Both processes' pieces of the run, with the learner's device and loop times.
  assert [(s["start"], s["steps"]) for s in summary["segments"]] == [(0, stopped),
                                                                      (stopped, stopped + 15)]
  assert all(s["device"] and s["wall_s"] > 0 for s in summary["segments"])
  assert summary["train_wall_s"] == pytest.approx(sum(s["wall_s"] for s in summary["segments"]))
  assert max(int(d) for d in os.listdir(ckpt) if d.isdigit()) == stopped + 15
  with open(os.path.join(out, "log.csv")) as f:
    rows = list(csv.DictReader(f))
  assert {r["agent"] for r in rows} == {"0", "1"}
  steps = [int(r["step"]) for r in rows]
  assert steps == sorted(steps) and steps[-1] > stopped  # the log never goes back
  walls = [float(r["wall_s"]) for r in rows]
  assert walls == sorted(walls)  # wall time carries across the resume
  assert os.path.exists(os.path.join(out, "learning_curve.png"))
  restored_cfg, agents, step = loop.load_run(out)
  assert step == stopped + 15 and restored_cfg == cfg
  assert agents.step.shape == (2,) and int(agents.step[0]) > 0
  # The buffers refilled for warmup_steps transitions (no updates), then one
  # update per transition: 15 − 5 = 10 updates, in pairs.
  np.testing.assert_array_equal(np.asarray(agents.step) - updates_at_stop, [10, 10])
  with pytest.raises(FileExistsError, match="--resume"):
    loop.train(cfg, progress=False)  # a new run would overwrite this one
  with pytest.raises(FileNotFoundError, match="no run in"):
    loop.train(loop.TrainConfig(steps=5, out_dir=str(tmp_path / "empty"), **CFG),
               resume=True, progress=False)
  assert not os.path.exists(tmp_path / "empty")
  if own:
    jax.config.update("jax_compilation_cache_dir", None)


@pytest.mark.slow
@pytest.mark.parametrize("start", [0, 40])
def test_no_update_is_owed_until_the_buffers_refill(start):
  # A fresh run (start 0) owes nothing during its warm-up; a resumed one (start
  # 40: its buffers were not checkpointed) owes nothing for a warm-up's worth of
  # transitions after its start, then `utd` per transition in pairs, as the fresh
  # run after its warm-up. Both drivers' bookkeeping (NumPy and traced).
  from dmcr_jax.train import step as train_step
  spec = train_step.StepSpec(agents=1, num_envs=4, warmup_steps=10, utd=1.0, sac=TINY,
                             agent_loop="vmap", low=(-1.0,), high=(1.0,))
  first = loop.updates_from(loop.TrainConfig(warmup_steps=10), start)
  assert first == start + 10
  for xp in (np, jnp):
    owed, ready, pairs_run = np.float32(0), False, []
    for step in range(start, start + 40, 4):
      owed, ready, pairs = train_step.plan_updates(
          owed, ready, step, lambda: True, spec, xp,
          first if xp is np else jnp.int32(first))
      ready = bool(ready)
      pairs_run.append(int(pairs))
    # Transitions start+4 … start+40 in steps of 4; the one ending past start+10
    # owes 2 (the part past the refill), every later one 4: 2 pairs each.
    assert pairs_run == [0, 0, 1, 2, 2, 2, 2, 2, 2, 2]


@pytest.mark.slow
def test_host_and_device_drivers_train_identical_agents(tmp_path):
  # One training step, two drivers: fed the same frames (the ray caster's), the
  # host driver (jitted act/learn/store around the env) and the device driver
  # (the same functions scanned) train the same agents from one seed: the same
  # RNG stream, updates and data, so only float32 rounding may differ (XLA compiles
  # the scan and the separate jits differently; on some CPUs bit for bit, on others
  # in the last bits, which Adam's normalised steps carry into every parameter).
  # Each entry must agree within a thousandth of its leaf's largest entry, but for
  # a few: a gradient entry at rounding level may change sign, which Adam's
  # normalised step turns into a whole step of difference (at most one entry or 1 %
  # of a leaf, 0.1 % of all entries). A different key, update count or transition
  # moves nearly every entry of every leaf.
  # The demo's run (test_demo, same group) twice as long: the device driver's two
  # chunks are the demo's one chunk, compiled once for both tests.
  agents = {}
  for physics in ("cpu", "device"):   # on a CPU: host driver, then device driver
    cfg = demo_run(tmp_path / physics, steps=48, chunk_steps=12, physics=physics)
    loop.train(cfg, progress=False)
    _, agents[physics], step = loop.load_run(cfg.out_dir)
    assert step == 48 and int(agents[physics].step[0]) > 0  # updates ran
  far_entries, entries = 0, 0
  for a, b in zip(jax.tree.leaves(agents["cpu"]), jax.tree.leaves(agents["device"])):
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype.kind in "biu":
      np.testing.assert_array_equal(a, b)
    else:
      far = ~(np.abs(a - b) <= 1e-3 * float(np.max(np.abs(b), initial=0.0)))   # NaN: far
      assert far.sum() <= max(1, far.size // 100), (far.sum(), far.size, a[far], b[far])
      far_entries, entries = far_entries + int(far.sum()), entries + far.size
  assert far_entries <= entries // 1000, (far_entries, entries)


@pytest.mark.slow
def test_host_driver_trains_the_same_agents_whichever_it_dispatches_first(tmp_path,
                                                                          monkeypatch):
  # The host driver dispatches the physics before the updates when they share a
  # device, else the updates first, before it waits for the actions (and the ray
  # caster's env, its physics in a worker process, does not wait for the frames).
  # The order moves work on the device's queue, not what it computes: with the
  # ray caster, physics in a worker and one seed, the same agents bit for bit.
  agents = {}
  for first in (True, False):
    monkeypatch.setattr(loop, "physics_before_updates", lambda device, first=first: first)
    cfg = demo_run(tmp_path / str(first), steps=24, physics="cpu", physics_workers=1)
    loop.train(cfg, progress=False)
    _, agents[first], step = loop.load_run(cfg.out_dir)
    assert step == 24 and int(agents[first].step[0]) > 0  # updates ran
  for a, b in zip(jax.tree.leaves(agents[True]), jax.tree.leaves(agents[False]), strict=True):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow
def test_agents_sharded_over_two_devices_or_mapped_match_one_vmapped_call():
  script = textwrap.dedent("""
      import dataclasses
      import jax, jax.numpy as jnp, numpy as np
      from dmcr_jax.train import loop, replay, sac, step
      assert jax.device_count() == 2
      cfg = sac.SACConfig(batch_size=8, conv_channels=4, feature_dim=8, hidden_dim=16)
      spec = step.StepSpec(agents=2, num_envs=2, warmup_steps=0, utd=1.0, sac=cfg,
                           agent_loop="vmap", low=(-1.0,), high=(1.0,))
      agents = loop.init_agents(loop.TrainConfig(seeds=(0, 1), sac=cfg), (16, 16, 9), 1)
      one = replay.init(64, 2, (16, 16, 3), 1, 3)
      buffers = jax.tree.map(lambda x: jnp.broadcast_to(x, (2,) + x.shape), one)
      learner = step.init_learner(agents, buffers, jax.random.key(3), 0, spec)
      rng = np.random.default_rng(0)
      for t in range(12):
        learner = step.store_jit(
            learner, jnp.asarray(rng.integers(0, 255, (4, 16, 16, 9), np.uint8)),
            jnp.full((4,), t % 6 == 0), jnp.asarray(rng.uniform(-1, 1, (2, 2, 1)), jnp.float32),
            jnp.asarray(rng.uniform(0, 1, (4,)), jnp.float32), spec=spec)
      mesh = loop.agent_mesh(2)
      assert mesh is not None
      copy = lambda t: jax.tree.map(lambda x: x.copy() if hasattr(x, "copy") else x, t)
      mapped_spec = dataclasses.replace(spec, agent_loop="map")
      plain = step.learn_jit(copy(learner), pairs=2, spec=spec)   # learn donates
      mapped = step.learn_jit(copy(learner), pairs=2, spec=mapped_spec)
      for a, b in zip(jax.tree.leaves(plain.agents.params), jax.tree.leaves(mapped.agents.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=2e-3)
      put = lambda t: loop.put_agents(t, mesh)
      sharded = step.learn_jit(copy(learner).replace(agents=put(learner.agents),
                                                     buffers=put(learner.buffers)),
                               pairs=2, spec=spec, mesh=mesh)
      leaf = jax.tree.leaves(sharded.agents.params)[0]
      assert len(leaf.sharding.device_set) == 2, leaf.sharding
      for name in plain.metrics:
        np.testing.assert_allclose(np.asarray(plain.metrics[name]),
                                   np.asarray(sharded.metrics[name]), rtol=1e-4, atol=1e-6,
                                   err_msg=name)
      for a, b in zip(jax.tree.leaves(plain.agents.params), jax.tree.leaves(sharded.agents.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=2e-3)
      obs = jnp.asarray(rng.integers(0, 255, (4, 16, 16, 9), np.uint8))
      acted = np.asarray(step.act_jit(plain, obs, spec=spec)[1])
      np.testing.assert_allclose(
          acted, np.asarray(step.act_jit(sharded, put(obs), spec=spec, mesh=mesh)[1]), atol=1e-3)
      # The agents' policies one after the other (`map`) act as the vmapped ones,
      # each agent's as its own `sac.act` on its envs with its key of the step.
      np.testing.assert_allclose(
          acted, np.asarray(step.act_jit(plain, obs, spec=mapped_spec)[1]), atol=1e-5)
      keys = jax.random.split(jax.random.split(plain.key)[1], 2)
      for k in range(2):
        one = jax.tree.map(lambda x: x[k], plain.agents)
        np.testing.assert_allclose(acted[k], np.asarray(sac.act(one, obs[2 * k:2 * k + 2], keys[k])),
                                   atol=1e-5)
      print("ok")
      """)
  # The session's compile flags (conftest) and two forced host devices.
  flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
  env = dict(os.environ, XLA_FLAGS=flags.strip(),
             JAX_PLATFORMS="cpu")
  out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       env=env, timeout=600)
  assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


def test_run_log_reports_progress_every_few_percent_and_announces_compiling(tmp_path, capsys):
  # A CPU run of 600 steps with log_every 1,000 showed 0/600 and an empty log.csv
  # until its end, and compiled for a minute without a word.
  cfg = loop.TrainConfig(steps=600, log_every=1000, out_dir=str(tmp_path), **{
      k: v for k, v in CFG.items() if k != "log_every"})
  log = runlog.RunLog(cfg, cfg.agents(), None, 0, resume=False, progress=False)
  try:
    assert "compiling" in capsys.readouterr().err
    assert log.every == 12  # 2 % of the run
    assert log.due(10, 12) and not log.due(0, 11) and log.due(599, 600)
    log.progress(12)
    assert "step 12/600 (2 %)" in capsys.readouterr().err
    log.episode(14, 0, 123.5, 1.0, {})
    with open(os.path.join(str(tmp_path), "log.csv")) as f:  # written at once
      assert [r["episode_return"] for r in csv.DictReader(f)] == ["123.5"]
  finally:
    log.close()


def test_progress_into_a_redirected_stderr_is_lines_not_a_bar(tmp_path, capsys):
  # tqdm wrote every update (carriage returns and all) into a redirected stderr;
  # without a terminal the progress is a line every few percent.
  cfg = loop.TrainConfig(steps=600, out_dir=str(tmp_path), **CFG)
  with runlog.RunLog(cfg, cfg.agents(), None, 0, resume=False, progress=True) as log:
    assert not sys.stderr.isatty()
    for step in range(2, 26, 2):
      log.episode(step, 0, 1.0, 1.0, {})
      if log.due(step - 2, step):
        log.progress(step)
  err = capsys.readouterr().err
  assert "\r" not in err and "it/s" not in err  # no tqdm bar
  lines = [line.split(",")[0] for line in err.splitlines() if ": step " in line]
  assert lines == [f"pendulum-swingup: step {s}/600 ({100 * s / 600:.0f} %)"
                   for s in (6, 10, 16, 20)]


def test_a_resumed_log_drops_the_rows_past_its_checkpoint_and_carries_wall_time(tmp_path,
                                                                               capsys):
  # A killed run logs episodes after its last checkpoint; resumed from that
  # checkpoint, `step` went backwards (…, 377, 375, 501), `wall_s` restarted at 0
  # and the killed process was missing from the summary's segments.
  cfg = loop.TrainConfig(steps=600, out_dir=str(tmp_path), **CFG)
  specs = cfg.agents()
  with runlog.RunLog(cfg, specs, None, 0, resume=False, progress=False) as log:
    for step in (100, 200, 300):
      log.episode(step, 0, float(step), 10.0 * step / 100, {})
    log.checkpointed(200)   # the last checkpoint before the kill: step 200
  segments = runlog.read_json(str(tmp_path / runlog.SEGMENTS))
  assert [(s["start"], s["steps"]) for s in segments] == [(0, 200)]
  killed_wall = segments[0]["wall_s"]
  with runlog.RunLog(cfg, specs, None, 200, resume=True, progress=False) as log:
    assert "dropped the log rows past step 200" in capsys.readouterr().err
    log.episode(250, 0, 1.0, 2.0, {})
    log.checkpointed(250)
    assert [(s["start"], s["steps"]) for s in log.segments(250)] == [(0, 200), (200, 250)]
  with open(tmp_path / "log.csv") as f:
    rows = list(csv.DictReader(f))
  assert [int(r["step"]) for r in rows] == [100, 200, 250]
  assert float(rows[-1]["wall_s"]) == pytest.approx(killed_wall + 2.0, abs=0.01)
  assert [(s["start"], s["steps"]) for s in runlog.read_json(
      str(tmp_path / runlog.SEGMENTS))] == [(0, 200), (200, 250)]


def test_learning_curve_shows_a_single_point(tmp_path):
  import matplotlib.image
  path = str(tmp_path / "log.csv")
  with open(path, "w") as f:
    f.write("step,agent,seed,aug,episode_return\n300,0,0,drq,40.0\n")
  png = str(tmp_path / "curve.png")
  assert loop.plot_learning_curve(path, png, [(0, "drq")]) == {"seed 0": 40.0}
  rgb = matplotlib.image.imread(png)[..., :3]
  blue = np.abs(rgb - np.array([0x1f, 0x77, 0xb4]) / 255).max(axis=-1) < 0.1  # line colour C0
  h, w = blue.shape
  # The lone point sits mid-axes (the legend goes to a corner): a marker there.
  assert blue[h // 4:3 * h // 4, w // 3:2 * w // 3].sum() > 5


def test_train_command_reports_progress_every_2_percent(tmp_path, monkeypatch):
  import dmcr_jax.train.__main__ as cli
  seen = {}

  def fake_train(plan, **kwargs):
    seen["plan"] = plan
    return {"interrupted": False}
  monkeypatch.setattr(cli, "train", fake_train)
  cli.main(["--steps", "600", "--out", str(tmp_path / "run")])
  assert seen["plan"].cfg.log_every == 12  # not the default 1,000 (> the run)


def test_egl_devices_reach_the_env_and_survive_config_json(monkeypatch, tmp_path):
  # --egl-devices places the render workers' frames (RenderPool's test checks that the
  # workers get them); here: the config carries them to `make` and through config.json,
  # and a resumed run may change them.
  import dmcr_jax
  cfg, _ = parse(["--task", "cartpole-balance", "--egl-devices", "1,2", "--workers", "3",
                  "--out", str(tmp_path)])
  assert cfg.egl_devices == (1, 2)
  seen = {}
  monkeypatch.setattr(dmcr_jax, "make", lambda *a, **k: seen.update(k))
  loop.make_env(cfg)
  assert (seen["egl_devices"], seen["workers"]) == ((1, 2), 3)
  loop.save_config(cfg, str(tmp_path))
  assert loop.load_config(str(tmp_path)) == cfg
  resumed, _ = parse(["--task", "cartpole-balance", "--egl-devices", "0", "--resume",
                      "--out", str(tmp_path)])
  assert resumed.egl_devices == (0,)
