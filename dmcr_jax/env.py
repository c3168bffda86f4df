"""`dmcr_jax.make`: N DMCR envs with pixels, as one gymnasium `VectorEnv`.

Two renderers, one interface (`renderer=`): "pool" (default, `PixelVectorEnv`)
renders MuJoCo's own pixels in CPU worker processes; "jax" (`JaxPixelVectorEnv`)
runs physics, the JAX ray caster (`visuals.jax_render`: close to MuJoCo's pixels,
not equal) and the frame stacks as one jitted call on the device
(`dmcr_jax.jax_env`, whose pure functions a training loop can scan). Both share
the arguments, spaces, visual seeds, auto-reset, observations and info described
below (`env_base.PixelEnvBase`); `workers`, `quality`, `gl`, `egl_devices`, `copy_obs` and
`render_pool` are the pool's,
`shadows`, `reflection`, `render_chunk`, `render_kernel` and `obs_on_device` the
JAX renderer's,
and either refuses the other's. With "jax" a look is made on the device from its
seed (`jax_env`), so a range of any size costs no host memory or time.

Per agent step of the pool env, for the whole batch:
1. physics — one jitted call (`physics_env.step`): frame skip, rewards summed,
   NEXT_STEP auto-reset, next visual seeds (device);
2. transfer — the few arrays the host needs (qpos, task variables, rewards,
   flags, state features, seeds) in one `jax.device_get`;
3. render — looks of envs whose visual seed changed are rebuilt
   (`visuals.sample` + `prepare`), then one `RenderPool.render` call, whose
   workers also append the new frames to the envs' frame stacks (a reset env's
   stack is its first frame repeated);
4. copy — the stacked observations are copied out of shared memory (skipped
   with `copy_obs=False`: observations are then views of the pool's shared
   memory, valid until the step after next — enough to store a transition).
`env.timings` accumulates the seconds spent in each part (the JAX env: "step",
the one jitted call, and "transfer", the observations and info to the host;
with `obs_on_device` and the physics on the host CPU, `step_wait` returns once
the physics is done and the frames are dispatched, without waiting for them, so
"step" times the physics and that dispatch).

`step` is `step_async` (checks the actions and dispatches the physics, without
waiting for it) followed by `step_wait` (waits for the physics, renders,
returns gymnasium's step tuple), as in gymnasium's `AsyncVectorEnv`: a caller can
dispatch its own device work between the two (a training loop dispatches its
gradient updates there), so that work and the env step run at the same time.
The pool env splits `step_wait` once more: `step_submit` waits for the physics
and hands the frames to the render workers, `step_wait` then waits for them, so
the caller can work while the workers draw (`dmcr_jax.protocol` steps two envs'
physics and policy so, each while the other's frames are drawn).

Physics device (`physics_device=`): None runs the physics on JAX's default
device; "cpu" on the host's CPU (XLA:CPU), where a small batch (a few dozen envs)
steps in a fraction of the time an accelerator's launch latency allows, and off
the accelerator's queue, so a learner's updates on the accelerator do not wait
behind it (and it does not wait behind them). Rewards, observations and pixels are
the same either way up to float32 rounding (`tests/test_env.py`). With the physics
on the CPU, `physics_workers=W` steps it in W worker processes, each a slice of
the envs on its own XLA:CPU (`dmcr_jax.physics_pool`): on a many-core host a small
batch steps several times faster than in one process; the results are again the
same up to float32 rounding.

Lifecycle: the first `reset` of an env of a new shape (task, sizes, devices)
announces on stderr that its physics (and, with "jax", its renderer) compiles,
and roughly how long that takes; later envs of the same shape compile nothing
and say nothing. A render or physics worker that is unresponsive for
`worker_timeout` seconds (default: `DMCR_WORKER_TIMEOUT`, else 10) is announced
and replaced, and its slice done again (`visuals.pool`). `close()` frees the
workers and shared memory at once and is recommended, not required: an env left
open is closed at interpreter exit, also after an exception, Ctrl-C or SIGTERM.
A closed env's `reset` and `step` raise RuntimeError.

Auto-reset follows gymnasium's NEXT_STEP mode: the step that ends an episode
returns its last observation, reward and `truncated=True`; the env's next step
ignores its action and returns the new episode's first observation with reward
0 and both flags False. DMC tasks never terminate (`terminated` is always False);
they are truncated at 1,000 control steps.

Visual seeds (`visual_seeds=`):
- an int: every env shows that look (0: dm_control's, the classic setting);
- N ints: a fixed look per env;
- a `SeedRange` (few-shot): every episode of every env draws its seed from the
  range, e.g. `levels(1000)` = seeds [0, 1000); evaluation draws from
  `TEST_SEEDS`, which no training range may overlap (see `visuals.levels`);
- N `SeedRange`s (or an `EnvRanges`): env i draws every episode's seed from its
  own range (e.g. agents with different few-shot ranges in one batch).
A seed's look depends on the seed (and `vary`) alone, whatever range drew it.

Moving looks (`moving=`, `intensity=`; `visuals.moving`): the named factors
("camera", "light", "body", "floor", "background") drift within each episode,
as a function of the env's visual seed and episode step alone
(`visuals.moving.look_at`), inside a range `intensity` ∈ [0, 1] scales; the
physics and rewards are those of static looks. The pool env computes each step's
looks on the host and ships them with the render call; the JAX env makes them in
its jitted step. `moving=None` (default) or intensity 0 gives the static looks.

Observations are uint8 (N, H, W, 3·frame_stack), channels-last, oldest frame
first. `info` holds, per env: "state" (dm_control's state features, flat),
"visual_seed", "episode_index" (episodes begun − 1), "episode_step" (agent steps
in the episode) and "episode_return", each with gymnasium's boolean mask
"_<key>" (every env has every key: all True). "episode" is left to gymnasium's
`RecordEpisodeStatistics` wrappers, which reserve it.

The modules: `env_checks` (the arguments and their defaults), `env_base` (what
both envs share), `env_pool` (the render-pool env) with `env_looks` (its looks),
`env_jax` (the ray-caster env); this module is the public door, `make`.
"""

