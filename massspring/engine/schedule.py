"""``Schedule``: a model's ``Controls`` written into its run's fields, interval by interval."""

from __future__ import annotations

import numpy as np

from massspring.kernels import state as state_kernels


class Schedule:
    """Writes each interval's pin velocities (``dev.pin_velocity``), wind (``dev.wind``)
    and rest lengths (``dev.l0``) of ``model.controls`` (``massspring.model.controls``) before
    a run's steps enter it. ``model`` is the model the kernels step (renumbered where
    the run renumbers); ``dt`` must divide the interval (ValueError naming ``dt``)."""

    def __init__(self, model, dev, dt):
        controls = model.controls
        self.controls = controls
        self.per = controls.steps_per_interval(dt)
        self.count = controls.intervals
        self.dev = dev
        self.applied = None
        self.n = model.n_particles
        self.fixed = model.fixed
        self.pins = None
        if controls.pin_targets is not None and model.has_fixed:
            self.pins = controls.pin_velocities(model.positions[model.fixed])
        self.rest = None
        if controls.rest_lengths is not None and controls.springs.size:
            self.rest = model.rest_lengths.astype(np.float64)

    def interval(self, step) -> int:
        """The interval step ``step`` (from 0) is in; ``count`` and above: after the last."""
        return min(step // self.per, self.count)

    def steps_left(self, step) -> int:
        """Steps from ``step`` to the next interval's first (None after the last)."""
        if step // self.per >= self.count:
            return None
        return (step // self.per + 1) * self.per - step

    def apply(self, step):
        """The fields for the step from ``step`` (its interval's values), if not already there."""
        s = self.interval(step)
        if s == self.applied:
            return
        held = min(s, self.count - 1)  # wind and rest lengths keep their last values
        if self.pins is not None:
            velocities = np.zeros((self.n, 3))
            if s < self.count:  # after the last interval the pins stay at their last targets
                velocities[self.fixed] = self.pins[s]
            state_kernels.load_vectors(self.dev.pin_velocity, velocities)
        if self.controls.wind is not None:
            self.dev.wind[None] = self.controls.wind[held].tolist()
        if self.rest is not None:
            self.rest[self.controls.springs] = self.controls.rest_lengths[held]
            state_kernels.load_reals(self.dev.l0, self.rest)
        self.applied = s
