"""`dmcr-sweep SPEC`: a grid of `dmcr-train` runs from a TOML spec, each evaluated and all
merged into one table, one run after another or as Ray tasks on a cluster.

A spec (TOML) names the grid and the options passed through::

    out = "runs/paper"                  # the sweep folder (default: runs/<spec name>)
    tasks = ["cartpole-balance", "walker-walk"]
    seeds = [0, 1, 2]                   # or "0,1,2"
    augs = ["drq", "cj+drq"]            # --aug values (default: dmcr-train's)
    looks = [0, "levels:10"]            # --visual-seeds values, one range each (default: [0])
    together = ["seeds"]                # axes trained as K agents of one run: seeds, augs

    [train]                             # dmcr-train options (flag names, dashes or not)
    steps = 50000
    num_envs = 16
    dtype = "bfloat16"

    [per_task.walker-walk]              # train options for one task (over [train])
    steps = 250000

    [evaluate]                          # dmcr-evaluate options (`EvalConfig` fields)
    visual_seeds = 100
    renderer = "pool"

`plan` expands it to runs (`Run`): one per task × look × each axis not in `together`
(an axis in `together` is one run's K agents), each in a stable folder under the
sweep folder named by the task, `dmcr-train`'s default name for the method, the
seeds and the looks (e.g. ``cartpole-balance-drq-s0-v0``, ``walker-walk-cj+drq-s0_1_2-levels10``).
Every run's command line is parsed by `dmcr-train`'s own parser and its evaluation
checked, so a bad spec (an unknown key, naming the valid ones; a bad value, as
dmcr-train says it) is refused before anything runs. A run is then in one of four
states (`Run.state`): "new"; "resume" (checkpoints below its steps: `dmcr-train
--resume` goes on from the newest); "evaluate" (trained, its `eval/eval.json`
missing, older than the checkpoint or of other evaluation options); "done"
(skipped). `run_one` brings a run to "done" (train, then `dmcr_jax.train.evaluate`,
which itself resumes an interrupted evaluation).

Backends: "local" runs the runs one after another in this process (runs of equal
shapes then share their compilations); "ray" submits each as a Ray task
(`ray.init(address=RAY_ADDRESS)`, a local instance when unset) holding one GPU when
the cluster has GPUs, else `[ray] cpus` CPUs (default 1); every node needs dmcr_jax
installed and the sweep folder on a shared filesystem. Finished, the eval.json of
every done run are merged into `<sweep>/table.md` (and `table.json`) by
`dmcr_jax.benchmarks.paper_table` (seeds trained apart pool into one row), one
table per training look; per task whose runs differ in training looks, the runs'
few-shot curve (`dmcr_jax.benchmarks.few_shot`: test return and E_G against the number
of training looks, mean and min–max over every seed) goes to
`<sweep>/few_shot_<task>.md`, `.json` and `.png`; per task whose runs were evaluated
during training (`--eval-every` in `[train]`) and differ in looks or augmentation, their
curves drawn together (`dmcr_jax.benchmarks.eval_curves`: held-out return against
training steps) go to `<sweep>/eval_curves_<task>.md`, `.json` and `.png`;
`<sweep>/runs.json` lists each run's folder and state.

    dmcr-sweep sweep.toml --dry-run     # the runs and what each still needs
    dmcr-sweep sweep.toml               # one after another, here
    dmcr-sweep sweep.toml --backend ray # RAY_ADDRESS=ray://head:10001 for a cluster
    dmcr-sweep sweep.toml --only 'walker-walk-*'   # only the runs of these names (`select`)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import os
import sys
import tomllib

KEYS = ("out", "tasks", "seeds", "augs", "looks", "together", "train", "per_task",
        "evaluate", "ray")
"""The top-level keys of a spec."""
TOGETHER = ("seeds", "augs")
"""The axes `together` may name."""
SWEEP_SET = ("task", "seeds", "aug", "visual_seeds", "out", "resume", "no_progress",
             "compile_cache", "no_compile_cache")
"""dmcr-train options the sweep sets itself (not allowed in [train])."""
RAY_KEYS = ("cpus",)
"""The keys of a spec's [ray] table."""
BACKENDS = ("local", "ray")
"""What `--backend` accepts."""


