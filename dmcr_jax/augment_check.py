"""An augmentation checker: the properties the SAC+AUG learner relies on.

Like gymnasium's env checker, `check(aug)` runs an augmentation on real
observations and names each property it breaks. The learner (`dmcr_jax.train.losses.
augment_and_mix`) calls ``aug(key, (obs, next_obs))`` on uint8 batches
(B, H, W, 3·stack) inside `jax.jit`, under `jax.vmap` over agents; the
appendix asks for one draw per sample, shared by the frames of its stack and by
its o and o′. The properties, in order (`PROPERTIES`):

- ``runs``: ``aug(key, obs)`` returns without raising;
- ``uint8``: every output array is uint8;
- ``shape``: the output has the input's structure and shapes;
- ``nan``: no NaN reaches a conversion to uint8 (where it silently becomes some
  backend-dependent byte);
- ``range``: every value converted to uint8 lies in 0…255, and no uint8
  addition, subtraction or multiplication overflows (no wrap-around: clip first);
- ``deterministic``: two eager evaluations with the same key are bit-identical
  (no NumPy randomness or other Python state);
- ``jit``: ``jax.jit(aug)`` gives the eager result;
- ``vmap``: under ``jax.vmap`` over agents it gives one call per agent's result,
  and (an `Augmentation`) the batch gives ``aug.one`` of every sample with its key;
- ``frames``: a stack of identical frames stays identical (one draw per sample,
  shared by the frames of its stack);
- ``alignment``: output frame f depends on input frame f only (frames are neither
  reordered nor mixed): it equals frame f of the stack that repeats input frame f;
- ``pair``: ``aug(key, (obs, next_obs))`` equals ``(aug(key, obs), aug(key,
  next_obs))``: a sample's o and o′ share the draw.

``nan`` and ``range`` evaluate the traced program operation by operation and
look at the inputs of every conversion to uint8 (also inside nested `jit`s,
custom derivatives and the taken branch of `lax.cond`; not inside loops).
A property whose prerequisite failed is skipped (``deterministic`` before the
comparisons, ``shape`` before the frame checks, ``frames`` before ``alignment``).

The observations (`observations`): dm_control states of a few tasks
(`CHECK_TASKS`, random actions, the paper's action repeat) drawn by MuJoCo's
renderer with DMCR looks (visual seed 0, dm_control's, and three random ones),
four consecutive frames per look: obs stacks frames 0–2, next_obs frames 1–3.
Rendered once per image size (a few seconds, EGL or OSMesa) and cached in
``<dmcr_jax.visuals.cache_dir()>/augment_check``.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax._files import write_atomic
from dmcr_jax.augment_core import Augmentation, _check_images, sample_keys
from dmcr_jax.augment_registry import from_function, get

CHECK_TASKS: tuple[str, ...] = ("cartpole-balance", "walker-walk", "finger-spin")
"""Tasks whose renders `check` uses: a dark and two bright scenes, thin and wide bodies."""

CHECK_LOOKS: tuple[int, ...] = (0, 3, 11, 42)
"""Visual seeds rendered per task (0 is dm_control's look)."""

STACK = 3
"""Frames per observation (`dmcr_jax.train.loop.TrainConfig.frame_stack`'s default)."""

PROPERTIES: tuple[tuple[str, str], ...] = (
    ("runs", "aug(key, obs) returns"),
    ("uint8", "uint8 in, uint8 out"),
    ("shape", "the input's structure and shapes kept"),
    ("nan", "no NaN converted to uint8"),
    ("range", "values converted to uint8 in 0…255; no uint8 overflow"),
    ("deterministic", "the same key gives the same output"),
    ("jit", "jax.jit gives the eager output"),
    ("vmap", "jax.vmap (over agents, and over samples) gives per-call outputs"),
    ("frames", "one draw per sample, shared by the frames of its stack"),
    ("alignment", "output frame f comes from input frame f only"),
    ("pair", "aug(key, (obs, next_obs)) shares each sample's draw between o and o′"),
)
"""(name, what it means) of every property `check` runs, in order."""

_NEEDS = {"uint8": "runs", "shape": "runs", "nan": "runs", "range": "runs",
          "deterministic": "runs", "jit": "deterministic", "vmap": "deterministic",
          "frames": "deterministic", "alignment": "frames", "pair": "deterministic"}
_NEEDS_SHAPE = ("frames", "alignment")
_VERSION = "v1"


@dataclasses.dataclass(frozen=True)
class Result:
  """One property's outcome.

  Attributes:
    name: the property (`PROPERTIES`).
    status: "pass", "fail" or "skip" (a prerequisite failed).
    detail: what failed or why it was skipped ("" when it passed).
  """
  name: str
  status: str
  detail: str = ""


@dataclasses.dataclass(frozen=True)
class Report:
  """What `check` found.

  Attributes:
    augmentation: the augmentation's name.
    results: one `Result` per property, in `PROPERTIES` order.
    shape: the observation batch's shape (B, H, W, 3·stack).
  """
  augmentation: str
  results: tuple[Result, ...]
  shape: tuple[int, ...]

  @property
  def failed(self) -> tuple[str, ...]:
    """The names of the failed properties."""
    return tuple(r.name for r in self.results if r.status == "fail")

  @property
  def ok(self) -> bool:
    """True when no property failed."""
    return not self.failed

  def paragraph(self) -> str:
    """The failures in one paragraph (for command-line errors)."""
    if self.ok:
      return f"augmentation {self.augmentation!r} passes every property"
    fails = "; ".join(f"{r.name} ({r.detail})" for r in self.results
                      if r.status == "fail")
    return (f"augmentation {self.augmentation!r} fails dmcr_jax.augment.check on real "
            f"observations {'×'.join(map(str, self.shape))} uint8: {fails}. See every "
            f"property with: python -c \"from dmcr_jax import augment; "
            f"print(augment.check({self.augmentation!r}, size={self.shape[1]}, "
            "raise_error=False))\"")

  def __str__(self) -> str:
    head = (f"augmentation {self.augmentation!r} on real observations "
            f"{'×'.join(map(str, self.shape))} uint8: ")
    head += ("passes every property" if self.ok else
             f"fails {', '.join(self.failed)}")
    lines = [head]
    for r in self.results:
      lines.append((f"  {r.status:4s}  {r.name:13s}  {r.detail}").rstrip())
    return "\n".join(lines)


class AugmentationCheckError(ValueError):
  """An augmentation failed `check`; `report` holds every result."""

  def __init__(self, report: Report):
    self.report = report
    super().__init__(str(report))


# --------------------------------------------------------------------------- #
# Real observations.
# --------------------------------------------------------------------------- #


def _cache_path(size: int) -> str:
  from dmcr_jax.visuals import cache_dir
  tag = f"{_VERSION}-{size}-{'_'.join(CHECK_TASKS)}-{'_'.join(map(str, CHECK_LOOKS))}"
  return os.path.join(str(cache_dir()), "augment_check", f"obs-{tag}.npz")


def _render(size: int) -> tuple[np.ndarray, np.ndarray]:
  """Renders (obs, next_obs), each uint8 (tasks·looks, size, size, 3·STACK)."""
  from dm_control import suite

  from dmcr_jax import visuals
  from dmcr_jax.env_checks import default_frame_skip
  from dmcr_jax.visuals import show
  stacks = []
  for task in CHECK_TASKS:
    domain, name = task.split("-", 1)
    rm = visuals.build_render_model(domain)
    looks = visuals.sample(domain, list(CHECK_LOOKS))
    env = suite.load(domain, name, task_kwargs={"random": 0})
    env.reset()
    rng = np.random.default_rng(0)
    spec = env.action_spec()
    frames = []
    for t in range(10 + STACK + 1):
      for _ in range(default_frame_skip(task)):
        env.step(rng.uniform(spec.minimum, spec.maximum))
      if t >= 10:
        qpos, variables = show.physics_state(env.physics, domain)
        frames.append([visuals.render_frame(rm, looks, qpos, index=i,
                                            model_variables=variables,
                                            height=size, width=size)
                       for i in range(len(CHECK_LOOKS))])
    env.physics.free()
    stacks.append(np.stack(frames, axis=1))  # (looks, STACK + 1, H, W, 3)
  visuals.close_renderers()
  frames = np.concatenate(stacks)
  stack = lambda f: np.concatenate(list(np.moveaxis(f, 1, 0)), axis=-1)
  return stack(frames[:, :STACK]), stack(frames[:, 1:])


def observations(size: int = 32) -> tuple[np.ndarray, np.ndarray]:
  """Real (obs, next_obs) for `check`: renders of `CHECK_TASKS`, cached on disk.

  Args:
    size: image side H = W in pixels.

  Returns:
    (obs, next_obs), uint8 (len(CHECK_TASKS)·len(CHECK_LOOKS), size, size,
    3·STACK); next_obs[i] is obs[i] one agent step later (its frames 0–1 are
    obs[i]'s frames 1–2).
  """
  if not isinstance(size, int) or size < 8:
    raise ValueError(f"size must be an int ≥ 8, got {size!r}")
  path = _cache_path(size)
  if os.path.exists(path):
    with np.load(path) as f:
      return f["obs"], f["next_obs"]
  obs, next_obs = _render(size)
  write_atomic(path, lambda f: np.savez_compressed(f, obs=obs, next_obs=next_obs))
  return obs, next_obs


# --------------------------------------------------------------------------- #
# Operation-by-operation evaluation (for the nan and range properties).
# --------------------------------------------------------------------------- #

_CALLS = {"jit": "jaxpr", "pjit": "jaxpr", "closed_call": "call_jaxpr",
          "core_call": "call_jaxpr", "custom_jvp_call": "call_jaxpr",
          "custom_vjp_call": "call_jaxpr", "checkpoint": "jaxpr", "remat": "jaxpr"}
_UINT8_ARITH = {"add": np.add, "sub": np.subtract, "mul": np.multiply}


def _eval_jaxpr(jaxpr, consts, args, problems: list[str]):
  """Evaluates `jaxpr` one primitive at a time, noting bad uint8 conversions."""
  from jax.extend.core import ClosedJaxpr, Literal
  env = {}
  read = lambda v: v.val if isinstance(v, Literal) else env[v]
  for v, x in zip(jaxpr.constvars, consts):
    env[v] = x
  for v, x in zip(jaxpr.invars, args):
    env[v] = x
  for eqn in jaxpr.eqns:
    ins = [read(v) for v in eqn.invars]
    name = eqn.primitive.name
    inner = eqn.params.get(_CALLS.get(name, ""))
    if inner is not None:
      closed = inner if isinstance(inner, ClosedJaxpr) else None
      outs = _eval_jaxpr(closed.jaxpr if closed else inner,
                         closed.consts if closed else (), ins, problems)
    elif name == "cond" and np.ndim(ins[0]) == 0:
      branch = eqn.params["branches"][int(ins[0])]
      outs = _eval_jaxpr(branch.jaxpr, branch.consts, ins[1:], problems)
    else:
      if name == "convert_element_type" and eqn.params["new_dtype"] == np.uint8:
        _note_conversion(np.asarray(ins[0]), problems)
      elif name in _UINT8_ARITH and all(getattr(x, "dtype", None) == np.uint8
                                        for x in ins):
        exact = _UINT8_ARITH[name](*(np.asarray(x, np.int64) for x in ins))
        if exact.min() < 0 or exact.max() > 255:
          problems.append(f"range: uint8 {name} overflows (exact results "
                          f"{exact.min()}…{exact.max()}); compute in int32 and clip")
      params = eqn.primitive.get_bind_params(eqn.params)  # (subfuns, params) in
      subfuns, params = params if isinstance(params, tuple) else ((), params)  # old JAX
      with eqn.ctx.manager:
        outs = eqn.primitive.bind(*subfuns, *ins, **params)
      if not eqn.primitive.multiple_results:
        outs = [outs]
    for v, x in zip(eqn.outvars, outs):
      env[v] = x
  return [read(v) for v in jaxpr.outvars]


def _note_conversion(x: np.ndarray, problems: list[str]) -> None:
  if x.dtype in (np.uint8, np.bool_) or x.size == 0:
    return
  if np.issubdtype(x.dtype, np.floating):
    nan = np.isnan(x)
    if nan.any():
      problems.append(f"nan: {int(nan.sum())} NaN value(s) converted to uint8 "
                      "(guard the division or log that makes them)")
    x = x[~nan]
    if x.size and (x.min() < 0 or x.max() >= 256):
      problems.append(f"range: {x.dtype} values {x.min():.4g}…{x.max():.4g} converted "
                      "to uint8 (clip to 0…255 first, e.g. jnp.clip(jnp.round(y), 0, "
                      "255))")
  elif np.issubdtype(x.dtype, np.integer) and (x.min() < 0 or x.max() > 255):
    problems.append(f"range: {x.dtype} values {x.min()}…{x.max()} converted to uint8 "
                    "(they wrap around; clip to 0…255 first)")


def conversion_problems(aug, key: jax.Array, images) -> list[str]:
  """Runs ``aug(key, images)`` operation by operation; returns what went wrong.

  Args:
    aug: a batch augmentation ``aug(key, images) -> images``.
    key: a `jax.random` key.
    images: uint8 arrays (a pytree).

  Returns:
    Messages starting "nan:" or "range:" (empty when all conversions to uint8
    get values in 0…255 and no uint8 arithmetic overflows).
  """
  closed = jax.make_jaxpr(aug)(key, images)
  problems: list[str] = []
  _eval_jaxpr(closed.jaxpr, closed.consts,
              jax.tree_util.tree_leaves((key, images)), problems)
  return list(dict.fromkeys(problems))


# --------------------------------------------------------------------------- #
# The checker.
# --------------------------------------------------------------------------- #


def _as_batch_aug(aug, batched: bool):
  """(name, batch callable, `Augmentation` or None) for what `check` accepts."""
  if isinstance(aug, str):
    aug = get(aug)
  elif not batched:
    aug = from_function(aug)
  name = getattr(aug, "name", getattr(aug, "__name__", type(aug).__name__))
  return name, aug, aug if isinstance(aug, Augmentation) else None


def _first_difference(a, b) -> str:
  """"" when the pytrees are equal, else where and by how much they differ."""
  la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
  if jax.tree_util.tree_structure(a) != jax.tree_util.tree_structure(b):
    return "different output structures"
  for i, (x, y) in enumerate(zip(la, lb)):
    x, y = np.asarray(x), np.asarray(y)
    if x.shape != y.shape:
      return f"array {i}: shapes {x.shape} and {y.shape}"
    diff = x.astype(np.float64) != y.astype(np.float64)
    if diff.any():
      where = np.argwhere(diff)[0]
      big = np.abs(x.astype(np.float64) - y.astype(np.float64)).max()
      return (f"{int(diff.sum())} of {diff.size} values differ (first at "
              f"{tuple(int(w) for w in where)}, largest difference {big:g})")
  return ""


def _frame(x, f: int):
  return x[..., 3 * f:3 * f + 3]


def check(aug: Any, *, size: int = 32, batched: bool = False, raise_error: bool = True,
          obs: np.ndarray | None = None, next_obs: np.ndarray | None = None,
          seed: int = 0) -> Report:
  """Runs every property of `PROPERTIES` on `aug`; raises or returns a `Report`.

  Args:
    aug: a name `dmcr_jax.augment.get` accepts (built-in, registered,
      ``"a+b"``, ``"package.module:function"``), an `Augmentation` / `Composed`,
      or a per-sample function ``fn(key, image) -> image`` (the convention of
      `dmcr_jax.augment.register`); with ``batched=True``, any batch callable
      ``aug(key, images) -> images``.
    size: side of the rendered observations (cached per size).
    batched: treat a plain callable as a batch augmentation, not a per-sample one.
    raise_error: raise `AugmentationCheckError` when a property fails (default,
      like gymnasium's checker); False returns the report either way.
    obs, next_obs: your own uint8 (B, H, W, 3·k) observations instead of the
      rendered ones (both or neither).
    seed: seeds the keys.

  Returns:
    The `Report` (``str(report)`` is a table of the properties).

  Raises:
    AugmentationCheckError: a property failed and `raise_error` is True.
  """
  name, fn, single = _as_batch_aug(aug, batched)
  if (obs is None) != (next_obs is None):
    raise ValueError("give both obs and next_obs, or neither")
  if obs is None:
    obs, next_obs = observations(size)
  obs, next_obs = jnp.asarray(obs), jnp.asarray(next_obs)
  _check_images((obs, next_obs))
  key = jax.random.key(seed)
  stack = obs.shape[-1] // 3
  compiled = jax.jit(fn)
  results: dict[str, Result] = {}

  def run(prop: str, test: Callable[[], str]) -> None:
    need = _NEEDS.get(prop)
    if need and results[need].status != "pass":
      results[prop] = Result(prop, "skip", f"needs {need}")
      return
    if prop in _NEEDS_SHAPE and results["shape"].status != "pass":
      results[prop] = Result(prop, "skip", "needs shape")
      return
    try:
      detail = test()
    except Exception as e:  # noqa: BLE001 - report, don't crash, like gymnasium's
      detail = f"raised {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    results[prop] = Result(prop, "fail" if detail else "pass", detail)

  out: dict[str, Any] = {}

  def runs():
    out["y"] = jax.block_until_ready(compiled(key, obs))
    return ""

  def uint8():
    bad = [str(y.dtype) for y in jax.tree_util.tree_leaves(out["y"]) if y.dtype != jnp.uint8]
    return f"output dtype {', '.join(bad)}, not uint8" if bad else ""

  def shape():
    y = out["y"]
    if jax.tree_util.tree_structure(y) != jax.tree_util.tree_structure(obs):
      return f"returned {jax.tree_util.tree_structure(y)}, not one array"
    return "" if y.shape == obs.shape else f"shape {y.shape} for input {obs.shape}"

  problems: dict[str, list[str]] = {}

  def conversions(kind):
    if "all" not in problems:
      problems["all"] = conversion_problems(fn, key, obs)
    mine = [p.split(": ", 1)[1] for p in problems["all"] if p.startswith(kind + ":")]
    return "; ".join(mine)

  def deterministic():
    with jax.disable_jit():
      out["eager"] = fn(key, obs)
      again = fn(key, obs)
    diff = _first_difference(out["eager"], again)
    return f"two eager calls with one key: {diff}" if diff else ""

  def jit():
    diff = _first_difference(out["y"], out["eager"])
    return f"jit against eager: {diff}" if diff else ""

  def vmap():
    keys = jax.random.split(jax.random.fold_in(key, 1), 2)
    xs = jnp.stack([obs, obs[::-1]])
    batched_out = jax.jit(jax.vmap(fn))(keys, xs)
    for a in range(2):
      diff = _first_difference(jax.tree.map(lambda y, a=a: y[a], batched_out),
                               compiled(keys[a], xs[a]))
      if diff:
        return f"jax.vmap over agents, agent {a} against its own call: {diff}"
    if single is not None:
      per = key if single.per_batch else sample_keys(key, obs.shape[0])
      one = jax.jit(single.one)
      for i in range(obs.shape[0]):
        diff = _first_difference(out["y"][i], one(per if single.per_batch else per[i],
                                                  obs[i]))
        if diff:
          return f"sample {i} of the batch against aug.one on it alone: {diff}"
    return ""

  def frames():
    same = jnp.tile(_frame(obs, 0), (1, 1, 1, stack))
    y = compiled(key, same)
    for f in range(1, stack):
      diff = _first_difference(_frame(y, f), _frame(y, 0))
      if diff:
        return (f"a stack of {stack} identical frames: output frame {f} differs from "
                f"frame 0 ({diff}); draw once per sample, apply to every frame")
    return ""

  def alignment():
    for f in range(stack):
      alone = compiled(key, jnp.tile(_frame(obs, f), (1, 1, 1, stack)))
      diff = _first_difference(_frame(out["y"], f), _frame(alone, 0))
      if diff:
        return (f"output frame {f} differs from the output of a stack repeating input "
                f"frame {f} ({diff}): frames reordered or mixed")
    return ""

  def pair():
    y, y_next = compiled(key, (obs, next_obs))
    for tag, got, want in (("obs", y, out["y"]), ("next_obs", y_next,
                                                  compiled(key, next_obs))):
      diff = _first_difference(got, want)
      if diff:
        return (f"aug(key, (obs, next_obs)): its {tag} differs from aug(key, {tag}) "
                f"({diff}); o and o′ must share each sample's draw")
    return ""

  tests = dict(runs=runs, uint8=uint8, shape=shape, nan=lambda: conversions("nan"),
               range=lambda: conversions("range"), deterministic=deterministic, jit=jit,
               vmap=vmap, frames=frames, alignment=alignment, pair=pair)
  for prop, _ in PROPERTIES:
    run(prop, tests[prop])
  report = Report(name, tuple(results[p] for p, _ in PROPERTIES), tuple(obs.shape))
  if raise_error and not report.ok:
    raise AugmentationCheckError(report)
  return report
