"""The commands as a user meets them: clean stdout, help with defaults, one-paragraph
errors that end the process (run in subprocesses with a timeout)."""

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.xdist_group("cli")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run(args, timeout=240, **env):
  """`python args…` from the repository root; (returncode, stdout, stderr)."""
  out = subprocess.run([sys.executable] + list(args), capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT,
                       env=dict(os.environ, JAX_PLATFORMS="cpu", **env))
  return out.returncode, out.stdout, out.stderr


def test_importing_the_package_prints_nothing_to_stdout():
  # mujoco-mjx prints "Failed to import warp: …" to stdout when warp is absent.
  code, stdout, stderr = run(["-c", "import dmcr_jax, dmcr_jax.train.loop"])
  assert code == 0, stderr[-2000:]
  assert stdout == ""
  assert "warp" not in stderr


def test_importing_the_package_sets_only_what_its_docstring_names():
  # `dmcr_jax._process_settings`: MUJOCO_GL (with PYOPENGL_PLATFORM) on a headless
  # machine and XLA's CPU scheduler flag; gymnasium, which registers the envs,
  # sets its own PYGAME_HIDE_SUPPORT_PROMPT. No JAX is imported, none configured.
  script = ("import os, sys; before = dict(os.environ); import dmcr_jax; "
            "print(sorted(k for k in set(before) | set(os.environ) "
            "if before.get(k) != os.environ.get(k)), 'jax' in sys.modules)")
  env = {k: v for k, v in os.environ.items()
         if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "XLA_FLAGS", "DISPLAY")}
  out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       timeout=120, cwd=ROOT, env=env)
  assert out.returncode == 0, out.stderr[-2000:]
  changed, jax_imported = out.stdout.rsplit(" ", 1)
  assert set(eval(changed)) <= {"MUJOCO_GL", "PYOPENGL_PLATFORM", "XLA_FLAGS",
                                "PYGAME_HIDE_SUPPORT_PROMPT"}, changed
  assert jax_imported.strip() == "False"


def test_train_and_benchmarks_install_under_the_projects_name(tmp_path):
  # Run outside the repository, so only the installed packages are importable: the
  # top-level folders must not install as `train` / `benchmarks` (they would shadow
  # a user's own modules of those names).
  out = subprocess.run(
      [sys.executable, "-c", "import importlib.util as u, dmcr_jax.train.loop, "
       "dmcr_jax.benchmarks.rows; print(u.find_spec('train'), u.find_spec('benchmarks'))"],
      capture_output=True, text=True, timeout=240, cwd=tmp_path,
      env=dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=""))
  assert out.returncode == 0, out.stderr[-2000:]
  assert out.stdout.split() == ["None", "None"]


@pytest.fixture(scope="module")
def run_without_checkpoint(tmp_path_factory):
  """A `train` folder with config.json (two agents) and no checkpoint yet."""
  from dmcr_jax.train import loop
  out = str(tmp_path_factory.mktemp("run"))
  loop.save_config(loop.TrainConfig(task="cartpole-balance", seeds=(0, 1), out_dir=out), out)
  return out


def assert_clean_error(code, stderr, prog, match):
  """Exit status 2 or 1, one error paragraph naming `match`, no traceback or noise."""
  assert code in (1, 2), stderr[-2000:]
  assert match in stderr, stderr[-2000:]
  assert f"{prog}: error:" in stderr
  for noise in ("Traceback", "Event loop is closed", "sys.meta_path", "warp"):
    assert noise not in stderr, stderr[-2000:]


def test_evaluate_without_a_checkpoint_fails_cleanly_and_exits(run_without_checkpoint):
  # It printed a FileNotFoundError inside 250-430 lines of noise and at times never exited.
  code, stdout, stderr = run(["-m", "dmcr_jax.train.evaluate", run_without_checkpoint], timeout=120)
  assert_clean_error(code, stderr, "dmcr-evaluate", "no checkpoint")
  assert stdout == ""
  assert not os.path.exists(os.path.join(run_without_checkpoint, "eval"))


def test_evaluate_refuses_agents_out_of_range(run_without_checkpoint):
  os.makedirs(os.path.join(run_without_checkpoint, "checkpoints", "5"), exist_ok=True)
  try:
    code, _, stderr = run(["-m", "dmcr_jax.train.evaluate", run_without_checkpoint, "--agents", "3"],
                          timeout=120)
  finally:
    os.rmdir(os.path.join(run_without_checkpoint, "checkpoints", "5"))
  assert_clean_error(code, stderr, "dmcr-evaluate", "agents must be indices in [0, 2)")


def test_train_refuses_bad_arguments_before_creating_the_folder(tmp_path):
  out = str(tmp_path / "run")
  for args, match in ((["--visual-seeds", "-1"], "visual_seeds -1: not a seed in"),
                      (["--resume"], "no run in")):
    code, _, stderr = run(["-m", "train", "--out", out, "--steps", "10"] + args, timeout=120)
    assert_clean_error(code, stderr, "dmcr-train", match)
    assert not os.path.exists(out)


def test_help_shows_defaults_and_choices():
  code, stdout, stderr = run(["-m", "train", "--help"], timeout=120)
  assert code == 0, stderr[-2000:]
  text = " ".join(stdout.split())
  for want in ("--steps STEPS training steps (transitions) per agent",
               "(default: 50000)", "(default: 0)", "(default: 10000)", "(default: 1000)",
               "--renderer {pool,jax}", "--quality {exact,fast,fastest}",
               "--dtype {float32,bfloat16}", "--agent-loop {vmap,map}"):
    assert want in text, want
  assert "warp" not in stdout
  code, stdout, stderr = run(["-m", "dmcr_jax.train.evaluate", "--help"], timeout=120)
  assert code == 0, stderr[-2000:]
  text = " ".join(stdout.split())
  for want in ("held-out looks per condition (default: 100)", "--renderer {pool,jax}",
               "(default: 3)"):
    assert want in text, want


@pytest.mark.slow
def test_train_imports_and_checks_your_augmentation_before_compiling(tmp_path):
  out = str(tmp_path / "run")
  (tmp_path / "my_augs.py").write_text(
      "import jax.numpy as jnp\n\n\ndef to_float(key, x):\n  return x.astype(jnp.float32)\n")
  path = os.pathsep.join(p for p in (os.environ.get("PYTHONPATH"), str(tmp_path)) if p)
  for aug, match in (("no_such_module:fn", "cannot import module 'no_such_module'"),
                     ("my_augs:missing", "has no attribute 'missing'; its functions: "
                                         "to_float"),
                     ("drq,my_augs:to_float+drq", "fails dmcr_jax.augment.check on real "
                                                  "observations 12×32×32×9 uint8: uint8")):
    code, _, stderr = run(["-m", "train", "--out", out, "--steps", "10", "--image-size",
                           "32", "--aug", aug], timeout=180, PYTHONPATH=path)
    assert_clean_error(code, stderr, "dmcr-train", match)
    assert not os.path.exists(out)


def test_train_takes_an_import_path_beside_the_builtins():
  from dmcr_jax.train.__main__ import parse
  cfg, _ = parse(["--task", "cartpole-balance", "--image-size", "32",
                  "--aug", "drq,cj+drq,examples.augmentations:hue_rotation+drq"])
  assert cfg.sac.aug_names == ("drq", "cj+drq", "examples.augmentations:hue_rotation+drq")
  assert cfg.out_dir == ("runs/cartpole-balance-drq_cj+drq_"
                         "examples.augmentations.hue_rotation+drq")
  assert [aug for _, aug in cfg.agents()] == list(cfg.sac.aug_names)