class SpecError(ValueError):
  """A sweep spec that cannot run, in one sentence naming the key."""


@dataclasses.dataclass(frozen=True)
class Run:
  """One run of a sweep.

  Attributes:
    name: its folder's name under the sweep folder.
    out_dir: its folder.
    task, look: its task and `--visual-seeds` value.
    train_argv: its `dmcr-train` arguments (without --resume).
    eval_options: its `dmcr_jax.train.evaluate.EvalConfig` fields.
    group: its W&B group (`--logger wandb`): the sweep folder's name, the method and
      the looks, so that seeds trained apart share one group.
  """
  name: str
  out_dir: str
  task: str
  look: str
  train_argv: tuple[str, ...]
  eval_options: tuple[tuple[str, object], ...]
  group: str = ""

  @property
  def eval_json(self) -> str:
    """Where its evaluation goes: `<out_dir>/eval/eval.json`."""
    return os.path.join(self.out_dir, "eval", "eval.json")

  def eval_config(self):
    """Its `EvalConfig`."""
    from dmcr_jax.train.evaluate import EvalConfig
    return EvalConfig(**dict(self.eval_options))

  def command(self) -> str:
    """Its `dmcr-train` and `dmcr-evaluate` command lines, for `--dry-run`."""
    import shlex
    ev = []
    for k, v in self.eval_options:
      if v is not None:
        ev += [f"--{k.replace('_', '-')}",
               ",".join(map(str, v)) if isinstance(v, (tuple, list)) else str(v)]
    return (shlex.join(["dmcr-train", *self.train_argv]) + " && "
            + shlex.join(["dmcr-evaluate", self.out_dir, *ev]))

  def state(self) -> str:
    """"new", "resume", "evaluate" or "done" (module doc)."""
    from dmcr_jax.train import checkpoint
    steps = checkpoint.steps(self.out_dir) if os.path.isdir(self.out_dir) else []
    if not steps:
      return "new"
    cfg = parse_train(self, resume=True)
    if steps[-1] < cfg.steps:
      return "resume"
    if not os.path.exists(self.eval_json):
      return "evaluate"
    with open(self.eval_json) as f:
      result = json.load(f)
    if (result.get("checkpoint_step") != steps[-1]
        or result.get("config") != json.loads(json.dumps(dataclasses.asdict(
            self.eval_config())))):
      return "evaluate"
    return "done"


def _names(value, key: str, kind=str) -> list:
  """A spec's list value (a list, or a comma-separated string for seeds)."""
  if isinstance(value, str) and kind is int:
    value = [v.strip() for v in value.split(",")]
  if not isinstance(value, list) or not value:
    raise SpecError(f"sweep spec: {key!r} must be a non-empty list, got {value!r}")
  if kind is int:
    try:
      value = [int(v) for v in value]
    except (TypeError, ValueError):
      raise SpecError(f"sweep spec: {key!r} takes ints (e.g. [0, 1, 2] or \"0,1,2\"), got "
                      f"{value!r}") from None
  if len(set(map(str, value))) != len(value):
    raise SpecError(f"sweep spec: {key!r} names a value twice: {value!r}")
  return value


def _flag(key: str) -> str:
  return key.replace("-", "_")


def train_options() -> dict[str, str]:
  """The `dmcr-train` options a spec's [train] may set: the flag's name with
  underscores (`num_envs`; each alias too) → the flag."""
  from dmcr_jax.train.__main__ import build_parser
  out = {}
  for action in build_parser()._actions:
    if action.option_strings and action.dest not in SWEEP_SET + ("help",):
      for flag in action.option_strings:
        out.setdefault(_flag(flag.lstrip("-")), action.option_strings[0])
  return out


def _argv(table: dict, where: str, valid: dict[str, str]) -> list[str]:
  """A [train] table as command-line arguments (lists joined by commas)."""
  argv = []
  for key, value in table.items():
    dest = _flag(key)
    if dest in SWEEP_SET:
      raise SpecError(f"sweep spec: {where} may not set {key!r}: the sweep sets it from "
                      "tasks, seeds, augs and looks (and the run's folder)")
    if dest not in valid:
      names = sorted({_flag(f.lstrip("-")) for f in valid.values()})
      raise SpecError(f"sweep spec: {where} has an unknown key {key!r}; valid: "
                      f"{', '.join(names)}")
    if isinstance(value, (dict, bool)):
      raise SpecError(f"sweep spec: {where}.{key} takes a number, a string or a list, got "
                      f"{value!r}")
    text = ",".join(map(str, value)) if isinstance(value, list) else str(value)
    argv += [valid[dest], text]
  return argv


