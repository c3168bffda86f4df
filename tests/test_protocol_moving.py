"""`dmcr_jax.protocol` under moving conditions (``moving-<factor>@<intensity>``).

A moving condition's returns equal those of `dmcr_jax.make(..., vary="none",
moving=F, intensity=I)` stepped from the host with the same policy and seeds, for the
ray caster (one block program holding static and moving conditions) and the pool (a
pool env per motion); intensity 0 is the static "none" exactly; bad names are refused
before anything compiles, naming the valid ones; the report's rows say factor and
intensity.

Tiny sizes: cartpole-balance at action repeat 100 (10 agent steps an episode), 16 px
frames, 2 held-out looks × 2 initial states. The policy reads four pixels with
elementwise arithmetic, so returns compare exactly across batch layouts.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dmcr_jax
from dmcr_jax import protocol as P
from dmcr_jax import protocol_pool, protocol_report
from tests.host_episodes import host_episode_returns

# In test_protocol's group: the pool test's envs (8: 2 looks × 4 initial states) step
# the physics that its pool pass compiled.
pytestmark = pytest.mark.xdist_group("protocol")

TASK = "cartpole-balance"
OPTS = dict(visual_seeds=2, dynamics_seeds=2, train_episodes=2, train_look=0,
            image_size=16, action_repeat=100, seed=0)
MOVING = {"moving-camera@0.5": ("camera", 0.5), "moving-all@0.3": ("all", 0.3)}


def policy(params, obs, key):
  """tanh of a weighted sum of four pixels of the newest frame."""
  x = obs.astype(jnp.float32) / 255.0
  w = params["w"]
  z = (params["b"] + w[0] * x[:, 2, 3, 6] + w[1] * x[:, 8, 8, 7] + w[2] * x[:, 12, 5, 8]
       + w[3] * x[:, 5, 12, 7])
  return jnp.tanh(z)[:, None]


PARAMS = dict(w=jax.random.normal(jax.random.key(0), (4,)) * 4.0, b=jnp.float32(-0.5))


def host_returns(renderer, conditions, opts=OPTS, act=None, **render):
  """Each condition's returns from `dmcr_jax.make` envs stepped from the host: one
  static env swept over the static conditions, one env per moving condition; the
  actions `act(obs)` (default: `policy` with `PARAMS`)."""
  seeds = np.repeat(P.held_out_seeds(opts["visual_seeds"], opts["seed"]),
                    opts["dynamics_seeds"])
  resets = P.reset_seeds(seeds.size, opts["seed"])
  act = act or jax.jit(lambda obs: policy(PARAMS, obs, None))
  make = lambda **kw: dmcr_jax.make(
      TASK, num_envs=seeds.size, visual_seeds=seeds, frame_skip=opts["action_repeat"],
      image_size=opts["image_size"], seed=opts["seed"], renderer=renderer, **render, **kw)

  run = lambda env: host_episode_returns(env, act, resets)

  out = {}
  if any(c not in MOVING for c in conditions):
    with make(vary="none") as env:
      for c in conditions:
        if c not in MOVING:
          env.set_visuals(seeds, vary=c)
          out[c] = run(env)
  for c in conditions:
    if c in MOVING:
      factor, intensity = MOVING[c]
      with make(vary="none", moving=factor, intensity=intensity) as env:
        out[c] = run(env)
  return out


def check_equal(result, want):
  for c, returns in want.items():
    np.testing.assert_allclose(result.returns[c][0], returns, rtol=1e-6, err_msg=c)
  # Intensity 0 is the static look exactly; moving looks change the returns.
  if "moving-camera@0" in result.returns:
    np.testing.assert_array_equal(result.returns["moving-camera@0"], result.returns["none"])
  assert not np.array_equal(result.returns["moving-camera@0.5"], result.returns["none"])


@pytest.mark.slow
def test_moving_conditions_return_what_the_host_stepped_moving_env_returns():
  # One block program holds static conditions, a factor moving alone, every factor
  # moving, and a factor at intensity 0; the host env moves the camera alone. The
  # pass is test_protocol's one-agent pass (its policy, options and conditions, which
  # hold these moving ones; same group and worker): one compilation serves both.
  from tests import test_protocol as TP
  proto = TP.prepare_single()
  assert set(TP.MOVING) <= set(proto.conditions) and "none" in proto.conditions
  assert proto.plan.moving == ("camera", "light", "body", "floor", "background")
  params = TP.make_params()
  result = proto(params)
  act = jax.jit(lambda obs: TP.pixel_policy(params, obs, jax.random.key(0)))
  check_equal(result, host_returns("jax", ("moving-camera@0.5",), TP.OPTS, act, **TP.RAY))
  assert not np.array_equal(result.returns["moving-all@0.3"], result.returns["none"])


@pytest.mark.slow
def test_the_pool_runs_moving_conditions_as_the_host_stepped_moving_pool_env():
  # A block of two motions: two pool envs of 8 envs each (2 looks × 4 initial states),
  # as the host's.
  conditions = ("none", "moving-camera@0.5")
  render = dict(quality="fastest", workers=1)
  opts = {**OPTS, "dynamics_seeds": 4}
  result = P.evaluate(TASK, policy, PARAMS, renderer="pool", conditions=conditions,
                      **render, **opts)
  check_equal(result, host_returns("pool", conditions, opts, **render))


def test_moving_intensities_add_every_factor_and_all_at_each_intensity():
  proto = P.prepare(TASK, policy, conditions=("none", "moving-camera@.1"),
                    moving_intensities=(0.1, 0.2), **OPTS)
  assert proto.conditions == ("none", "moving-camera@0.1", "moving-light@0.1",
                              "moving-body@0.1", "moving-floor@0.1", "moving-background@0.1",
                              "moving-all@0.1", "moving-camera@0.2", "moving-light@0.2",
                              "moving-body@0.2", "moving-floor@0.2", "moving-background@0.2",
                              "moving-all@0.2")
  plan = proto.plan
  seg = {s.name: s for s in plan.segments}
  assert seg["moving-all@0.2"].vary == "none"
  assert seg["moving-all@0.2"].motion == (plan.moving, 0.2)
  on, level = plan.motion_arrays(np.arange(plan.episodes))
  # "none" and the static train episodes move nothing; moving-body@0.1 moves the body.
  b = seg["moving-body@0.1"].start
  assert not on[:2].any() and level[:2].tolist() == [0, 0]
  assert on[b].tolist() == [False, False, True, False, False] and level[b] == np.float32(0.1)
  # Pool: one env per motion in a block of several motions.
  groups = protocol_pool.block_groups(2, np.array([0, 0, 1, 2, 1]))
  assert [(m, rows.tolist()) for m, rows, _ in groups] == [
      (0, [0, 1, 5, 6]), (1, [2, 4, 7, 9]), (2, [3, 8])]


@pytest.mark.slow
def test_each_env_of_a_block_draws_the_look_of_its_own_moving_env():
  # One block's looks at a step, envs of several motions (a factor alone, every
  # factor, none: a static condition) against the look `dmcr_jax.make(moving=F,
  # intensity=I)` makes for each env alone; the static envs' extras (a zero floor
  # offset, a sky blended with weight 0) draw the static floor and sky.
  from dmcr_jax import jax_env, protocol_ray
  from dmcr_jax.visuals import jax_render_scene as JS
  from dmcr_jax.visuals.params import factor_mask
  rm, scene = jax_env.scene_of("cartpole")
  envs = [("none", ("camera",), 0.5),
          ("none", ("camera", "light", "body", "floor", "background"), 0.3), ("all", (), 0.0)]
  moving = ("camera", "light", "body", "floor", "background")
  seeds = jnp.asarray([2**30 + 5, 2**30 + 6, 2**30 + 7], jnp.int32)
  masks = jnp.asarray(np.stack([factor_mask("cartpole", v) for v, _, _ in envs]))
  on = jnp.asarray([[f in m for f in moving] for _, m, _ in envs])
  level = jnp.asarray([i for _, _, i in envs], jnp.float32)
  maker = JS.look_maker(scene, rm, "all")
  t = jnp.int32(37)
  got = jax.jit(lambda: protocol_ray.step_looks(
      maker, protocol_ray.block_params(maker, masks, seeds), t, moving, (on, level)))()
  for e, (vary, factors, intensity) in enumerate(envs):
    alone = JS.look_maker(scene, rm, vary, factors, intensity)
    want = jax.jit(lambda s: alone(s, jnp.full((1,), t)))(seeds[e:e + 1])
    for field in JS.DeviceLook.__dataclass_fields__:
      mine, theirs = getattr(got, field), getattr(want, field)
      if theirs is None:   # the factor does not move here: its static value
        theirs = {"floor_rgba": scene.rgba[scene.floor_obj][None],
                  "sky_mix": np.zeros(1), "sky2": np.asarray(mine[e:e + 1])}[field]
      # Equal up to float32 rounding (the env's intensity is a constant of its own
      # program, here an array: XLA folds constants its own way).
      np.testing.assert_allclose(np.asarray(mine[e:e + 1]), np.asarray(theirs), rtol=2e-6,
                                 atol=2e-6, err_msg=f"env {e} {field}")
  # The looks move: env 0's camera is not the static camera.
  static = protocol_ray.block_looks(maker, masks, seeds)
  assert not np.array_equal(got.cam_pos[0], static.cam_pos[0])
  np.testing.assert_array_equal(got.cam_pos[2:], static.cam_pos[2:])


def _no_compile(monkeypatch):
  def fail(*a, **k):
    raise AssertionError("compiled before the input was checked")
  monkeypatch.setattr(P, "_ray_block_jit", fail)


@pytest.mark.parametrize("options, match", [
    (dict(conditions=("moving-fog@0.2",)), r"'fog' is not a moving factor of cartpole-balance; "
     r"valid: none, light, camera, body, floor, background, all, or moving-<factor>@"
     r"<intensity> with factor one of camera, light, body, floor, background, all"),
    (dict(conditions=("moving-camera@2",)), r"intensity must be a number in \[0, 1\], got '2'"),
    (dict(conditions=("moving-camera@x",)), r"intensity must be a number in \[0, 1\]"),
    (dict(conditions=("moving-camera",)), r"conditions \['moving-camera'\] are not valid"),
    (dict(conditions=("camera@0.2",)), r"are not valid for cartpole-balance; valid: none"),
    (dict(conditions=("moving-camera@0.2", "moving-camera@.2")), "name a condition twice"),
    (dict(moving_intensities=(0.1, 1.5)), r"moving intensities must be numbers in \[0, 1\]"),
])
def test_bad_moving_conditions_are_refused_before_anything_compiles(options, match,
                                                                    monkeypatch):
  _no_compile(monkeypatch)
  with pytest.raises(ValueError, match=match):
    P.evaluate(TASK, policy, PARAMS, **{**OPTS, **options})


def test_a_moving_factor_the_domain_lacks_is_refused():
  with pytest.raises(ValueError, match="'background' is not a moving factor of reacher-easy"):
    P.check_conditions("reacher-easy", ("moving-background@0.2",))


def test_the_report_rows_say_factor_and_intensity(tmp_path):
  names = ("none", "moving-camera@0.1", "moving-all@0.1", "moving-camera@0.2", "moving-all@0.2")
  returns = {c: [[100.0 - 10 * i, 100.0 - 10 * i]] for i, c in enumerate(names)}
  r = P.Results(task=TASK, conditions=names, train=np.array([[100.0, 100.0]]),
                returns={c: np.asarray(v) for c, v in returns.items()},
                test_visual_seeds=np.array([2**30 + 1, 2**30 + 2]), train_looks=("seed 0",),
                config=dict(visual_seeds=2, dynamics_seeds=1, train_episodes=2,
                            renderer="jax"),
                labels=("mine",), device="cpu", wall_s=1.0, compile_s=1.0, agent_steps=20)
  summary = r.write(str(tmp_path))
  saved = json.loads((tmp_path / "eval.json").read_text())
  assert saved["moving"][1] == dict(condition="moving-all@0.1", factor="all", intensity=0.1)
  cell = saved["agents"][0]["conditions"]["moving-camera@0.2"]
  assert (cell["factor"], cell["intensity"], cell["mean"]) == ("camera", 0.2, 70.0)
  table = (tmp_path / "eval.md").read_text()
  assert table == protocol_report.markdown(summary)
  assert "| agent | train | none | E_G |" in table      # the static table: static columns
  assert "| agent | intensity | train | camera | all |" in table
  assert "| mine | 0.1 | 100.0 | 90.0 | 80.0 |" in table
  assert "| mine | 0.2 | 100.0 | 70.0 | 60.0 |" in table
  assert "| policy | intensity | camera | all |" in table
  assert "| mine | 0.2 | 30.0 % | 40.0 % |" in table
  assert (tmp_path / "eval.png").stat().st_size > 0


def test_dmcr_evaluate_takes_moving_intensities():
  from dmcr_jax.train import evaluate as E
  cfg = E.EvalConfig(conditions=("none", "all"),
                     moving_intensities=E.intensities_arg("0.1,0.3"))
  assert E.check_eval_config(cfg, "reacher-easy") == (
      "none", "all", "moving-camera@0.1", "moving-light@0.1", "moving-body@0.1",
      "moving-floor@0.1", "moving-all@0.1", "moving-camera@0.3", "moving-light@0.3",
      "moving-body@0.3", "moving-floor@0.3", "moving-all@0.3")
  with pytest.raises(ValueError, match="'sky' is not a moving factor of walker-walk"):
    E.check_eval_config(E.EvalConfig(conditions=("moving-sky@0.1",)), "walker-walk")
