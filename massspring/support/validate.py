"""Checks of user-given arguments, shared by the API and the CLI.

Each raises ``ValueError`` whose message starts with the argument's name.
"""

from __future__ import annotations

import math
import numbers
import sys

import numpy as np

from massspring.support.text import brief

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


# Largest magnitude accepted for any input number (and 1 / smallest mass): squares
# and products of a few inputs, which the kernels form (energies, momenta, b.b in
# the implicit solve), then stay within the float64 range (1.8e308).
MAX_MAGNITUDE = 1e100


def real_array(name, value):
    """``value`` as a float64 array of finite real numbers of magnitude <= MAX_MAGNITUDE.

    Refuses what numpy would silently convert: bools, complex numbers (the imaginary
    part would be dropped), strings of digits, None and other objects.
    """
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: cannot be read as an array of numbers ({exc})") from None
    if arr.dtype.kind not in "iuf":
        what = {"b": "bools", "c": "complex numbers", "U": "strings", "S": "strings"}.get(arr.dtype.kind)
        raise ValueError(f"{name}: expected real numbers, got " + (what or f"{brief(value, 40)}"))
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"{name}: contains a non-finite value (NaN or Inf) at index {tuple(int(b) for b in bad)}")
    if arr.size and np.abs(arr).max() > MAX_MAGNITUDE:
        bad = np.unravel_index(int(np.argmax(np.abs(arr))), arr.shape)
        raise ValueError(f"{name}: {arr[bad]:g} at index {tuple(int(b) for b in bad)} is beyond the accepted "
                         f"magnitude {MAX_MAGNITUDE:g} (products of such values overflow float64)")
    return arr


def real_number(name, value, low=None, low_text=""):
    """One real number with ``real_array``'s checks; ``> low`` or ``>= low`` (``low_text``)
    when ``low`` is given."""
    arr = real_array(name, value)
    if arr.ndim != 0:
        raise ValueError(f"{name}: expected a number, got shape {arr.shape}")
    out = float(arr)
    if low is not None and not (out > low if low_text == ">" else out >= low):
        raise ValueError(f"{name}: must be {low_text} {low:g}, got {out:g}")
    return out
