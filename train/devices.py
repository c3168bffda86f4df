"""Devices of a training run: the agent axis sharded over local devices.

The host driver shards the agent axis over the local devices with `shard_map`
(each device updates and acts for K / D of the agents, their buffers on it): all
D of them when K is a multiple of D, else one (`mesh_devices`; `train(...,
devices=D)` picks D). One process drives them all and renders every env in one
render pool on the host. The device driver runs on one device.
"""

from __future__ import annotations

import jax
import numpy as np

def valid_device_counts(k: int, available: int) -> list[int]:
  """The local device counts K agents can be sharded over: 1, and every count up
  to `available` that divides K (`shard_map` gives each device K / count agents)."""
  return [n for n in range(1, available + 1) if n == 1 or k % n == 0]


def check_devices(devices: int, k: int, available: int) -> None:
  """Raises ValueError, naming the valid counts, unless K agents can be sharded
  over `devices` of the `available` local devices (`valid_device_counts`)."""
  valid = valid_device_counts(k, available)
  if isinstance(devices, bool) or not isinstance(devices, (int, np.integer)) or devices < 1:
    why = "not a positive device count"
  elif devices in valid:
    return
  elif devices > available:
    why = "more than the local devices"
  else:
    why = f"{k} agent{'s are' if k != 1 else ' is'} not a multiple of it"
  raise ValueError(f"devices {devices!r}: {why} ({available} local device"
                   f"{'s' if available != 1 else ''}); valid counts for {k} agent"
                   f"{'s' if k != 1 else ''}: {', '.join(map(str, valid))}")


def mesh_devices(k: int, devices: int | None = None, available: int | None = None) -> int:
  """How many local devices `train` shards K agents over.

  Args:
    k: the number of agents.
    devices: a count (checked with `check_devices`), or None: all `available`
      devices when K is a multiple of their count, else one.
    available: the local device count (None: `jax.local_device_count()`).
  """
  available = jax.local_device_count() if available is None else available
  if devices is not None:
    check_devices(devices, k, available)
    return int(devices)
  return available if k % available == 0 else 1


def agent_mesh(k: int, devices: int | None = None):
  """A mesh over the agent axis of the first `mesh_devices(k, devices)` local
  devices, or None for one device (the arrays stay on the default device)."""
  n = mesh_devices(k, devices)
  if n < 2:
    return None
  return jax.sharding.Mesh(np.array(jax.local_devices()[:n]), ("agents",))


def put_agents(tree, mesh):
  """`tree`'s arrays split along their leading (agent) axis over `mesh` (None: as
  they are)."""
  if mesh is None:
    return tree
  return jax.device_put(tree, jax.sharding.NamedSharding(
      mesh, jax.sharding.PartitionSpec("agents")))



def one_device_note(k: int, available: int, devices: int | None, device_driver: bool
                    ) -> str | None:
  """Why a run on a host with several local devices uses only one (None when it
  uses them all, was asked for its count, or there is one device)."""
  if available < 2 or devices is not None:
    return None
  if device_driver:
    return (f"training on one of the {available} local devices: the device driver "
            "(renderer 'jax', physics on the device) runs on one")
  if k % available:
    return (f"training on one of the {available} local devices: the {k} agents are not "
            f"a multiple of {available} (shard them with a multiple of {available} agents, "
            "or limit the visible devices, e.g. CUDA_VISIBLE_DEVICES)")
  return None


def shared_frames_note(renderer: str, egl_devices, platform: str, available: int,
                       used: int) -> str | None:
  """How to keep the pool's frames off the learner's GPU, when some GPU is idle.

  None unless the pool draws its frames on MuJoCo's default EGL device
  (`egl_devices` None: neither `--egl-devices` nor `MUJOCO_EGL_DEVICE_ID` given)
  on a GPU host (`platform` "gpu") whose learner uses `used` of its `available`
  local devices and leaves at least one idle. That EGL device is usually the
  learner's first GPU, where the frames slow the updates.
  """
  if renderer != "pool" or egl_devices is not None or platform != "gpu" or used >= available:
    return None
  return (f"the pool draws its frames on the first EGL device, usually the learner's "
          f"GPU, where they slow the updates; {available - used} of the {available} GPUs "
          f"stay idle: --egl-devices {used} draws the frames on the next one (EGL's "
          "device order, usually the GPUs')")

