"""The CLIs' persistent compilation cache (`--compile-cache DIR`, `--no-compile-cache`):
its default folder, JAX's config set from the flags (an executable then lands in the
folder), the physics workers handed the same settings, and the benchmarks and the
library left without it."""

import glob
import os

import jax
import pytest

from dmcr_jax import physics_pool
from dmcr_jax.train import compile_cache as cc
from dmcr_jax.train.__main__ import build_parser

SETTINGS = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
            "jax_compilation_cache_max_size")


@pytest.fixture
def jax_cache_config():
  """Restores JAX's cache settings (the session's, conftest) after a test."""
  from jax.experimental.compilation_cache import compilation_cache
  saved = {name: getattr(jax.config, name) for name in SETTINGS}
  yield
  for name, value in saved.items():
    jax.config.update(name, value)
  compilation_cache.reset_cache()


def test_the_default_folder_is_jaxs_variable_else_the_xdg_cache(tmp_path):
  home = os.path.expanduser("~")
  assert cc.default_dir({}) == os.path.join(home, ".cache", "dmcr_jax", "xla")
  assert cc.default_dir({"XDG_CACHE_HOME": "/x"}) == "/x/dmcr_jax/xla"
  assert cc.default_dir({"XDG_CACHE_HOME": "/x", cc.ENV: "/j"}) == "/j"
  parse = build_parser().parse_args
  assert cc.chosen(parse([]), {"XDG_CACHE_HOME": "/x"}) == "/x/dmcr_jax/xla"
  assert cc.chosen(parse(["--compile-cache", str(tmp_path)]), {cc.ENV: "/j"}) == str(tmp_path)
  assert cc.chosen(parse(["--no-compile-cache"]), {cc.ENV: "/j"}) is None


@pytest.mark.parametrize("module", ["dmcr_jax.train.evaluate", "dmcr_jax.train.sweep"])
def test_evaluate_and_sweep_take_the_same_options(module, capsys):
  import importlib
  with pytest.raises(SystemExit):
    importlib.import_module(module).main(["--help"])
  out = capsys.readouterr().out
  assert "--compile-cache DIR" in out and "--no-compile-cache" in out


def test_one_or_the_other(capsys):
  with pytest.raises(SystemExit):
    build_parser().parse_args(["--compile-cache", "/x", "--no-compile-cache"])
  assert "not allowed with argument" in capsys.readouterr().err


def test_the_flag_sets_jaxs_cache_and_an_executable_lands_in_it(tmp_path, jax_cache_config):
  folder = str(tmp_path / "xla")
  environ = {}
  jax.jit(lambda x: x - 1)(1.0)  # JAX's cache is open (the session's folder): `use` moves it
  assert cc.use(cc.chosen(build_parser().parse_args(["--compile-cache", folder])),
                environ) == folder
  assert jax.config.jax_compilation_cache_dir == folder and os.path.isdir(folder)
  assert jax.config.jax_persistent_cache_min_compile_time_secs == cc.MIN_COMPILE_TIME_S
  assert jax.config.jax_compilation_cache_max_size == cc.MAX_SIZE_BYTES == 10 * 2**30
  assert environ == {cc.ENV: folder, "JAX_COMPILATION_CACHE_MAX_SIZE": str(cc.MAX_SIZE_BYTES),
                     "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "1.0"}
  # The physics workers get this folder and its settings.
  assert physics_pool._user_cache_dir() == folder
  assert physics_pool._cache_env(folder) == environ
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # cache a tiny one
  jax.jit(lambda x: x * 3 + 17)(jax.numpy.arange(5.0)).block_until_ready()
  assert glob.glob(os.path.join(folder, "*-cache"))


def test_no_compile_cache_sets_none_and_hands_none_on(jax_cache_config):
  environ = {cc.ENV: "/j"}
  assert cc.use(cc.chosen(build_parser().parse_args(["--no-compile-cache"])), environ) is None
  assert jax.config.jax_compilation_cache_dir is None and cc.ENV not in environ


def test_the_users_jax_folder_keeps_jaxs_own_settings(tmp_path, jax_cache_config):
  jax.config.update("jax_compilation_cache_max_size", -1)
  environ = {cc.ENV: str(tmp_path)}
  cc.use(cc.chosen(build_parser().parse_args([]), environ), environ)
  assert jax.config.jax_compilation_cache_dir == str(tmp_path)
  assert jax.config.jax_compilation_cache_max_size == -1 and environ == {cc.ENV: str(tmp_path)}


def test_a_sweep_spec_may_not_set_the_cache_and_the_benchmarks_never_use_it():
  from dmcr_jax.train import sweep
  assert "compile_cache" not in sweep.train_options()
  # The benchmarks time compilation from empty: none sets the cache or runs a CLI's
  # `main` (`benchmarks/training.py` takes dmcr-train's `parse` alone).
  import re
  import dmcr_jax.benchmarks as benchmarks
  folder = os.path.dirname(benchmarks.__file__)
  for path in glob.glob(os.path.join(folder, "*.py")):
    with open(path) as f:
      text = f.read()
    assert "compile_cache" not in text, path
    assert not re.search(r"\b(train_cli|evaluate|tev|sweep|__main__)\.main\(", text), path


def test_each_ray_task_of_a_sweep_sets_the_sweeps_cache_on_its_node(tmp_path, monkeypatch,
                                                                    jax_cache_config):
  from dmcr_jax.train import sweep
  for variable in (cc.ENV, "JAX_COMPILATION_CACHE_MAX_SIZE",
                   "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"):
    value = os.environ.get(variable)
    monkeypatch.setenv(variable, "restored after")  # the variable restored as it is now
    monkeypatch.delenv(variable) if value is None else monkeypatch.setenv(variable, value)
  seen = []
  monkeypatch.setattr(sweep, "run_one", lambda run: seen.append(
      (run, jax.config.jax_compilation_cache_dir)) or {})
  sweep._run_with_cache("run", str(tmp_path), False)
  sweep._run_with_cache("run", None, True)
  assert seen == [("run", str(tmp_path)), ("run", None)]
