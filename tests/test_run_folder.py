"""A training run's folder: one run per folder (a lock two processes contend for),
damaged checkpoints and unusable folders refused with a paragraph, a damaged newest
checkpoint resumed from the one before, a finished run's resume ending at once."""

import csv
import dataclasses
import os
import shutil
import subprocess
import sys
import tempfile
import time

import pytest

from dmcr_jax.train import checkpoint, loop, runlog

# test_train's group: the tiny run is its drivers' test run (the demo's sizes).
pytestmark = pytest.mark.xdist_group("train")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def tiny_config(out, **changes) -> loop.TrainConfig:
  """The demo's tiny run (pendulum, 2 envs, the ray caster's device driver), 48
  steps in two chunks, checkpoints at 24 and 48."""
  from tests.test_train import demo_run
  return demo_run(out, steps=48, chunk_steps=12, checkpoint_every=24, **changes)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
  """A finished tiny run's folder (checkpoints 24 and 48); copy it to change it."""
  cfg = tiny_config(tmp_path_factory.mktemp("tiny") / "run")
  loop.train(cfg, progress=False)
  assert checkpoint.steps(cfg.out_dir) == [24, 48]
  return cfg.out_dir


def copy_of(run: str, tmp_path) -> str:
  out = str(tmp_path / "run")
  shutil.copytree(run, out)
  return out


def largest_file(out: str, step: int) -> str:
  """The largest file of checkpoint `step` (one holding array data)."""
  path = os.path.join(checkpoint.folder(out), str(step))
  files = [os.path.join(r, f) for r, _, fs in os.walk(path) for f in fs
           if f != checkpoint.DIGEST]
  return max(files, key=os.path.getsize)


