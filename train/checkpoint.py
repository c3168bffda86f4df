"""A training run's folder: its lock, its checkpoints, and the errors a bad folder gives.

One run per folder: `RunLock` holds an OS file lock (`fcntl.flock`) on
`<out>/.lock` for the life of a run; the kernel releases it when the process
ends, however it ends, so a lock left by a dead process is simply taken over,
and a second process asking for the folder of a live run is refused with the
holder's pid, host and start time (written into the lock file).

Checkpoints (orbax, `<out>/checkpoints/<step>`, the newest `KEEP` kept): the
agents, the run's RNG key and the step counter. After orbax has written a step,
`save` adds `DIGEST`, the size and SHA-256 of every file of that step; `restore`
checks it before orbax reads anything, so a truncated or altered checkpoint is
refused with one paragraph naming the file (orbax itself may read such a file
without a word, or fail with pages of tensorstore errors). A checkpoint without
a digest (written by an older version, or killed between orbax's commit and
the digest) is read as it is, orbax's errors turned into that paragraph.
`restore(..., fallback=True)` (a resumed run) moves a damaged newest step aside,
into `<out>/damaged/`, says so on stderr, and restores the one before it.

Errors are `RunFolderError`s (a `ValueError`): one paragraph saying what is wrong
with the folder and what to do, raised before anything is written.
"""

from __future__ import annotations

import datetime
import errno
import fcntl
import functools
import hashlib
import json
import os
import shutil
import socket
import sys

import jax
import jax.numpy as jnp
import numpy as np

KEEP = 2
"""Checkpoints a run keeps (the newest; the one before is the fallback of a
damaged newest)."""
LOCK = ".lock"
"""The lock file in a run folder (`RunLock`)."""
DIGEST = "dmcr_digest.json"
"""The file in a checkpoint step's folder listing its files' sizes and SHA-256."""
DAMAGED = "damaged"
"""The folder in a run folder that damaged checkpoints are moved into."""


class RunFolderError(ValueError):
  """A run folder that cannot be used as asked; the message says what to do."""


class RunLockedError(RunFolderError):
  """The folder belongs to a training process that is still running."""


class DamagedCheckpointError(RunFolderError):
  """A checkpoint whose files differ from what was saved or cannot be read."""


# The folder ---------------------------------------------------------------------------


def check_out_dir(out_dir: str) -> None:
  """Raises `RunFolderError` unless a run can write in `out_dir`: it must be a
  folder (or not exist yet, below a folder) that this process may write in, and
  so must its `checkpoints` folder if it has one. Nothing is created."""
  path = os.path.abspath(out_dir)
  if os.path.exists(path) and not os.path.isdir(path):
    raise RunFolderError(f"--out {out_dir!r} is a file, not a folder: choose a folder "
                         "path for the run's outputs (a new one is created)")
  existing = path
  while not os.path.exists(existing):
    existing = os.path.dirname(existing)
  if not os.path.isdir(existing):
    raise RunFolderError(f"--out {out_dir!r} cannot be created: {existing!r} is a file, "
                         "not a folder; choose another folder path")
  effective = os.access in os.supports_effective_ids
  for where, what in ((existing, "--out" if existing == path else "the folder it goes in"),
                      (os.path.join(path, "checkpoints"), "its checkpoints folder")):
    if os.path.isdir(where) and not os.access(where, os.W_OK | os.X_OK,
                                              effective_ids=effective):
      raise RunFolderError(f"--out {out_dir!r}: this process may not write in {where!r} "
                           f"({what}: permission denied or a read-only file system); "
                           "choose a folder you can write in, or fix its permissions")


class RunLock:
  """The exclusive lock of a run folder, held from `acquire` to `release` (or the
  process's end: the kernel drops it). A context manager.

  Args:
    out_dir: the run folder (created if missing).
  """

  def __init__(self, out_dir: str):
    self.out_dir = out_dir
    self.path = os.path.join(out_dir, LOCK)
    self._fd = None

  def acquire(self) -> "RunLock":
    """Takes the lock, writing this process's pid, host and start time into it.

    Raises:
      RunLockedError: naming the holder, if another live process holds it.
      RunFolderError: the folder or its lock file cannot be created.
    """
    try:
      os.makedirs(self.out_dir, exist_ok=True)
      fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
      raise RunFolderError(f"--out {self.out_dir!r}: cannot create the run folder or its "
                           f"lock file ({e.strerror}): choose a folder you can write in"
                           ) from None
    try:
      fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
      holder = os.pread(fd, 4096, 0).decode(errors="replace")
      os.close(fd)
      if e.errno not in (errno.EAGAIN, errno.EACCES):
        raise RunFolderError(f"--out {self.out_dir!r}: cannot lock {self.path} "
                             f"({e.strerror}): choose a folder on a local file system"
                             ) from None
      raise RunLockedError(f"{self.out_dir!r} belongs to a training process that is still "
                           f"running ({describe_holder(holder)}): wait for it to end or stop "
                           "it (Ctrl-C saves a checkpoint; then --resume), or choose "
                           "another --out") from None
    info = dict(pid=os.getpid(), host=socket.gethostname(),
                started=datetime.datetime.now(datetime.timezone.utc)
                .isoformat(timespec="seconds"))
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)
    self._fd = fd
    return self

  def release(self) -> None:
    """Drops the lock (the file stays: removing it would race a new holder)."""
    if self._fd is not None:
      fcntl.flock(self._fd, fcntl.LOCK_UN)
      os.close(self._fd)
      self._fd = None

  def __enter__(self):
    return self.acquire()

  def __exit__(self, *exc):
    self.release()