def eval_options(table: dict) -> dict:
  """A spec's [evaluate] table as `EvalConfig` fields (lists as tuples)."""
  from dmcr_jax.train.evaluate import EvalConfig
  valid = [f.name for f in dataclasses.fields(EvalConfig)]
  out = {}
  for key, value in table.items():
    name = _flag(key)
    if name not in valid:
      raise SpecError(f"sweep spec: [evaluate] has an unknown key {key!r}; valid: "
                      f"{', '.join(valid)}")
    out[name] = tuple(value) if isinstance(value, list) else value
  return out


def parse_train(run: Run, resume: bool = False):
  """`dmcr-train`'s own parse of a run's arguments (its `TrainConfig`; with `resume`,
  the run folder's config with the arguments that may change applied).

  Raises:
    SpecError: what dmcr-train says is wrong, naming the run.
  """
  from dmcr_jax.train.__main__ import parse
  err = io.StringIO()
  try:
    with contextlib.redirect_stderr(err):
      cfg, _ = parse(list(run.train_argv) + (["--resume"] if resume else []))
  except SystemExit:
    lines = [l for l in err.getvalue().splitlines() if l.strip()]
    why = lines[-1].split("error: ", 1)[-1] if lines else "refused"
    raise SpecError(f"sweep spec: run {run.name}: {why}") from None
  return cfg


def load(path: str) -> dict:
  """The spec at `path` (TOML), checked for its keys (`SpecError` naming a bad one)."""
  try:
    with open(path, "rb") as f:
      spec = tomllib.load(f)
  except OSError as e:
    raise SpecError(f"sweep spec {path!r}: cannot read it ({e.strerror})") from None
  except tomllib.TOMLDecodeError as e:
    raise SpecError(f"sweep spec {path!r}: not valid TOML ({e})") from None
  bad = [k for k in spec if k not in KEYS]
  if bad:
    raise SpecError(f"sweep spec {path!r}: unknown key {bad[0]!r}; valid: {', '.join(KEYS)}")
  return spec


def _look_part(look) -> str:
  text = str(look)
  return text.replace("levels:", "levels").replace(",", "_") if "levels" in text else f"v{text}"