def truncate(path: str) -> None:
  with open(path, "r+b") as f:
    f.truncate(os.path.getsize(path) // 2)


def flip_a_bit(path: str) -> None:
  with open(path, "r+b") as f:
    f.seek(os.path.getsize(path) // 2)
    byte = f.read(1)
    f.seek(-1, os.SEEK_CUR)
    f.write(bytes([byte[0] ^ 0x10]))


@pytest.mark.slow
@pytest.mark.parametrize("damage, why", [(truncate, "truncated"),
                                         (flip_a_bit, "its contents differ from those saved")])
def test_a_damaged_checkpoint_is_refused_with_a_paragraph(tiny_run, tmp_path, damage, why):
  # A truncated data file loaded silently (orbax read what was left); others gave a
  # 260-line orbax/tensorstore traceback.
  out = copy_of(tiny_run, tmp_path)
  path = largest_file(out, 48)
  damage(path)
  with pytest.raises(checkpoint.DamagedCheckpointError) as e:
    loop.load_run(out)
  text = str(e.value)
  assert f"checkpoint step 48 in {checkpoint.folder(out)}/48 is damaged: {path}" in text
  assert why in text and "\n" not in text
  assert f"dmcr-train --resume --out {out}" in text and "step=24" in text
  assert loop.load_run(out, step=24)[2] == 24   # the one before is intact


@pytest.mark.slow
def test_resume_falls_back_to_the_checkpoint_before_a_damaged_one(tiny_run, tmp_path,
                                                                 capfd):
  out = copy_of(tiny_run, tmp_path)
  flip_a_bit(largest_file(out, 48))
  summary = loop.train(tiny_config(out), resume=True, progress=False)
  err = capfd.readouterr().err
  assert "checkpoint step 48" in err and "is damaged" in err
  assert f"moved it to {os.path.join(out, 'damaged', '48')}, resuming from the checkpoint " \
         "before it" in err
  assert summary["steps"] == 48 and checkpoint.steps(out) == [24, 48]
  assert checkpoint.damage(out, 48) is None   # written again, intact
  # The segments: the first process up to the checkpoint resumed from, then this one.
  assert [(s["start"], s["steps"]) for s in summary["segments"]] == [(0, 24), (24, 48)]
  with open(os.path.join(out, "log.csv")) as f:
    steps = [int(r["step"]) for r in csv.DictReader(f)]
  assert steps == sorted(steps)


@pytest.mark.slow
def test_resuming_a_finished_run_says_so_and_builds_nothing(tiny_run, tmp_path, capsys,
                                                           monkeypatch):
  # It started up for 12 s and appended an empty segment.
  import dmcr_jax.train.__main__ as cli
  out = copy_of(tiny_run, tmp_path)
  before = runlog.read_json(os.path.join(out, "summary.json"))

  def no_env(*args, **kwargs):
    raise AssertionError("an env was built")
  monkeypatch.setattr(loop, "make_env", no_env)
  cli.main(["--out", out, "--resume"])   # exit status 0: no SystemExit
  captured = capsys.readouterr()
  assert (f"train: the run in {out} is finished: its checkpoint is at step 48 (steps 48); "
          "pass a larger --steps to extend it") in captured.err
  assert '"steps": 48' in captured.out
  assert runlog.read_json(os.path.join(out, "summary.json")) == before


def test_a_running_run_holds_its_folder_against_a_second_process(tmp_path):
  # Two `train` processes with the same --out both finished, leaving a folder that
  # mixed them. Here one process holds the folder; a second `train` (a resume of
  # the run in it) is refused, naming the holder; once the holder is killed, its
  # stale lock is taken over.
  out = str(tmp_path / "run")
  cfg = tiny_config(out)
  os.makedirs(out)
  loop.save_config(cfg, out)
  os.makedirs(os.path.join(checkpoint.folder(out), "24"))   # "a checkpoint"
  holder = subprocess.Popen(
      [sys.executable, "-c", "import sys, time; from dmcr_jax.train import checkpoint; "
       f"checkpoint.RunLock({out!r}).acquire(); print('held', flush=True); time.sleep(600)"],
      stdout=subprocess.PIPE, text=True, cwd=ROOT)
  try:
    assert holder.stdout.readline().strip() == "held"
    with open(os.path.join(out, "config.json")) as f:
      config_text = f.read()
    t = time.perf_counter()
    second = subprocess.run([sys.executable, "-m", "dmcr_jax.train", "--out", out, "--resume",
                             "--no-progress"], capture_output=True, text=True, timeout=240,
                            cwd=ROOT, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert second.returncode == 1, second.stderr[-2000:]
    assert f"train: error: {out!r} belongs to a training process that is still running " \
           f"(pid {holder.pid} on " in second.stderr
    assert "Traceback" not in second.stderr and "compiling" not in second.stderr
    assert time.perf_counter() - t < 120
    with open(os.path.join(out, "config.json")) as f:
      assert f.read() == config_text
    # In this process too, a fresh run into the folder is refused before anything.
    with pytest.raises(checkpoint.RunLockedError, match=f"pid {holder.pid}"):
      loop.open_run(dataclasses.replace(cfg, out_dir=str(tmp_path / "run")), resume=True)
  finally:
    holder.kill()
    holder.wait(timeout=60)
  with checkpoint.RunLock(out) as lock:   # the dead process's lock: taken over
    with open(lock.path) as f:
      assert f'"pid": {os.getpid()}' in f.read()


def test_an_out_that_is_a_file_or_not_writable_fails_before_anything(tmp_path):
  # A file gave "[Errno 17] File exists", a read-only folder a raw PermissionError.
  path = tmp_path / "a_file"
  path.write_text("mine")
  cfg = tiny_config(path)
  with pytest.raises(checkpoint.RunFolderError, match="is a file, not a folder"):
    loop.train(cfg, progress=False)
  with pytest.raises(checkpoint.RunFolderError, match="cannot be created: .* is a file"):
    loop.train(dataclasses.replace(cfg, out_dir=str(path / "run")), progress=False)
  assert path.read_text() == "mine"
  # A folder this process may not write in (as root, which writes anywhere, checked
  # as an ordinary user: a world-readable folder outside pytest's private ones).
  base = tempfile.mkdtemp()
  ro = os.path.join(base, "read_only")
  os.mkdir(ro)
  os.chmod(base, 0o755)
  os.chmod(ro, 0o555)
  root = os.geteuid() == 0
  try:
    if root:
      os.seteuid(65534)
    for out in (os.path.join(ro, "run"), ro):
      with pytest.raises(checkpoint.RunFolderError, match="may not write in"):
        checkpoint.check_out_dir(out)
  finally:
    if root:
      os.seteuid(0)
    assert os.listdir(ro) == []
    shutil.rmtree(base)


def test_cli_names_an_out_that_is_a_file_in_one_paragraph(tmp_path):
  from tests.test_cli import assert_clean_error, run
  path = tmp_path / "a_file"
  path.write_text("mine")
  code, _, stderr = run(["-m", "train", "--out", str(path), "--steps", "10"], timeout=120)
  assert_clean_error(code, stderr, "train", "is a file, not a folder")
  assert path.read_text() == "mine"
