"""``Model(strain_limit=s)``'s value checked (the pass that applies it: ``massspring.passes.strain_limit``)."""

from __future__ import annotations

import math

import numpy as np


def check(value, n_springs):
    """``Model``'s ``strain_limit``: None, or a finite number > 0 (the largest l / l0 - 1);
    ValueError naming ``strain_limit`` otherwise."""
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"strain_limit: expected None or a number > 0 (the largest stretch l / l0 - 1), "
                         f"got {value!r}")
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"strain_limit: must be a finite number > 0 (the largest stretch l / l0 - 1), got {value!r}")
    if n_springs == 0:
        raise ValueError("strain_limit: the model has no springs to limit")
    return value