def plan(spec: dict, default_out: str) -> tuple[str, list[Run]]:
  """The sweep folder and its runs (module doc), every run's arguments checked by
  dmcr-train's parser and its evaluation options by `check_eval_config`.

  Args:
    spec: a loaded spec (`load`).
    default_out: the sweep folder when the spec names none.

  Raises:
    SpecError: naming the key (and the valid choices) or the run that is refused.
  """
  from dmcr_jax.train.__main__ import default_out as method_name
  from dmcr_jax.train.config import parse_visual_seeds
  from dmcr_jax.train.evaluate import EvalConfig, check_eval_config
  if "tasks" not in spec:
    raise SpecError("sweep spec: 'tasks' is missing (a list of tasks, e.g. "
                    "[\"cartpole-balance\"])")
  out = str(spec.get("out", default_out))
  tasks = _names(spec["tasks"], "tasks")
  seeds = _names(spec.get("seeds", [0]), "seeds", int)
  augs = _names(spec["augs"], "augs") if "augs" in spec else [None]
  looks = _names(spec.get("looks", [0]), "looks")
  together = _names(spec.get("together", ["none"]), "together")
  together = [] if together == ["none"] else together
  for axis in together:
    if axis not in TOGETHER:
      raise SpecError(f"sweep spec: 'together' names {axis!r}; valid: {', '.join(TOGETHER)}")
  for look in looks:
    try:
      ranges = parse_visual_seeds(look)
    except ValueError as e:
      raise SpecError(f"sweep spec: looks {look!r}: {e}") from None
    if len(ranges) > 1:
      raise SpecError(f"sweep spec: looks {look!r} names several ranges; give each as its "
                      f"own item, e.g. {[f'levels:{len(r)}' for r in ranges]!r}")
  for name in ("train", "per_task", "evaluate", "ray"):
    if not isinstance(spec.get(name, {}), dict):
      raise SpecError(f"sweep spec: {name!r} must be a table ([{name}])")
  unknown = [t for t in spec.get("per_task", {}) if t not in tasks]
  if unknown:
    raise SpecError(f"sweep spec: [per_task] names {unknown[0]!r}, not one of tasks: "
                    f"{', '.join(tasks)}")
  bad = [k for k in spec.get("ray", {}) if k not in RAY_KEYS]
  if bad:
    raise SpecError(f"sweep spec: [ray] has an unknown key {bad[0]!r}; valid: "
                    f"{', '.join(RAY_KEYS)}")
  valid = train_options()
  base = _argv(spec.get("train", {}), "[train]", valid)
  ev = eval_options(spec.get("evaluate", {}))
  try:
    eval_cfg = EvalConfig(**ev)
  except TypeError as e:
    raise SpecError(f"sweep spec: [evaluate]: {e}") from None
  seed_groups = [seeds] if "seeds" in together else [[s] for s in seeds]
  aug_groups = [augs] if "augs" in together else [[a] for a in augs]
  runs = []
  for task in tasks:
    extra = _argv(spec.get("per_task", {}).get(task, {}), f"[per_task.{task}]", valid)
    try:
      check_eval_config(eval_cfg, task)
    except ValueError as e:
      raise SpecError(f"sweep spec: [evaluate] for {task}: {e}") from None
    for look in looks:
      for aug_group in aug_groups:
        for seed_group in seed_groups:
          argv = ["--task", task, "--seeds", ",".join(map(str, seed_group)),
                  "--visual-seeds", str(look), *base, *extra]
          if aug_group != [None]:
            argv += ["--aug", ",".join(aug_group)]
          draft = Run(name=task, out_dir=out, task=task, look=str(look),
                      train_argv=tuple(argv), eval_options=())
          cfg = parse_train(draft)
          method = os.path.basename(method_name(task, cfg.sac))
          name = (f"{method}-s{'_'.join(map(str, seed_group))}-{_look_part(look)}")
          folder = os.path.join(out, name)
          runs.append(Run(name=name, out_dir=folder, task=task, look=str(look),
                          train_argv=tuple(argv + ["--out", folder]),
                          eval_options=tuple(sorted(ev.items())),
                          group=f"{os.path.basename(os.path.abspath(out))}/{method}-"
                                f"{_look_part(look)}"))
  if len({r.name for r in runs}) != len(runs):
    raise SpecError("sweep spec: two runs share a folder name; make tasks, seeds, augs "
                    "and looks distinct")
  for run in runs:
    if os.path.exists(os.path.join(run.out_dir, "config.json")):
      parse_train(run, resume=True)  # a changed setting of an existing run is refused
  return out, runs


def run_one(run: Run, progress: bool = False) -> dict:
  """Trains (or resumes) and evaluates `run` as far as it still needs (`Run.state`);
  {"name", "state" (before), "eval_json" (None when interrupted), "interrupted"}."""
  from dmcr_jax.train import evaluate
  from dmcr_jax.train.__main__ import parse
  from dmcr_jax.train.loop import train
  state = run.state()
  result = dict(name=run.name, state=state, eval_json=None, interrupted=False)
  if state in ("new", "resume"):
    resume = state == "resume"
    argv = list(run.train_argv) + (["--resume"] if resume else [])
    _, args = parse(argv)
    group = {"WANDB_RUN_GROUP": run.group} if "WANDB_RUN_GROUP" not in os.environ else {}
    os.environ.update(group)
    try:
      summary = train(args.plan, resume=resume, progress=progress)
    finally:
      for key in group:
        os.environ.pop(key, None)
    if summary["interrupted"]:
      return dict(result, interrupted=True)
  if state != "done":
    evaluate.evaluate(run.out_dir, run.eval_config(), progress=progress)
  return dict(result, eval_json=run.eval_json)


