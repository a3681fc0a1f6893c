"""Checks of user-given arguments, shared by the API and the CLI.

Each raises ``ValueError`` whose message starts with the argument's name.
"""

from __future__ import annotations

import math
import numbers
import sys

from massspring.text import brief

MAX_INT32 = 2**31 - 1  # kernels count in int32


def positive_float(name, value) -> float:
    """A finite number > 0 (not a bool or string), no smaller than the smallest normal
    float (a subnormal one loses its digits and its inverse overflows)."""
    if isinstance(value, (bool, str)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name}: expected a number, got {value!r}")
    try:
        out = float(value)
    except OverflowError:
        raise ValueError(f"{name}: {brief(value)} is beyond the range of a number") from None
    if not math.isfinite(out) or out <= 0:
        raise ValueError(f"{name}: must be a finite number > 0, got {brief(value)}")
    if out < sys.float_info.min:
        raise ValueError(f"{name}: {value!r} is below the smallest normal number ({sys.float_info.min:.3g})")
    return out


def fraction(name, value) -> float:
    """A number in (0, 1)."""
    out = positive_float(name, value)
    if out >= 1:
        raise ValueError(f"{name}: must be < 1, got {value!r}")
    return out


def count(name, value, low=1, high=MAX_INT32) -> int:
    """An integer (not a bool) within [low, high]."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not low <= value <= high:
        raise ValueError(f"{name}: expected an integer within {low}..{high}, got {value!r}")
    return int(value)


def choice(name, value, options):
    """One of ``options``."""
    if value not in options:
        raise ValueError(f"{name}: unknown value {value!r}, expected one of {', '.join(options)}")
    return value
