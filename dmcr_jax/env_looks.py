"""The render-pool env's looks: each env's static look, kept between steps, moving or not.

An env's static look is a function of its visual seed and the factors it varies
alone (`RenderModel.sample`, the seed's `VisualParams`; `render_model.prepare`, the
host arrays the render workers write into MuJoCo's model). `StaticLooks` holds N
envs' static looks, both forms, with the seeds and factors they were made for;
`static_looks` brings one up to date for the envs' current seeds and factors,
sampling again only when one of them changed and preparing only the envs whose
look changed. A static env draws `StaticLooks.looks`; a moving env draws
`visuals.moving.look_at` of `StaticLooks.params` at each env's episode step.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from dmcr_jax.visuals import render_model as rmod
from dmcr_jax.visuals.params import VisualParams


def vary_key(vary) -> str | tuple:
  """A `vary` value as a hashable key (a sequence of factors as a tuple; a string
  or None as it is); the key is itself a valid `vary`, naming the same factors."""
  return vary if vary is None or isinstance(vary, str) else tuple(vary)


@dataclasses.dataclass(frozen=True)
class StaticLooks:
  """N envs' static looks and what they were made from.

  Attributes:
    seeds: int32 (N,) each env's visual seed.
    varies: N `vary_key`s, each env's factors.
    params: `VisualParams` (N,) of those seeds under those factors, as
      `RenderModel.sample` returns them (device arrays).
    looks: `render_model.Looks` (N,), `prepare` of `params` (host arrays).
  """
  seeds: np.ndarray
  varies: tuple
  params: VisualParams
  looks: rmod.Looks


def _sample(rm: rmod.RenderModel, seeds: np.ndarray, varies: tuple) -> VisualParams:
  """`rm.sample` of each env's seed under its own factors: one call per distinct
  factors, the rows put back in the envs' order."""
  groups = dict.fromkeys(varies)
  if len(groups) == 1:
    return rm.sample(seeds, vary=varies[0])
  rows = [np.flatnonzero([v == key for v in varies]) for key in groups]
  parts = [rm.sample(seeds[r], vary=key) for r, key in zip(rows, groups)]
  order = np.argsort(np.concatenate(rows), kind="stable")
  return jax.tree.map(lambda *xs: jnp.concatenate(xs)[order], *parts)


def static_looks(rm: rmod.RenderModel, seeds, varies: Sequence,
                 cached: StaticLooks | None = None) -> StaticLooks:
  """N envs' static looks for visual seeds `seeds` under factors `varies`.

  Args:
    rm: the render pool's `RenderModel` (its domain and texture bank).
    seeds: int (N,) visual seeds.
    varies: N `vary_key`s, one per env.
    cached: the envs' previous `StaticLooks`, or None.

  Returns:
    `cached` itself when no env's seed or factors changed; else new
    `StaticLooks`, whose prepared looks are `cached`'s for the envs that kept
    their seed and factors (a look depends on those alone).
  """
  seeds = np.asarray(seeds, np.int32)
  varies = tuple(varies)
  same_size = cached is not None and len(cached.seeds) == len(seeds)
  if same_size and cached.varies == varies and np.array_equal(cached.seeds, seeds):
    return cached
  params = _sample(rm, seeds, varies)
  if not same_size:
    return StaticLooks(seeds.copy(), varies, params, rmod.prepare(rm, params))
  changed = seeds != cached.seeds
  if cached.varies != varies:
    changed |= np.array([a != b for a, b in zip(varies, cached.varies)])
  rows = np.flatnonzero(changed)
  if len(rows) == len(seeds):
    return StaticLooks(seeds.copy(), varies, params, rmod.prepare(rm, params))
  new = rmod.prepare(rm, params.take(rows))
  looks = {}
  for f in dataclasses.fields(rmod.Looks):
    looks[f.name] = getattr(cached.looks, f.name).copy()
    looks[f.name][rows] = getattr(new, f.name)
  return StaticLooks(seeds.copy(), varies, params, rmod.Looks(**looks))