def merge(out: str, runs: list[Run]) -> str | None:
  """`<out>/table.md` and `table.json` from the done runs' eval.json, through
  `dmcr_jax.benchmarks.paper_table` (`collect`, `merge`, `markdown`), one table per
  training look; the Markdown (None when no run is done)."""
  from dmcr_jax.benchmarks import paper_table
  by_look: dict[str, list[str]] = {}
  for run in runs:
    if os.path.exists(run.eval_json):
      by_look.setdefault(run.look, []).append(run.eval_json)
  if not by_look:
    return None
  parts, data = [], {}
  for look, paths in by_look.items():
    collected = paper_table.collect(paths)
    rows = paper_table.merge(collected)
    table = paper_table.markdown(collected)
    parts.append(table if len(by_look) == 1 else f"## Trained on visual seeds {look}\n\n{table}")
    data[look] = dict(rows=rows, runs=collected, missing=paper_table.missing(rows))
  text = "\n".join(parts)
  with open(os.path.join(out, "table.md"), "w") as f:
    f.write(text)
  with open(os.path.join(out, "table.json"), "w") as f:
    json.dump(data, f, indent=1)
  return text


def few_shot_tasks(runs: list[Run]) -> dict[str, list[str]]:
  """{task: its looks} of each task whose runs differ in training looks: the tasks
  whose few-shot curve `few_shot_curves` draws."""
  looks: dict[str, list[str]] = {}
  for run in runs:
    looks.setdefault(run.task, [])
    if run.look not in looks[run.task]:
      looks[run.task].append(run.look)
  return {task: ls for task, ls in looks.items() if len(ls) > 1}


def few_shot_curves(out: str, runs: list[Run]) -> list[str]:
  """`<out>/few_shot_<task>.md`, `.json` and `.png` for each task of `few_shot_tasks`
  from its evaluated runs' eval.json (`dmcr_jax.benchmarks.few_shot.curves`: one
  curve over every range, augmentation and seed); the Markdown paths written. A
  task whose evaluations cannot merge is reported on stderr and skipped."""
  from dmcr_jax.benchmarks import few_shot
  written = []
  for task in few_shot_tasks(runs):
    paths = [r.eval_json for r in runs if r.task == task and os.path.exists(r.eval_json)]
    try:
      drawn = few_shot.curves(paths, out)
    except ValueError as e:
      print(f"sweep: few-shot curve of {task} not drawn: {e}", file=sys.stderr, flush=True)
      continue
    written += [os.path.join(out, f"few_shot_{t}.md") for t in drawn]
  return written


def eval_curves(out: str, runs: list[Run]) -> list[str]:
  """`<out>/eval_curves_<task>.md`, `.json` and `.png` from the runs that hold an
  eval_curve.csv (`dmcr_jax.benchmarks.eval_curves.curves`), task by task; the
  Markdown paths written. A task whose runs' curves cannot be drawn together is
  reported on stderr and skipped."""
  from dmcr_jax.benchmarks import eval_curves as curves_of_runs
  from dmcr_jax.train import eval_curve
  written = []
  for task in dict.fromkeys(r.task for r in runs):
    with_curves = [r.out_dir for r in runs if r.task == task
                   and os.path.exists(os.path.join(r.out_dir, eval_curve.CSV))]
    if not with_curves:
      continue
    try:
      drawn = curves_of_runs.curves(with_curves, out)
    except ValueError as e:
      print(f"sweep: eval curves of {task} not drawn together: {e}", file=sys.stderr,
            flush=True)
      continue
    written += [os.path.join(out, f"eval_curves_{t}.md") for t in drawn]
  return written


def _run_with_cache(run: Run, cache: str | None, off: bool) -> dict:
  """`run_one` in a Ray worker, with the sweep's compilation cache: `--compile-cache`
  as given (None: the node's own default folder, `compile_cache.default_dir`), or
  none with `off`."""
  from dmcr_jax.train import compile_cache
  compile_cache.use(compile_cache.chosen(argparse.Namespace(compile_cache=cache,
                                                            no_compile_cache=off)))
  return run_one(run)


