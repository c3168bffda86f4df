"""`dmcr-demo` (train/demo.py): argument checks, and the files a run writes."""

import json
import os
import subprocess
import sys

import imageio.v3 as iio
import pytest

from dmcr_jax.train import demo as dm
from dmcr_jax.train import sac

# test_train's and test_evaluate's group: test_evaluate's JAX-renderer evaluation is
# sized as the demo's (2 envs, pendulum, 16 px) and test_train's device driver trains
# as the demo does, so one worker compiles those programs once for all.
pytestmark = pytest.mark.xdist_group("train")

# Pendulum at action repeat 100 (10 agent steps per episode), tiny networks: the
# files and the refusal do not depend on the task (the default, cartpole, is the
# full test's); pendulum's env, with the fewest bodies to step and ray-cast,
# compiles fastest. Six training looks: the training env is test_jax_env's (2 envs,
# levels:6), whose step test_train's host driver shares.
TINY = dm.Demo(task="pendulum-swingup", steps=24, num_envs=2, train_looks=6, image_size=16,
               action_repeat=100, warmup_steps=8, eval_looks=2, eval_states=1,
               sac=sac.SACConfig(batch_size=8, conv_channels=4, feature_dim=8, hidden_dim=16))


@pytest.mark.parametrize("argv, match", [
    (["--steps", "0"], "steps must be a positive int"),
    (["--task", "cartpole-nope"], "Valid tasks: ball_in_cup-catch"),
])
def test_bad_arguments_fail_before_anything_is_created(tmp_path, capsys, argv, match):
  out = tmp_path / "demo"
  with pytest.raises(SystemExit) as e:
    dm.main(argv + ["--out", str(out)])
  assert e.value.code == 2
  assert match in capsys.readouterr().err
  assert not out.exists()


def test_help_shows_the_defaults(capsys):
  with pytest.raises(SystemExit):
    dm.main(["--help"])
  text = " ".join(capsys.readouterr().out.split())
  assert "(default: dmcr_demo)" in text and f"(default: {dm.Demo().steps})" in text
  assert "(default: cartpole-balance)" in text


def test_readme_starts_with_the_demo_and_the_script_is_installed():
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  with open(os.path.join(root, "README.md")) as f:
    readme = f.read()
  first = readme.split("```bash\n", 1)[1].split("```", 1)[0]
  commands = [l for l in first.splitlines() if l and not l.startswith("#")]
  assert commands[0] == ("python3 -m venv .venv && . .venv/bin/activate && pip install -e . "
                         "&& dmcr-demo")
  assert "dmcr-rollout" in readme.split("## Tasks", 1)[0]  # still the second example
  with open(os.path.join(root, "pyproject.toml")) as f:
    assert 'dmcr-demo = "dmcr_jax.train.demo:main"' in f.read()
  out = subprocess.run([sys.executable, "-m", "dmcr_jax.train.demo", "--help"], capture_output=True,
                       text=True, timeout=120, cwd=root)
  assert out.returncode == 0 and "usage: dmcr-demo" in out.stdout, out.stderr[-2000:]


@pytest.mark.slow
def test_demo_writes_its_files_and_refuses_to_overwrite_them(tmp_path, capsys):
  out = str(tmp_path / "demo")
  result = dm.run(TINY, out, progress=False)
  files = result["files"]
  assert set(files) == {"visual seeds", "learning curve", "training log",
                        "per-factor table", "eval.png", "eval.json"}
  for path in files.values():
    assert os.path.getsize(path) > 0, path
  # Two rows of tiles: the training looks, then as many held-out looks (here the
  # evaluation's two).
  grid = iio.imread(files["visual seeds"])
  tile = dm.GRID_TILE
  assert grid.shape == (2 * (tile + 2) + 2, 6 * (tile + 2) + 2, 3)
  with open(files["eval.json"]) as f:
    ev = json.load(f)
  assert ev["conditions"] == ["none", "light", "camera", "body", "floor", "background",
                              "all"]
  agent = ev["agents"][0]
  assert len(agent["train"]["episodes"]) == 2
  assert all(len(agent["conditions"][c]["episodes"]) == 2 for c in ev["conditions"])
  assert ev["train_look"] == "levels:6" and ev["checkpoint_step"] == 24
  with open(files["per-factor table"]) as f:
    assert "| seed 0, drq |" in f.read()
  assert result["train"]["steps"] == 24 and result["last_return"] is not None
  text = dm.report(TINY, result)
  assert "What it cannot show" in text and f"dmcr-train --task {TINY.task} --steps 50000" in text
  assert all(path in text for path in files.values())
  # A second demo into the same folder is refused before anything is done.
  with pytest.raises(ValueError, match="already holds a demo run"):
    dm.run(TINY, out, progress=False)
  with pytest.raises(SystemExit):
    dm.main(["--out", out])
  assert "already holds a demo run" in capsys.readouterr().err


@pytest.mark.full
def test_the_readme_command_runs_the_whole_demo(tmp_path):
  # `dmcr-demo` at its defaults, as the README's first command runs it (minutes).
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  out = subprocess.run([sys.executable, "-m", "dmcr_jax.train.demo", "--out", str(tmp_path / "d"),
                        "--no-progress"], capture_output=True, text=True, timeout=900,
                       cwd=root, env=dict(os.environ, JAX_PLATFORMS="cpu"))
  assert out.returncode == 0, out.stderr[-3000:]
  for name in ("visual_seeds.png", "run/learning_curve.png", "eval/eval.md"):
    assert os.path.exists(tmp_path / "d" / name), name
  assert "What it cannot show" in out.stdout
