"""Tests of `dmcr_jax.train.replay` against NumPy envs with NEXT_STEP auto-reset.

The envs are simulated here in NumPy with `dmcr_jax.make`'s semantics (the step
that ends an episode returns truncated=True; the next step ignores its action,
returns reward 0 and the new episode's first frame repeated k times). Each
frame encodes (env, call index t, pixel position) in its three channels, so every
sampled stack decodes to the frames it was built from. A reference list of valid
transitions, written from the env's own stacks (not from the buffer's rule), is
checked against `valid_mask` exactly and against many jitted samples: each is a
real transition with the env's stacks, none crosses an episode boundary or uses
the reset step or an overwritten frame, every valid one appears, and the counts
are uniform. Episodes are short (1–6 steps) and staggered across envs; rings are
small so that they wrap several times.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax.train import replay

pytestmark = pytest.mark.xdist_group("replay")

H, W, A = 3, 2, 2
KEY = jax.random.key(0)

_add = jax.jit(replay.add)
_sample = jax.jit(replay.sample, static_argnames="batch_size")
_valid = jax.jit(replay.valid_mask)
_num_valid = jax.jit(replay.num_valid)


def _frame(env: int, t: int) -> np.ndarray:
  """Frame of env at call index t: channels (env, t, position code h·W + w)."""
  f = np.empty((H, W, 3), np.uint8)
  f[..., 0], f[..., 1] = env, t
  f[..., 2] = np.arange(H * W).reshape(H, W)
  return f


def _simulate(lengths, num_steps: int, k: int, seed: int = 0) -> dict:
  """Runs len(lengths) NumPy envs with NEXT_STEP auto-reset for num_steps steps.

  Env i truncates after lengths[i] steps. Returns, per call index t and env i,
  what the training loop passes to `add` (frame, first, action, reward) and the
  observation's stack as frame call indices (oldest first), for t = 0 … num_steps
  (the last observation is never added).
  """
  rng = np.random.default_rng(seed)
  n = len(lengths)
  stacks = np.zeros((num_steps + 1, n, k), np.int64)
  first = np.zeros((num_steps + 1, n), bool)
  action = rng.uniform(-1, 1, (num_steps, n, A)).astype(np.float32)
  reward = np.zeros((num_steps, n), np.float32)
  stacks[0], first[0] = 0, True  # reset: frame 0 repeated
  ep_step = np.zeros(n, int)
  needs_reset = np.zeros(n, bool)
  for t in range(num_steps):
    for i in range(n):
      if needs_reset[i]:  # NEXT_STEP: action ignored, reward 0, new episode
        stacks[t + 1, i], first[t + 1, i] = t + 1, True
        ep_step[i], needs_reset[i] = 0, False
      else:
        stacks[t + 1, i] = np.append(stacks[t, i, 1:], t + 1)
        reward[t, i] = rng.uniform(0, 1)
        ep_step[i] += 1
        needs_reset[i] = ep_step[i] == lengths[i]  # truncated
  frames = np.stack([[_frame(i, t) for i in range(n)] for t in range(num_steps)])
  return dict(frames=frames, first=first, action=action, reward=reward, stacks=stacks,
              n=n, num_steps=num_steps)


def _reference_valid(sim: dict, ring: int) -> set[tuple[int, int]]:
  """(env, t) of the transitions a buffer with `ring` rows per env may return.

  Stored call indices are the last min(S, ring); a transition t -> t+1 is valid
  if t+1 was added, o_{t+1} does not start an episode, and every frame of the
  env's own stack o_t is still stored.
  """
  s = sim["num_steps"]
  lo = s - min(s, ring)
  out = set()
  for i in range(sim["n"]):
    for t in range(lo, s - 1):
      if not sim["first"][t + 1, i] and sim["stacks"][t, i].min() >= lo:
        out.add((i, t))
  return out


def _fill(sim: dict, ring: int, k: int) -> replay.ReplayBuffer:
  buf = replay.init(ring * sim["n"], sim["n"], (H, W, 3), A, k)
  for t in range(sim["num_steps"]):
    buf = _add(buf, sim["frames"][t], sim["first"][t], sim["action"][t], sim["reward"][t])
  return buf


def _decode(stack: np.ndarray, k: int):
  """(B, H, W, 3k) -> env (B,), frame call indices (B, k); checks the encoding."""
  f = stack.reshape(stack.shape[0], H, W, k, 3).astype(np.int64)
  np.testing.assert_array_equal(f[..., 2], np.arange(H * W).reshape(1, H, W, 1)
                                + np.zeros_like(f[..., 2]))
  env, ts = f[..., 0], f[..., 1]
  assert (env == env[:, :1, :1, :1]).all(), "a stack mixes envs or pixels"
  assert (ts == ts[:, :1, :1, :]).all(), "a frame mixes call indices"
  return env[:, 0, 0, 0], ts[:, 0, 0, :]


CASES = [  # (lengths, num_steps, ring, k)
    pytest.param((5, 3, 4, 6), 30, 40, 3, id="no_wrap"),
    pytest.param((5, 3, 4, 6), 48, 12, 3, id="wrap_k3"),
    pytest.param((2, 3, 5, 1), 40, 9, 4, id="wrap_k4_short_episodes"),
    pytest.param((5, 3, 4), 23, 6, 1, id="wrap_k1"),
    pytest.param((4, 2), 10, 10, 2, id="exactly_full"),
]


@pytest.mark.parametrize("lengths,num_steps,ring,k", CASES)
def test_valid_mask_matches_reference(lengths, num_steps, ring, k):
  sim = _simulate(lengths, num_steps, k)
  ref = _reference_valid(sim, ring)
  buf = _fill(sim, ring, k)
  np.testing.assert_array_equal(buf.count, min(num_steps, ring))
  np.testing.assert_array_equal(buf.pos, num_steps % ring)
  mask = np.zeros((sim["n"], ring), bool)
  for i, t in ref:
    mask[i, t % ring] = True  # call t is written to slot t mod T
  np.testing.assert_array_equal(np.asarray(_valid(buf)), mask)
  assert int(_num_valid(buf)) == len(ref) == replay.check_can_sample(buf)
  if num_steps > ring and k > 1:  # the cases exercise both sides of the stack rule
    lo = num_steps - ring
    cut = [(i, t) for i in range(sim["n"]) for t in range(lo, num_steps - 1)
           if not sim["first"][t + 1, i] and (i, t) not in ref]
    assert cut, "no transition lost to an overwritten frame"
    assert any(t - lo < k - 1 for _, t in ref), "no episode start rescues a stack"


@pytest.mark.parametrize("lengths,num_steps,ring,k", CASES)
def test_samples_are_real_uniform_transitions(lengths, num_steps, ring, k):
  sim = _simulate(lengths, num_steps, k, seed=ring)
  ref = _reference_valid(sim, ring)
  buf = _fill(sim, ring, k)
  draws = max(20_000, 100 * len(ref))
  batches = [_sample(buf, key, batch_size=4096)
             for key in jax.random.split(KEY, math.ceil(draws / 4096))]
  b = jax.tree.map(lambda *x: np.concatenate(x), *batches)
  assert b.obs.dtype == b.next_obs.dtype == np.uint8
  assert b.obs.shape == b.next_obs.shape == (len(b.reward), H, W, 3 * k)
  assert b.action.dtype == b.reward.dtype == b.discount.dtype == np.float32
  env, ts = _decode(b.obs, k)
  env2, next_ts = _decode(b.next_obs, k)
  np.testing.assert_array_equal(env, env2)
  t = ts[:, -1]
  lo = num_steps - min(num_steps, ring)
  assert ts.min() >= lo and next_ts.min() >= lo, "an overwritten frame was sampled"
  assert {(int(i), int(s)) for i, s in zip(env, t)} <= ref, "an invalid transition"
  # Each sample is the env's own transition: stacks, action and reward.
  np.testing.assert_array_equal(ts, sim["stacks"][t, env])
  np.testing.assert_array_equal(next_ts, sim["stacks"][t + 1, env])
  assert not sim["first"][t + 1, env].any(), "o′ starts an episode"
  np.testing.assert_array_equal(b.action, sim["action"][t, env])
  np.testing.assert_array_equal(b.reward, sim["reward"][t, env])
  np.testing.assert_array_equal(b.discount, 1.0)
  # Coverage and uniformity over the valid transitions.
  counts = {}
  for key in zip(env.tolist(), t.tolist()):
    counts[key] = counts.get(key, 0) + 1
  assert set(counts) == ref, f"never sampled: {sorted(ref - set(counts))}"
  c = np.array(list(counts.values()), float)
  expected = len(env) / len(ref)
  chi2, dof = ((c - expected) ** 2 / expected).sum(), len(ref) - 1
  assert abs(chi2 - dof) < 6 * math.sqrt(2 * dof) + 6, (chi2, dof)
  assert np.abs(c - expected).max() < 6 * math.sqrt(expected)


def test_episode_starts_repeat_the_first_frame():
  """Early in an episode o's stack repeats the episode's first frame."""
  k = 4
  sim = _simulate((6, 6), 12, k)
  buf = _fill(sim, 20, k)
  b = _sample(buf, KEY, batch_size=2048)
  _, ts = _decode(np.asarray(b.obs), k)
  _, next_ts = _decode(np.asarray(b.next_obs), k)
  t = ts[:, -1]
  for newest in range(k):  # episode 0 starts at call 0, episode 1 at call 7
    for start in (0, 7):
      rows = ts[t == start + newest]
      assert len(rows), (start, newest)
      want = [max(start, start + newest - d) for d in range(k - 1, -1, -1)]
      np.testing.assert_array_equal(rows, np.broadcast_to(want, rows.shape))
  assert not (t == 6).any() and not (next_ts[:, -1] == 7).any(), "reset step sampled"


def test_empty_and_nearly_empty_buffers():
  buf = replay.init(8, 2, (H, W, 3), A, 2)
  assert int(replay.num_valid(buf)) == 0
  with pytest.raises(ValueError, match="no valid transition"):
    replay.check_can_sample(buf)
  filler = _sample(buf, KEY, batch_size=5)
  np.testing.assert_array_equal(filler.discount, 0.0)
  sim = _simulate((3, 3), 2, 2)
  buf = _add(buf, sim["frames"][0], sim["first"][0], sim["action"][0], sim["reward"][0])
  assert int(replay.num_valid(buf)) == 0  # o′ not written yet
  buf = _add(buf, sim["frames"][1], sim["first"][1], sim["action"][1], sim["reward"][1])
  assert replay.check_can_sample(buf) == 2


def test_init_layout_and_memory_formula():
  n, ring, k, frame = 3, 7, 3, (5, 4, 3)
  buf = replay.init(n * ring + 2, n, frame, A, k)  # the remainder is unused
  assert buf.frames.shape == (n, ring) + frame and buf.frames.dtype == jnp.uint8
  assert buf.action.shape == (n, ring, A) and buf.action.dtype == jnp.float32
  assert buf.reward.shape == buf.first.shape == (n, ring)
  assert buf.first.dtype == jnp.bool_ and buf.reward.dtype == jnp.float32
  assert (buf.num_envs, buf.ring_size, buf.frame_stack) == (n, ring, k)
  assert len(jax.tree.leaves(buf)) == 6  # frame_stack is static
  nbytes = sum(x.nbytes for x in jax.tree.leaves(buf))
  assert nbytes == n * ring * (math.prod(frame) + 4 * A + 4 + 1) + 8 * n  # + pos, count


@pytest.mark.parametrize("kwargs,match", [
    (dict(capacity=7), "frame_stack \\+ 1 = 4"),
    (dict(capacity=0), "capacity must be a positive int"),
    (dict(capacity=8.0), "capacity must be a positive int"),
    (dict(num_envs=0), "num_envs"),
    (dict(num_envs=True), "num_envs"),
    (dict(frame_shape=(4, 4)), "frame_shape must be"),
    (dict(frame_shape=84), "frame_shape must be"),
    (dict(frame_shape=(4, 0, 3)), "frame_shape\\[1\\]"),
    (dict(action_size=0), "action_size"),
    (dict(frame_stack=0), "frame_stack"),
])
def test_init_rejects_bad_arguments(kwargs, match):
  args = dict(capacity=16, num_envs=2, frame_shape=(4, 4, 3), action_size=A, frame_stack=3)
  with pytest.raises(ValueError, match=match):
    replay.init(**(args | kwargs))


def test_add_and_sample_reject_bad_arguments():
  buf = replay.init(16, 2, (H, W, 3), A, 2)
  frame, first = np.zeros((2, H, W, 3), np.uint8), np.ones(2, bool)
  act, rew = np.zeros((2, A), np.float32), np.zeros(2, np.float32)
  with pytest.raises(ValueError, match="frame must have shape"):
    _add(buf, frame[:1], first, act, rew)
  with pytest.raises(ValueError, match="action must have shape"):
    _add(buf, frame, first, act[:, :1], rew)
  with pytest.raises(ValueError, match="first must have shape"):
    _add(buf, frame, first[:, None], act, rew)
  with pytest.raises(ValueError, match="reward must have shape"):
    _add(buf, frame, first, act, rew[:1])
  with pytest.raises(TypeError, match="uint8"):
    _add(buf, frame.astype(np.float32), first, act, rew)
  with pytest.raises(ValueError, match="batch_size"):
    replay.sample(buf, KEY, 0)


def test_jitted_once_and_scan_matches_loop():
  traces = {"add": 0, "sample": 0}

  def add(*a):
    traces["add"] += 1
    return replay.add(*a)

  def sample(buf, key):
    traces["sample"] += 1
    return replay.sample(buf, key, 8)

  add_j, sample_j = jax.jit(add, donate_argnums=0), jax.jit(sample)
  sim = _simulate((3, 4), 15, 2)
  buf = replay.init(2 * 6, 2, (H, W, 3), A, 2)
  for t in range(15):
    buf = add_j(buf, sim["frames"][t], sim["first"][t], sim["action"][t], sim["reward"][t])
  for key in jax.random.split(KEY, 4):
    sample_j(buf, key)
  assert traces == {"add": 1, "sample": 1}

  def body(b, xs):
    return replay.add(b, *xs), None

  xs = tuple(jnp.asarray(sim[f][:15]) for f in ("frames", "first", "action", "reward"))
  scanned, _ = jax.jit(lambda b: jax.lax.scan(body, b, xs))(
      replay.init(2 * 6, 2, (H, W, 3), A, 2))
  jax.tree.map(np.testing.assert_array_equal, scanned, buf)
  assert scanned.frame_stack == buf.frame_stack
