"""Time-varying inputs of a run: keyframed pins, wind and rest lengths per interval.

A :class:`Controls` cuts time into intervals of ``interval`` seconds; interval s covers
[s T, (s + 1) T) and holds one value of each control given:

- ``pin_targets`` (S, k, 3) m: where the pinned particles are at the end of each
  interval (a row per pin in the order of ``Model.fixed``). A pin moves in a straight
  line at the constant velocity (P_s - P_{s-1}) / T over interval s, from its model
  position P_{-1}, and stays at its last target after the last interval. (A pin's
  velocity in the state is the one it last moved with, its first interval's at the
  start: ``Model.pin_velocity``.)
- ``wind`` (S, 3) m/s: the drag term's wind over each interval (a model with drag).
- ``rest_lengths`` (S, c) m of the springs ``springs`` (c,) (user numbering): the
  actuated springs' rest lengths over each interval (DiffTaichi's robots).

Wind and rest lengths keep their last values after the last interval. A run steps
with them when ``T`` is a whole number of its steps (``Simulation`` refuses other
``dt``); ``massspring.gradient`` gives their gradients as "controls.pin_targets",
"controls.wind" and "controls.rest_lengths", arrays shaped like them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from massspring.support import validate
from massspring.support.validate import real_array

STEP_TOLERANCE = 1e-9  # relative: how close interval / dt must be to a whole number
NAMES = ("pin_targets", "wind", "rest_lengths")  # the controls' arrays, what "controls.<name>" names


@dataclass(frozen=True, eq=False)
class Controls:
    """Keyframed pins, wind and spring rest lengths per interval (see the module).

    Parameters
    ----------
    interval : float > 0, s
    pin_targets : None or (S, k, 3) float, m
    wind : None or (S, 3) float, m/s
    springs : None or (c,) int, the actuated springs (distinct indices)
    rest_lengths : None or (S, c) float >= 0, m (with ``springs``)

    Every array given has the same S >= 1. Checked here for shapes and values, and by
    the ``Model`` it is given to against its pins, springs and drag.
    """

    interval: float
    pin_targets: np.ndarray | None = None
    wind: np.ndarray | None = None
    springs: np.ndarray | None = None
    rest_lengths: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "interval", validate.positive_float("controls.interval", self.interval))
        counts = {}
        for name, ndim, last in (("pin_targets", 3, 3), ("wind", 2, 3), ("rest_lengths", 2, None)):
            value = getattr(self, name)
            if value is None:
                continue
            arr = real_array(f"controls.{name}", value)
            if arr.ndim != ndim or arr.shape[0] < 1 or (last is not None and arr.shape[-1] != last):
                shape = {"pin_targets": "(S, k, 3)", "wind": "(S, 3)", "rest_lengths": "(S, c)"}[name]
                raise ValueError(f"controls.{name}: expected shape {shape} with S >= 1 intervals, got {arr.shape}")
            counts[name] = arr.shape[0]
            object.__setattr__(self, name, _readonly(arr.copy()))
        if not counts:
            raise ValueError("controls: give at least one of pin_targets, wind, rest_lengths")
        if len(set(counts.values())) > 1:
            raise ValueError(f"controls: every array must have the same number of intervals, got "
                             + ", ".join(f"{name} {count}" for name, count in counts.items()))
        if (self.springs is None) != (self.rest_lengths is None):
            raise ValueError("controls: springs and rest_lengths go together (the actuated springs and their "
                             "rest lengths per interval)")
        if self.springs is not None:
            try:
                springs = np.asarray(self.springs)
            except ValueError:  # ragged nesting
                raise ValueError(f"controls.springs: expected spring indices (c,) int, got {self.springs!r}") from None
            if springs.ndim != 1 or springs.dtype.kind not in "iu":
                raise ValueError(f"controls.springs: expected spring indices (c,) int, got {springs.dtype} "
                                 f"of shape {springs.shape}")
            if np.unique(springs).size != springs.size:
                raise ValueError("controls.springs: a spring is listed twice")
            if self.rest_lengths.shape[1] != springs.size:
                raise ValueError(f"controls.rest_lengths: expected shape (S, {springs.size}) (one column per "
                                 f"entry of springs), got {self.rest_lengths.shape}")
            if np.any(self.rest_lengths < 0):
                raise ValueError("controls.rest_lengths: rest lengths must be >= 0")
            object.__setattr__(self, "springs", _readonly(springs.astype(np.int64)))

    @property
    def intervals(self) -> int:
        """S, the number of intervals."""
        for name in NAMES:
            value = getattr(self, name)
            if value is not None:
                return value.shape[0]
        raise AssertionError("unreachable: checked in __post_init__")

    def check(self, n_springs, fixed, drag):
        """Checked against a model: its springs (count), its pins (sorted indices) and
        whether it has drag. Raises ValueError naming the array."""
        if self.pin_targets is not None and self.pin_targets.shape[1] != fixed.size:
            raise ValueError(f"controls.pin_targets: expected shape (S, {fixed.size}, 3) (a row per pinned "
                             f"particle of the model), got {self.pin_targets.shape}")
        if self.wind is not None and not drag:
            raise ValueError("controls.wind: the model has no air drag (drag = 0), so wind does nothing; "
                             "give it drag > 0")
        if self.springs is not None and self.springs.size and (self.springs.min() < 0
                                                               or self.springs.max() >= n_springs):
            bad = int(self.springs[(self.springs < 0) | (self.springs >= n_springs)][0])
            raise ValueError(f"controls.springs: spring {bad} is outside 0..{n_springs - 1}")

    def steps_per_interval(self, dt) -> int:
        """Steps of ``dt`` in an interval; ValueError if it is not a whole number."""
        ratio = self.interval / dt
        steps = round(ratio)
        if steps < 1 or abs(ratio - steps) > STEP_TOLERANCE * ratio:
            raise ValueError(f"dt: controls.interval {self.interval:g} s is not a whole number of steps of "
                             f"{dt:g} s")
        return steps

    def pin_velocities(self, start) -> np.ndarray:
        """(S, k, 3) m/s: each pin's velocity over each interval, from its positions
        ``start`` (k, 3) at time 0."""
        ends = self.pin_targets
        begins = np.concatenate([np.asarray(start)[None], ends[:-1]])
        return (ends - begins) / self.interval

    def pin_target_gradient(self, by_velocity) -> np.ndarray:
        """dL/d(pin_targets) from dL/d(pin velocity of each interval) (S, k, 3)."""
        later = np.concatenate([by_velocity[1:], np.zeros_like(by_velocity[:1])])
        return (by_velocity - later) / self.interval

    def speeds(self, start, rest) -> float:
        """What the controls can drive (m/s): the fastest pin or wind of any interval, or
        the fastest change of an actuated rest length (its change over an interval by the
        interval: muscles move the particles they join as a pin would), from the pins'
        positions ``start`` (k, 3) and the model's rest lengths ``rest`` (m,) at time 0."""
        fastest = 0.0
        if self.pin_targets is not None and self.pin_targets.shape[1]:
            fastest = float(np.linalg.norm(self.pin_velocities(start), axis=2).max())
        if self.wind is not None:
            fastest = max(fastest, float(np.linalg.norm(self.wind, axis=1).max()))
        if self.rest_lengths is not None and self.springs.size:
            lengths = np.concatenate([np.asarray(rest)[self.springs][None], self.rest_lengths])
            fastest = max(fastest, float(np.abs(np.diff(lengths, axis=0)).max()) / self.interval)
        return fastest

    def renumbered(self, fixed_order, spring_inverse) -> Controls:
        """These controls for a renumbered model: pin rows in the order ``fixed_order``
        (argsort of the new pins' indices), spring indices mapped by ``spring_inverse``."""
        return Controls(self.interval,
                        None if self.pin_targets is None else self.pin_targets[:, fixed_order],
                        self.wind,
                        None if self.springs is None else spring_inverse[self.springs],
                        self.rest_lengths)

    def digest(self) -> bytes:
        """Bytes that tell these controls apart (``Model.fingerprint``)."""
        parts = [repr(float(self.interval)).encode()]
        for name in ("pin_targets", "wind", "springs", "rest_lengths"):
            value = getattr(self, name)
            parts.append(name.encode() + (b"-" if value is None else np.ascontiguousarray(value).tobytes()))
        return b"|".join(parts)


def _readonly(arr):
    arr.setflags(write=False)
    return arr
