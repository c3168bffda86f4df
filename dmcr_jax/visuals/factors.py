"""Visual factors of variation: names, stable stream ids, and per-domain applicability.

DMCR varies seven factors (paper, Sec. 3 and Table 5): `camera`, `light`, `body`,
`target`, `floor`, `background` and `reflectance`. Each factor draws from its own
random stream, `fold_in(key(seed), FACTOR_IDS[name])`, so switching one factor on
or off never changes the values another factor draws. The ids below are part of
the benchmark's definition: never renumber them (a new factor gets a new id).

Not every factor applies to every domain (Table 5 of the paper): `target` only
to fish and reacher (the only domains with a target), `background` not to fish,
humanoid and reacher (their default cameras do not show the sky in the original
release), and `reflectance` only to cheetah, walker and hopper ("limited effect"
for the latter two, "no" elsewhere). A factor that does not apply is ignored
for that domain: it keeps dm_control's default look.
"""

from __future__ import annotations

from typing import Iterable

FACTORS: tuple[str, ...] = (
    "camera", "light", "body", "target", "floor", "background", "reflectance")

# Column of each factor in `VisualParams.varied` (bool (N, len(FACTORS))).
FACTOR_INDEX: dict[str, int] = {f: i for i, f in enumerate(FACTORS)}

# Stable stream ids for `jax.random.fold_in` (part of the benchmark definition).
FACTOR_IDS: dict[str, int] = {
    "camera": 1, "light": 2, "body": 3, "target": 4, "floor": 5,
    "background": 6, "reflectance": 7,
}

DOMAINS: tuple[str, ...] = (
    "ball_in_cup", "cartpole", "cheetah", "finger", "fish", "hopper", "humanoid",
    "pendulum", "reacher", "walker")

_ALWAYS = frozenset({"camera", "light", "body", "floor"})

# The paper's Table 5 ("Limited Effect" counts as applicable).
APPLICABLE: dict[str, frozenset[str]] = {
    "cheetah": _ALWAYS | {"background", "reflectance"},
    "walker": _ALWAYS | {"background", "reflectance"},
    "hopper": _ALWAYS | {"background", "reflectance"},
    "cartpole": _ALWAYS | {"background"},
    "finger": _ALWAYS | {"background"},
    "pendulum": _ALWAYS | {"background"},
    "fish": _ALWAYS | {"target"},
    "humanoid": _ALWAYS,
    "ball_in_cup": _ALWAYS | {"background"},
    "reacher": _ALWAYS | {"target"},
}


def check_domain(domain: str) -> str:
  """Validates a domain name (a task name like "walker-walk" is also accepted).

  Args:
    domain: a DMCR domain such as "walker", or a task name "walker-walk".

  Returns:
    The domain name.

  Raises:
    ValueError: if it is not one of the ten DMCR domains (the message lists them).
  """
  if isinstance(domain, str) and "-" in domain:
    domain = domain.split("-", 1)[0]
  if domain not in APPLICABLE:
    raise ValueError(
        f"Unknown domain {domain!r}. Valid domains: {', '.join(DOMAINS)}.")
  return domain


def parse_vary(vary: str | Iterable[str] | None) -> frozenset[str]:
  """Parses a `vary` argument into a set of factor names.

  Args:
    vary: "all", "none" (or None / an empty iterable), a comma-separated string
      such as "floor,background", or an iterable of factor names. Names are
      case-insensitive; surrounding spaces are ignored.

  Returns:
    The requested factors as a frozenset (not yet filtered by domain).

  Raises:
    ValueError: for an unknown factor name (the message lists the valid ones).
    TypeError: if `vary` is neither a string nor an iterable of strings.
  """
  if vary is None:
    return frozenset()
  if isinstance(vary, str):
    items = [s for s in (p.strip().lower() for p in vary.split(",")) if s]
  else:
    try:
      items = list(vary)
    except TypeError:
      raise TypeError(
          f"vary must be 'all', 'none', a comma-separated string or an iterable "
          f"of factor names, got {vary!r}.") from None
    if not all(isinstance(s, str) for s in items):
      raise TypeError(f"vary must contain factor names (strings), got {vary!r}.")
    items = [s.strip().lower() for s in items]
  if items == ["all"]:
    return frozenset(FACTORS)
  if items in ([], ["none"]):
    return frozenset()
  unknown = [s for s in items if s not in FACTOR_IDS]
  if unknown:
    raise ValueError(
        f"Unknown visual factor(s) {', '.join(map(repr, unknown))}. Valid "
        f"factors: {', '.join(FACTORS)} (or 'all' / 'none').")
  return frozenset(items)


def active_factors(domain: str, vary: str | Iterable[str] | None) -> frozenset[str]:
  """The factors that `vary` switches on and that apply to `domain` (Table 5).

  Args:
    domain: a DMCR domain (or task name).
    vary: as for `parse_vary`.

  Returns:
    The factors that will actually vary for this domain.
  """
  return parse_vary(vary) & APPLICABLE[check_domain(domain)]


def check_vary(domain: str, vary: str | Iterable[str] | None) -> frozenset[str]:
  """`active_factors` for a `vary` a user passes (`make`, `set_visuals`, `train`):
  an empty string and named factors that do not apply to `domain` are refused.

  Raises:
    ValueError: naming the problem and the domain's factors.
  """
  domain = check_domain(domain)
  own = ", ".join(f for f in FACTORS if f in APPLICABLE[domain])
  if isinstance(vary, str) and not vary.strip():
    raise ValueError(f"vary is empty: pass 'none' (dm_control's look), 'all' or factor "
                     f"names; {domain}'s factors: {own}")
  requested = parse_vary(vary)
  missing = [f for f in FACTORS if f in requested - APPLICABLE[domain]]
  if missing and requested != frozenset(FACTORS):
    raise ValueError(f"vary: {', '.join(missing)} do(es) not apply to {domain} (the "
                     f"paper's Table 5); {domain}'s factors: {own} (or 'all' / 'none')")
  return requested & APPLICABLE[domain]