from __future__ import annotations

from typing import Any, Sequence

from dmcr_jax.env_base import INFO_KEYS, announce_compile
from dmcr_jax.env_checks import (ACTION_REPEAT, MAX_RESET_SEED, PHYSICS_DEVICES, RENDERERS,
                                 check_camera, check_physics_workers, check_renderer_name,
                                 check_renderer_options, check_reset_seed, default_frame_skip)
from dmcr_jax.env_jax import JaxPixelVectorEnv, to_host
from dmcr_jax.env_pool import TIMING_PARTS, PixelVectorEnv

__all__ = ["ACTION_REPEAT", "INFO_KEYS", "MAX_RESET_SEED", "PHYSICS_DEVICES", "RENDERERS",
           "TIMING_PARTS", "JaxPixelVectorEnv", "PixelVectorEnv", "announce_compile",
           "check_camera", "check_physics_workers", "check_renderer_name", "check_reset_seed",
           "default_frame_skip", "make", "to_host"]


def make(task: str, num_envs: int = 1, visual_seeds: Any = 0,
         vary: str | Sequence[str] | None = "all", frame_skip: int | None = None,
         frame_stack: int = 3, image_size: int | tuple[int, int] = 84,
         camera: int | str = 0, seed: int = 0, renderer: str = "pool",
         moving: str | Sequence[str] | None = None, intensity: float = 0.0,
         **kwargs) -> PixelVectorEnv | JaxPixelVectorEnv:
  """N DMCR envs with pixels, stepped as one batch (see the module docstring).

  Args:
    task: one of `dmcr_jax.ALL_TASKS`, e.g. "walker-walk".
    num_envs: N ≥ 1.
    visual_seeds: an int (every env), N ints (one per env), a `SeedRange`
      drawn from at every reset (few-shot: `levels(1000)`; test: `TEST_SEEDS`),
      or N `SeedRange`s (an `EnvRanges`): env i draws from its own.
    vary: factors the visual seeds change ("all", "none", "floor,background", …;
      named factors must apply to the task's domain, `visuals.factors.APPLICABLE`).
    frame_skip: control steps per agent step, rewards summed (default: the
      paper's action repeat, `default_frame_skip(task)`).
    frame_stack: frames per observation, stacked on the channel axis.
    image_size: H = W, or (H, W).
    camera: camera id or name (camera 0 is the one the visual seeds move).
    seed: dynamics seed, an int in [0, 2**32) (initial states; and few-shot seed
      draws).
    renderer: "pool" (default: MuJoCo's renderer in CPU worker processes,
      dm_control's pixels) or "jax" (the JAX ray caster on the device, physics,
      frames and stacks in one jitted call; close to MuJoCo's pixels, not equal).
    moving: factors that move within each episode: None (default: static looks),
      "all", or names from `visuals.moving.MOVING_FACTORS` ("camera", "light",
      "body", "floor", "background"; comma-separated or a sequence), each
      applicable to the task's domain (docs/moving.md).
    intensity: how far they move, in [0, 1] (a fraction of each factor's range, as
      the Distracting Control Suite's difficulty: .1, .2, .3); 0 is static.
    **kwargs: for "pool": `workers`, `quality` ("exact", "fast", "fastest"), `gl`
      ("egl", the default, or "osmesa", which needs the OSMesa library; no
      environment variable needed), `egl_devices` (EGL device indices the
      workers are spread over; None: MuJoCo's default) for the `RenderPool`, `copy_obs` (default True; False
      returns views of shared memory, see the module docstring), `render_pool` (a
      `RenderPool` of the task and frame sizes, or a `RenderPool.rows(a, b)` view
      of one, drawn with instead of starting workers of its own: envs that share
      workers, one step's frames in flight at a time among them; the env does not
      close it; its workers, quality, GL and camera are the pool's). For "jax"
      (which has no workers and no quality presets): `shadows`, `reflection`
      (default True: MuJoCo's picture), `render_chunk` (envs per render chunk,
      see `jax_env.make_env`), `render_kernel` (default False: render through
      XLA; True: in one fused GPU kernel, `visuals.jax_render_kernel`, with the same
      frames, faster, for minutes of compiling: benchmarks/results/jax_env_h100.md;
      None: the kernel on a GPU only), `obs_on_device`
      (default False; True returns observations as device arrays, skipping
      their transfer). Both:
      `solver_iterations`, `ls_iterations` for the physics (`models.load`);
      `physics_device` (None: JAX's default device; "cpu": the host CPU, see the
      module docstring; with renderer="jax" the frames are still rendered on
      the default device); `physics_workers` (None or 0: the physics in this
      process; W ≥ 1: in W CPU worker processes, with `physics_device="cpu"`);
      `worker_timeout` (seconds a busy render or physics worker may send no
      heartbeat before it is announced on stderr and replaced, its slice redone;
      None: the `DMCR_WORKER_TIMEOUT` environment variable, else 10).

  Returns:
    A `PixelVectorEnv` or a `JaxPixelVectorEnv` (gymnasium `VectorEnv`s); call
    `reset()` first (its first call, and the first `step`, compile, announced
    on stderr once per shape). `close()` when done is recommended (it frees the
    workers and shared memory at once) but optional: an env left open is closed
    at interpreter exit, also after an exception, Ctrl-C or SIGTERM.

  Raises:
    ValueError: unknown task, factor, camera, renderer, quality or GL backend (the
      message lists the valid ones), a factor that does not apply to the task's
      domain or an empty `vary`, num_envs or workers ≤ 0, a seed outside
      [0, 2**32), a worker_timeout that is not a number > 0, a visual-seed
      count other than 1 or N, an option of the other
      renderer, a range straddling `TRAIN_SEEDS` and `TEST_SEEDS`, ranges mixed
      with fixed seeds, an unknown or inapplicable moving factor, an intensity
      outside [0, 1].
  """
  check_renderer_options(renderer, kwargs)
  cls = PixelVectorEnv if renderer == "pool" else JaxPixelVectorEnv
  return cls(task, num_envs, visual_seeds, vary, frame_skip, frame_stack, image_size,
             camera, seed, moving=moving, intensity=intensity, **kwargs)
