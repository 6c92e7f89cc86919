"""Checks of user-supplied numbers shared by every config: one line naming the field, its value
and what was expected (NaN and inf never pass)."""

from __future__ import annotations

from typing import Any, Mapping, NamedTuple, Sequence

# Counters on the device are int32 (the train state's iteration, each env slot's step count).
MAX_INT32 = 2**31 - 1


def _text(x: Any) -> str:
  """A bound as it reads best in a message: ints in full, floats short (``1e+06``, ``0.5``)."""
  return str(x) if isinstance(x, int) else f"{x:g}"


def check_number(name: str, value: Any, low: float, high: float, unit: str = "",
                 open_low: bool = False) -> None:
  """Checks that ``value`` lies in ``[low, high]`` (``(low, high]`` with ``open_low``); NaN never
  does, and inf does not either, the bounds being finite.

  Raises:
    ValueError: ``'<name> must be in [low, high] <unit>, got <value>'``.
  """
  inside = low < value <= high if open_low else low <= value <= high
  if not inside:
    interval = f"{'(' if open_low else '['}{_text(low)}, {_text(high)}]"
    raise ValueError(f"{name} must be in {interval}{' ' + unit if unit else ''}, got {value}")


def check_range(name: str, value: Any, low: float, high: float, unit: str = "",
                open_low: bool = False) -> None:
  """Checks that ``value`` is a range ``(lo, hi)`` with ``low <= lo <= hi <= high`` (``low < lo``
  with ``open_low``); NaN is never in it.

  Raises:
    ValueError: ``'<name> must be a range (lo, hi) with low <= lo <= hi <= high <unit>, got
      <value>'``.
  """
  ok = len(value) == 2 and (low < value[0] if open_low else low <= value[0])
  if not (ok and value[0] <= value[1] <= high):
    rule = f"{_text(low)} {'<' if open_low else '<='} lo <= hi <= {_text(high)}"
    raise ValueError(f"{name} must be a range (lo, hi) with {rule}{' ' + unit if unit else ''}, "
                     f"got {value}")


class Bound(NamedTuple):
  """The sane bounds of one config field: a number in ``[low, high]`` (``(low, high]`` with
  ``open_low``) or, with ``pair``, a range ``(lo, hi)`` within them with ``lo <= hi``. A field
  whose value is None (where the type allows it: "the robot's", "the run's") is not checked."""

  field: str
  low: float
  high: float
  unit: str = ""
  open_low: bool = False
  pair: bool = False


def check_bounds(config: Any, bounds: Sequence[Bound],
                 labels: Mapping[str, str] | None = None) -> None:
  """Checks each field of ``config`` that ``bounds`` names against its :class:`Bound`.

  Args:
    config: a config dataclass.
    bounds: its table of bounds.
    labels: how to name a field in the message (a command line passes its flags, e.g.
      ``{'num_episodes': '--episodes'}``); a field not in it is named as it is.

  Raises:
    ValueError: one line naming the field, its value and what was expected.
  """
  for b in bounds:
    value = getattr(config, b.field)
    if value is None:
      continue
    name = (labels or {}).get(b.field, b.field)
    check = check_range if b.pair else check_number
    check(name, value, b.low, b.high, b.unit, b.open_low)