def _ray_results(runs: list[Run], cpus: int, cache: tuple | None = None):
  """Each run as a Ray task (module doc); yields `run_one`'s results as they end (an
  exception's text as "error"). `cache`: (`--compile-cache`, `--no-compile-cache`)
  as given, applied in each task (`_run_with_cache`); None: the tasks' processes
  keep the compilation cache they have."""
  import ray
  if not ray.is_initialized():
    ray.init(address=os.environ.get("RAY_ADDRESS") or None, log_to_driver=False)
  gpus = 1 if ray.cluster_resources().get("GPU", 0) >= 1 else 0
  task = ray.remote(num_gpus=gpus, num_cpus=0 if gpus else cpus, max_retries=0)(
      run_one if cache is None else _run_with_cache)
  print(f"sweep: {len(runs)} Ray tasks, each holding "
        + ("one GPU" if gpus else f"{cpus} CPU{'s' if cpus > 1 else ''}"),
        file=sys.stderr, flush=True)
  pending = {task.remote(r, *(cache or ())): r for r in runs}
  while pending:
    done, _ = ray.wait(list(pending), num_returns=1)
    run = pending.pop(done[0])
    try:
      yield ray.get(done[0])
    except Exception as e:  # noqa: BLE001 - a failed run is reported, the others go on
      yield dict(name=run.name, error=f"{type(e).__name__}: {str(e).splitlines()[0]}")


def _local_results(runs: list[Run]):
  """The runs one after another here; stops after an interrupted one."""
  for run in runs:
    try:
      result = run_one(run)
    except (ValueError, FileExistsError, FileNotFoundError) as e:
      result = dict(name=run.name, error=f"{type(e).__name__}: {e}")
    yield result
    if result.get("interrupted"):
      return


def select(runs: list[Run], patterns: str) -> set[str]:
  """The names of `runs` that match one of `patterns` (comma-separated shell patterns,
  e.g. "cartpole-balance-*-levels10000,*cj+drq*"); SpecError for a pattern that
  matches none, naming the runs."""
  import fnmatch
  names, chosen = [r.name for r in runs], set()
  for pattern in (p.strip() for p in patterns.split(",")):
    hits = fnmatch.filter(names, pattern)
    if not hits:
      raise SpecError(f"--only {pattern!r} matches none of the spec's runs: "
                      f"{', '.join(names)}")
    chosen.update(hits)
  return chosen


def sweep(out: str, runs: list[Run], backend: str = "local", cpus: int = 1,
          cache: tuple | None = None, only: set[str] | None = None) -> dict:
  """Brings every run (those named in `only`, when given) to "done" (`run_one`;
  "done" ones are skipped), then merges the evaluations of all done runs (`merge`)
  and draws the few-shot curves (`few_shot_curves`) and the runs' eval curves
  (`eval_curves`); {"runs": each result, "table": the Markdown or None, "few_shot"
  and "eval_curves": the curves' Markdown paths}. `<out>/runs.json`
  records them. `cache`: (`--compile-cache`, `--no-compile-cache`) as given, which
  each Ray task applies on its node (None: the tasks keep their processes' cache;
  local runs use this process's, which `main` sets)."""
  os.makedirs(out, exist_ok=True)
  states = {r.name: r.state() for r in runs}
  todo = [r for r in runs if states[r.name] != "done" and (only is None or r.name in only)]
  results = {}
  for r in runs:
    if states[r.name] == "done":
      print(f"sweep: {r.name}: done, skipped", file=sys.stderr, flush=True)
      results[r.name] = dict(name=r.name, state="done", eval_json=r.eval_json)
    elif r not in todo:
      print(f"sweep: {r.name}: {states[r.name]}, not in --only", file=sys.stderr, flush=True)
      results[r.name] = dict(name=r.name, state=states[r.name])
  stream = _ray_results(todo, cpus, cache) if backend == "ray" else _local_results(todo)
  for result in stream:
    results[result["name"]] = result
    what = ("failed: " + result["error"] if "error" in result else
            "interrupted" if result.get("interrupted") else "done")
    print(f"sweep: {result['name']}: {what}", file=sys.stderr, flush=True)
  table = merge(out, runs)
  curves = few_shot_curves(out, runs)
  during = eval_curves(out, runs)
  listing = [dict(name=r.name, out_dir=r.out_dir, **{k: v for k, v in
                                                     results.get(r.name, {}).items()
                                                     if k != "name"}) for r in runs]
  with open(os.path.join(out, "runs.json"), "w") as f:
    json.dump(listing, f, indent=1)
  return dict(runs=listing, table=table, few_shot=curves, eval_curves=during)