def describe_holder(text: str) -> str:
  """A lock file's contents ("pid 12, host h, started 2026-…") for a message."""
  try:
    info = json.loads(text)
    return f"pid {info['pid']} on {info['host']}, started {info['started']}"
  except (ValueError, KeyError, TypeError):
    return "holder unknown"


# Checkpoints ----------------------------------------------------------------------


def folder(out_dir: str) -> str:
  """The checkpoints folder of a run (absolute: orbax wants that)."""
  return os.path.abspath(os.path.join(out_dir, "checkpoints"))


def steps(out_dir: str) -> list[int]:
  """The steps of a run's committed checkpoints, oldest first (from the folder
  names; orbax writes a step under a temporary name and renames it when done)."""
  path = folder(out_dir)
  if not os.path.isdir(path):
    return []
  return sorted(int(d) for d in os.listdir(path)
                if d.isdigit() and os.path.isdir(os.path.join(path, d)))


def manager(out_dir: str):
  """The orbax `CheckpointManager` of a run's checkpoints (`KEEP` kept)."""
  import orbax.checkpoint as ocp
  return ocp.CheckpointManager(folder(out_dir),
                               options=ocp.CheckpointManagerOptions(max_to_keep=KEEP))


def _state(agents, key, step: int) -> dict:
  return {"agents": agents, "key": jax.random.key_data(key),
          "step": np.asarray(step, np.int64)}


def save(mgr, step: int, agents, key) -> None:
  """Saves (agents, key, step) as checkpoint `step` and writes its digest."""
  import orbax.checkpoint as ocp
  mgr.save(step, args=ocp.args.StandardSave(_state(agents, key, step)), force=True)
  mgr.wait_until_finished()
  path = os.path.join(str(mgr.directory), str(step))
  digest = _digest(path)
  with open(os.path.join(path, DIGEST + ".tmp"), "w") as f:
    json.dump(digest, f)
  os.replace(os.path.join(path, DIGEST + ".tmp"), os.path.join(path, DIGEST))


def _digest(path: str) -> dict:
  """{relative path: [size, sha256]} of every file under `path` but the digest."""
  out = {}
  for root, _, files in os.walk(path):
    for name in files:
      full = os.path.join(root, name)
      rel = os.path.relpath(full, path)
      if rel in (DIGEST, DIGEST + ".tmp"):
        continue
      h = hashlib.sha256()
      with open(full, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
          h.update(block)
      out[rel] = [os.path.getsize(full), h.hexdigest()]
  return out


def damage(out_dir: str, step: int) -> str | None:
  """What is wrong with checkpoint `step` of a run ("<file>: truncated, …"), or None
  when its files match its digest (or it has none to check)."""
  path = os.path.join(folder(out_dir), str(step))
  try:
    with open(os.path.join(path, DIGEST)) as f:
      saved = json.load(f)
  except FileNotFoundError:
    return None
  except (OSError, ValueError):
    return f"{os.path.join(path, DIGEST)}: unreadable"
  now = _digest(path)
  for rel, (size, sha) in sorted(saved.items()):
    full = os.path.join(path, rel)
    if rel not in now:
      return f"{full}: missing"
    if now[rel][0] != size:
      return f"{full}: {now[rel][0]} bytes, {size} when saved (truncated or overwritten)"
    if now[rel][1] != sha:
      return f"{full}: its contents differ from those saved"
  return None


def _uncommitted(tree):
  """`tree`'s arrays as fresh ones are: on the default device and uncommitted.

  Orbax restores arrays committed to a device; a jitted function given committed
  arguments lowers to another program (each input carries its sharding) than the
  one fresh agents compiled, so a resumed run would miss the compilation cache and
  compile its learner again."""
  return jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), tree)


def _read(out_dir: str, step: int, agents, key):
  """Checkpoint `step` restored like (agents, key): (agents, key, step), after
  checking its digest. Raises DamagedCheckpointError (its message without advice)."""
  import orbax.checkpoint as ocp
  why = damage(out_dir, step)
  if why is None:
    try:
      state = manager(out_dir).restore(
          step, args=ocp.args.StandardRestore(_state(agents, key, 0)))
      state = _uncommitted(state)
      return state["agents"], jax.random.wrap_key_data(state["key"]), int(state["step"])
    except Exception as e:  # noqa: BLE001 - orbax/tensorstore raise many types
      why = f"orbax cannot read it ({type(e).__name__}: {str(e).splitlines()[0][:200]})"
  raise DamagedCheckpointError(
      f"checkpoint step {step} in {os.path.join(folder(out_dir), str(step))} is damaged: "
      f"{why}")


