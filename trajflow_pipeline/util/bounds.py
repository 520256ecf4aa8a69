"""The numbers a setting accepts, declared next to it (:func:`bounded`) and checked by one rule (:func:`check_value`).

Config fields (:mod:`trajflow_pipeline.model.config`) and every command option that is a seed use it, so a NaN
learning rate, a negative weight decay or a seed torch cannot take is a one-line UsageError before any work.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..errors import UsageError

#: The largest integer a setting may hold: TOML integers (config.toml) and the report's Int64 columns are 64-bit.
INT_MAX = 2**63 - 1


@dataclass(frozen=True)
class Bounds:
    """The values a numeric setting accepts: finite, within 64-bit integers for an integer, and inside the limits
    given (None: no limit on that side; ge / le inclusive, gt / lt exclusive)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def admits(self, value: int | float) -> bool:
        """Whether `value` is finite and within the bounds (and within 64-bit integers when it is an int)."""
        if isinstance(value, int) and not -INT_MAX - 1 <= value <= INT_MAX:
            return False
        return (math.isfinite(value) and (self.ge is None or value >= self.ge) and (self.gt is None or value > self.gt)
                and (self.le is None or value <= self.le) and (self.lt is None or value < self.lt))

    def describe(self, integer: bool) -> str:
        """The accepted values in words: "an integer from 0 to 9223372036854775807", "a finite number > 0"."""
        kind = "an integer" if integer else "a finite number"
        if self.ge is not None and self.le is not None:
            return f"{kind} from {_number(self.ge)} to {_number(self.le)}"
        limits = [f"{sign} {_number(limit)}" for sign, limit in ((">=", self.ge), (">", self.gt), ("<=", self.le),
                                                                  ("<", self.lt)) if limit is not None]
        return f"{kind} {' and '.join(limits)}" if limits else kind


#: The bounds of a setting that declares none: any finite number (any 64-bit integer).
UNBOUNDED = Bounds()
#: A seed: torch takes seeds up to 2**64 - 1 and numpy any non-negative integer, but a seed is also written to TOML
#: and to Int64 tables, so 0 .. 2**63 - 1.
SEED = Bounds(ge=0, le=INT_MAX)


def bounded(default: Any, *, ge: float | None = None, gt: float | None = None, le: float | None = None,
            lt: float | None = None, bounds: Bounds | None = None) -> Any:
    """A dataclass field with `default` whose values must lie within the bounds (`bounds`, or those the keywords
    give); for a tuple-valued field every item must. See :func:`check_value`."""
    return field(default=default, metadata={"bounds": bounds or Bounds(ge=ge, gt=gt, le=le, lt=lt)})


def check_value(value: Any, metadata: Mapping[str, Any] | Bounds, key: str, source: str | None = None) -> None:
    """Refuse (UsageError naming `source` when given, `key` and the value) a number, or an item of a tuple, outside
    the bounds: `metadata` is a field's metadata (:func:`bounded`; none declared: :data:`UNBOUNDED`) or the bounds.
    Values of other types pass: their type is checked where they are read."""
    bounds = metadata if isinstance(metadata, Bounds) else metadata.get("bounds", UNBOUNDED)
    for number in value if isinstance(value, tuple) else (value,):
        if isinstance(number, (int, float)) and not isinstance(number, bool) and not bounds.admits(number):
            where = f"{source}: " if source else ""
            each = "each item of " if isinstance(value, tuple) else ""
            huge = isinstance(number, int) and not -INT_MAX - 1 <= number <= INT_MAX
            raise UsageError(f"{where}{each}{key} must be {bounds.describe(isinstance(number, int))}, got "
                             f"{_shown(value)}" + (" (beyond the 64-bit integers TOML holds)" if huge else ""))


def check_seed(value: Any, name: str) -> int:
    """`value` as a seed, refused (UsageError naming the option `name`) unless it is an integer within
    :data:`SEED`: every command that takes a seed checks it by this rule, as train.seed is."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise UsageError(f"{name} must be an integer, got {_shown(value)}")
    check_value(value, SEED, name)
    return value


def _number(limit: float) -> str:
    return str(int(limit)) if float(limit).is_integer() else repr(limit)


def _shown(value: Any) -> str:
    """A value as a message shows it: lists as TOML writes them, numbers as Python does (nan, inf)."""
    return "[" + ", ".join(map(_shown, value)) + "]" if isinstance(value, (list, tuple)) else repr(value)