def main(argv=None) -> None:
  """`dmcr-sweep SPEC [--backend local|ray] [--dry-run] [--only PATTERNS] [--out DIR]
  [--compile-cache DIR | --no-compile-cache]` (module doc; the cache:
  `dmcr_jax.train.compile_cache`); exit status 1 when a run failed or was interrupted."""
  from dmcr_jax.train import compile_cache
  p = argparse.ArgumentParser(prog="dmcr-sweep", description=__doc__.splitlines()[0])
  p.add_argument("spec", help="the sweep's TOML spec")
  p.add_argument("--backend", default="local", choices=BACKENDS,
                 help="local: the runs one after another in this process; ray: each run "
                      "a Ray task (RAY_ADDRESS, else a local instance), holding one GPU "
                      "when the cluster has GPUs")
  p.add_argument("--ray", dest="backend", action="store_const", const="ray",
                 help="the same as --backend ray")
  p.add_argument("--out", default=None,
                 help="the sweep folder (default: the spec's out, else runs/<spec name>)")
  p.add_argument("--dry-run", action="store_true",
                 help="print the runs, their state and commands, and run nothing")
  p.add_argument("--only", default=None, metavar="PATTERNS",
                 help="run only the runs whose names match one of these comma-separated "
                      "shell patterns (e.g. 'cartpole-balance-*-levels10000'); the merged "
                      "table still holds every done run")
  compile_cache.add_arguments(p)
  a = p.parse_args(argv)
  try:
    if a.backend == "ray":
      import importlib.util
      if importlib.util.find_spec("ray") is None:
        raise SpecError("--backend ray needs the ray package, which is not installed: "
                        "pip install 'dmcr-jax[ray]'")
    spec = load(a.spec)
    if a.out:
      spec["out"] = a.out
    out, runs = plan(spec, os.path.join("runs", os.path.splitext(os.path.basename(a.spec))[0]))
    cpus = spec.get("ray", {}).get("cpus", 1)
    if isinstance(cpus, bool) or not isinstance(cpus, int) or cpus < 1:
      raise SpecError(f"sweep spec: [ray] cpus must be a positive int, got {cpus!r}")
    only = None if a.only is None else select(runs, a.only)
  except SpecError as e:
    p.error(str(e))
  if a.dry_run:
    for run in runs:
      if only is None or run.name in only:
        print(f"{run.name} [{run.state()}]: {run.command()}")
    for task, looks in few_shot_tasks(runs).items():
      print(f"few-shot curve of {task} over looks {', '.join(looks)}: "
            f"{os.path.join(out, f'few_shot_{task}')}.md, .json and .png, once its runs "
            "are evaluated")
    for task in dict.fromkeys(r.task for r in runs):
      evaluated = [r for r in runs if r.task == task and parse_train(r).eval_every]
      if len(evaluated) > 1:
        print(f"eval curves of {task}'s {len(evaluated)} runs evaluated during training: "
              f"{os.path.join(out, f'eval_curves_{task}')}.md, .json and .png, when the sweep ends")
    print(f"{len(runs)} runs in {out}" if only is None else
          f"{len(only)} of {len(runs)} runs in {out} (--only)")
    return
  compile_cache.use(compile_cache.chosen(a))
  result = sweep(out, runs, a.backend, cpus, (a.compile_cache, a.no_compile_cache), only)
  if result["table"]:
    print(result["table"], end="")
    print(f"wrote {os.path.join(out, 'table.md')} and table.json")
  for path in result["few_shot"] + result["eval_curves"]:
    print(f"wrote {os.path.splitext(path)[0]}.md, .json and .png")
  bad = [r["name"] for r in result["runs"] if "error" in r or r.get("interrupted")]
  if bad:
    sys.exit(f"sweep: {len(bad)} run{'s' if len(bad) > 1 else ''} not done: {', '.join(bad)}"
             f"; run dmcr-sweep {a.spec} again to go on")


if __name__ == "__main__":
  main()