def restore(out_dir: str, agents, key, step: int | None = None, fallback: bool = False):
  """A run's checkpoint, restored with the structure of `agents` and `key`.

  Args:
    out_dir: the run folder.
    agents, key: fresh agents and a key (their shapes and dtypes).
    step: which checkpoint (None: the newest).
    fallback: when the newest is damaged, move it into `<out>/damaged/`, say so on
      stderr and restore the one before it (a resumed run); else raise.

  Returns:
    (agents, key, step).

  Raises:
    FileNotFoundError: no checkpoint (or not `step`).
    DamagedCheckpointError: the checkpoint (with `fallback`: every one) is damaged;
      the message names the file and what to do.
  """
  have = steps(out_dir)
  if not have or (step is not None and step not in have):
    what = "no checkpoint" if not have else f"no checkpoint at step {step} (have: " \
        + ", ".join(map(str, have)) + ")"
    raise FileNotFoundError(f"{what} in {folder(out_dir)}")
  if not fallback:
    step = have[-1] if step is None else step
    try:
      return _read(out_dir, step, agents, key)
    except DamagedCheckpointError as e:
      earlier = [s for s in have if s < step]
      advice = (f"`dmcr-train --resume --out {out_dir}` continues the run from the "
                f"checkpoint before it (step {earlier[-1]}), moving the damaged one aside, "
                f"and `load_run({out_dir!r}, step={earlier[-1]})` loads that one"
                if earlier else
                "no checkpoint of the run comes before it: start the run again (another "
                "--out, or delete this folder)")
      raise DamagedCheckpointError(f"{e}; {advice}") from None
  reasons = []
  for s in reversed(have):
    try:
      restored = _read(out_dir, s, agents, key)
    except DamagedCheckpointError as e:
      reasons.append(str(e))
      aside = move_aside(out_dir, s)
      print(f"train: {e}; moved it to {aside}"
            + (", resuming from the checkpoint before it" if s != have[0] else ""),
            file=sys.stderr, flush=True)
      continue
    return restored
  raise DamagedCheckpointError(
      f"--resume: every checkpoint of {out_dir!r} is damaged ({'; '.join(reasons)}); they "
      f"were moved to {os.path.join(out_dir, DAMAGED)}: start the run again (another --out, "
      "or delete this folder)")


def move_aside(out_dir: str, step: int) -> str:
  """Moves checkpoint `step` into `<out>/damaged/<step>` (replacing an earlier one
  there); its new path."""
  dest = os.path.join(out_dir, DAMAGED, str(step))
  os.makedirs(os.path.dirname(dest), exist_ok=True)
  if os.path.exists(dest):
    shutil.rmtree(dest)
  shutil.move(os.path.join(folder(out_dir), str(step)), dest)
  return dest


# Agents -------------------------------------------------------------------------------


def init_agents(cfg, obs_shape, action_size: int):
  """Fresh agents for `cfg.agents()` (a `TrainConfig`), stacked along a leading
  agent axis (`sac.AgentState`).

  Each agent is initialised by its own call of one jitted function (its seed and
  augmentation index are arguments, so one compilation serves them all): the
  K agents' initialisations vmapped into one XLA:CPU program never finished on a
  2-core machine (every thread waiting), while one agent's always does.
  """
  aug_index = {name: i for i, name in enumerate(cfg.sac.aug_names)}
  agents = [_init_agent(jnp.asarray(seed), jnp.asarray(aug_index[aug]), tuple(obs_shape),
                        int(action_size), cfg.sac)
            for seed, aug in cfg.agents()]
  return jax.tree.map(lambda *x: jnp.stack(x), *agents)


@functools.partial(jax.jit, static_argnums=(2, 3, 4))
def _init_agent(seed, aug_index, obs_shape, action_size, config):
  # Jitted: one compilation instead of op-by-op dispatch (the same values).
  from dmcr_jax.train import sac
  return sac.init_agent(jax.random.key(seed), obs_shape, action_size, config, aug_index)


def load_run(out_dir: str, step: int | None = None):
  """The agents of a `train` run from its checkpoints.

  Args:
    out_dir: the run's output folder (with config.json and checkpoints/).
    step: which checkpoint; None = the newest.

  Returns:
    (cfg, agents with a leading agent axis in `cfg.agents()` order, step).

  Raises:
    FileNotFoundError: no config.json or no checkpoint.
    DamagedCheckpointError: the checkpoint is damaged (the message names the file
      and the checkpoint before it).
  """
  import dmcr_jax
  from dmcr_jax.train.config import load_config
  cfg = load_config(out_dir)
  if not steps(out_dir):
    raise FileNotFoundError(f"no checkpoint in {folder(out_dir)}")
  task = dmcr_jax.models.load(cfg.task)
  obs_shape = (cfg.image_size, cfg.image_size, 3 * cfg.frame_stack)
  agents, _, step = restore(out_dir, init_agents(cfg, obs_shape, task.action_size),
                            jax.random.key(0), step)
  return cfg, agents, step
