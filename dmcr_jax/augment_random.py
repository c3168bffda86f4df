"""Counter-based random words for the augmentations, a function of a per-sample key.

A key's bits are hashed (Wellons' "lowbias32") into uint32 words, which give
uniform integers and floats and rounded Gaussian noise by exact integer arithmetic,
so a key gives the same draws on every backend and in NumPy.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np


def _key_words(key: jax.Array) -> jax.Array:
  """The raw uint32 words of a key (typed `jax.random.key` or raw `PRNGKey`)."""
  if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
    key = jax.random.key_data(key)
  return jnp.ravel(key).astype(jnp.uint32)


def _words(key: jax.Array, n: int) -> jax.Array:
  """n pseudo-random uint32 words, a hash of the (per-sample) key's bits.

  Word j is ``_hash32(_hash32(k0 + j·0x9E3779B9) ^ k1) …`` over the key's words
  k0, k1, …: far cheaper to compile and run than a threefry call per sample,
  and the per-sample key itself comes from `jax.random.fold_in`.
  """
  kw = _key_words(key)
  w = _hash32(kw[0] + jnp.arange(n, dtype=jnp.uint32) * jnp.uint32(0x9E3779B9))
  for i in range(1, kw.shape[0]):
    w = _hash32(w ^ kw[i])
  return w


def _randint(word: jax.Array, lo, hi) -> jax.Array:
  """An int32 in [lo, hi) from a uint32 word: lo + ((word >> 16) · (hi − lo)) >> 16.

  Exact integer arithmetic (hi − lo ≤ 2^16; `lo`, `hi` may be traced); every value
  has probability (hi − lo)^-1 to within 2^-16.
  """
  span = jnp.asarray(hi - lo).astype(jnp.uint32)
  return jnp.asarray(lo, jnp.int32) + (((word >> 16) * span) >> 16).astype(jnp.int32)


def _unit(word: jax.Array) -> jax.Array:
  """A float32 in [0, 1) from a uint32 word (its top 24 bits)."""
  return (word >> 8).astype(jnp.float32) * jnp.float32(2.0 ** -24)


def _hash32(x: jax.Array) -> jax.Array:
  """A 32-bit integer hash (Wellons' "lowbias32"), elementwise on uint32."""
  x = x ^ (x >> 16)
  x = x * jnp.uint32(0x7FEB352D)
  x = x ^ (x >> 15)
  x = x * jnp.uint32(0x846CA68B)
  return x ^ (x >> 16)


@functools.lru_cache(maxsize=None)
def _rounded_gaussian_thresholds(std: float) -> tuple[int, np.ndarray]:
  """(K, T): P(round(N(0, std²)) ≤ k) · 2^16 for k = −K … K−1, rounded."""
  k_max = max(1, math.ceil(6 * std))
  ks = np.arange(-k_max, k_max)
  cdf = np.array([0.5 * (1 + math.erf((k + 0.5) / (std * math.sqrt(2)))) for k in ks])
  return k_max, np.round(cdf * 65536).astype(np.uint32)


def _rounded_gaussian(seed: jax.Array, shape: tuple[int, ...], std: float) -> jax.Array:
  """Int32 noise round(N(0, std²)), clipped to ±⌈6·std⌉, a function of `seed`.

  Element ``i`` (row-major) takes the top 16 bits of
  ``_hash32(_hash32(i) ^ seed)`` through the inverse CDF of the rounded normal:
  exact integer arithmetic, cheap on any backend (no erf_inv), reproducible in
  NumPy.
  """
  k_max, thresholds = _rounded_gaussian_thresholds(float(std))
  idx = jnp.arange(math.prod(shape), dtype=jnp.uint32)
  u = (_hash32(_hash32(idx) ^ seed) >> 16)[:, None]
  n = jnp.sum(u >= jnp.asarray(thresholds)[None, :], axis=1, dtype=jnp.int32)
  return (n - k_max).reshape(shape)
