"""Particles and springs in a cache-friendly order, chosen once per model.

A spring pass reads both ends' positions and velocities, and each particle then
gathers its springs' forces; a CG product does the same. When the particles of a
spring lie far apart in memory, or consecutive springs jump across the particle
arrays, every spring misses the cache: a cloth whose particles came in a scrambled
order (a mesh exported by a tool that does not keep vertex locality) takes 1.3-4.9x
as long per symplectic step as the same cloth in grid order
(``benchmarks/ordering.py``).

``plan`` measures the model's order (``far_share``) and, when it is poor, builds a
copy of the model in Z-order (Morton order) of the initial positions, with the
springs sorted by their lower new end. ``Simulation`` steps that copy and maps every
array at its edges (positions, velocities, a restart's state) back to the user's
order, so the reordering is invisible to the API: only ``Simulation.info()["order"]``
tells. Models whose order is already good (the built-in grids, meshes from most
meshers) are stepped as given, to the bit as before.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from massspring.model import Model

WINDOW = 4096     # particles: two indices further apart than this are "far" (48 KB-196 KB of state)
FAR_SHARE = 0.05  # reorder when more than this share of accesses is far, and Z-order halves it
MORTON_BITS = 21  # per axis: 63-bit codes
_PLANS = weakref.WeakKeyDictionary()  # model -> ((WINDOW, FAR_SHARE), its plan): one per model


def far_share(springs, window) -> float:
    """The share of a spring pass's accesses that jump by more than ``window`` particles:
    springs whose two ends are that far apart, plus consecutive springs whose first
    ends are, over 2 m. springs: (m, 2) int."""
    m = len(springs)
    if m == 0:
        return 0.0
    ends = np.abs(springs[:, 0] - springs[:, 1]) > window
    steps = np.abs(np.diff(springs[:, 0])) > window
    return float(ends.sum() + steps.sum()) / (2 * m)


def morton_order(positions, bits=MORTON_BITS) -> np.ndarray:
    """Indices that sort ``positions`` ((n, 3) float, m) along a Z-order curve of
    their bounding cube, cut into 2**bits cells per axis (ties in input order)."""
    x = np.asarray(positions, dtype=np.float64)
    low = x.min(axis=0)
    extent = float((x.max(axis=0) - low).max())
    scale = (2**bits - 1) / extent if extent > 0 else 0.0
    cells = np.minimum((x - low) * scale, 2**bits - 1).astype(np.uint64)
    code = np.zeros(len(x), dtype=np.uint64)
    one = np.uint64(1)
    for bit in range(bits):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & one) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


@dataclass(frozen=True)
class Ordering:
    """A model renumbered: ``model`` is the copy the kernels step, ``particles[k]`` the
    user's index of its particle k (``inverse`` the other way), ``springs[k]`` the
    user's index of its spring k."""

    model: Model
    particles: np.ndarray
    inverse: np.ndarray
    springs: np.ndarray

    def to_inner(self, rows):
        """Rows in the user's particle order -> the copy's."""
        return np.ascontiguousarray(rows[self.particles])

    def to_user(self, rows):
        """Rows in the copy's particle order -> the user's."""
        return np.ascontiguousarray(rows[self.inverse])


def renumbered(model: Model, particles, springs) -> Model:
    """``model`` with its particle k being ``model``'s particle ``particles[k]`` and its
    spring k being spring ``springs[k]`` (both permutations, int arrays); every array
    that holds particle indices (springs, fixed, triangles) is mapped to the new
    numbering, pin velocities and keyframes follow their pins, actuated springs theirs."""
    inverse = _inverse(particles)
    controls, pins = model.controls, model.pin_velocity
    if controls is not None:
        controls = controls.renumbered(np.argsort(inverse[model.fixed], kind="stable"), _inverse(springs))
        if controls.pin_targets is not None:
            pins = None  # the keyframes' first velocities, as the model derived them
    return model.replaced(positions=model.positions[particles], springs=inverse[model.springs][springs],
                          masses=model.masses[particles], stiffness=model.stiffness[springs],
                          damping=model.damping[springs], rest_lengths=model.rest_lengths[springs],
                          velocities=model.velocities[particles], fixed=inverse[model.fixed],
                          triangles=inverse[model.triangles], pin_velocity=pins, controls=controls)


def plan(model: Model) -> Ordering | None:
    """The renumbered copy of ``model`` if its order is poor (``far_share`` above
    ``FAR_SHARE``) and Z-order at least halves the share; else None. Made once per
    model (0.03 s at 16,384 particles, 0.6 s at 262,144) and kept while the model
    lives, so a sweep's runs of one model share it."""
    limits = (WINDOW, FAR_SHARE)
    kept = _PLANS.get(model)
    if kept is not None and kept[0] == limits:
        return kept[1]
    result = _plan(model)
    _PLANS[model] = (limits, result)
    return result


def wanted(model: Model) -> bool:
    """Whether ``plan`` will try to renumber ``model`` (its ``far_share`` is above
    ``FAR_SHARE``): then a run builds a copy of the model's arrays."""
    return _poor(far_share(model.springs, WINDOW))


def _poor(share):
    return share > FAR_SHARE


def _inverse(permutation):
    """The inverse of a permutation (int array)."""
    inverse = np.empty_like(permutation)
    inverse[permutation] = np.arange(len(permutation))
    return inverse


def _plan(model):
    given = far_share(model.springs, WINDOW)
    if not _poor(given):
        return None
    particles = morton_order(model.positions)
    inverse = _inverse(particles)
    ends = inverse[model.springs]
    low, high = np.minimum(ends[:, 0], ends[:, 1]), np.maximum(ends[:, 0], ends[:, 1])
    springs = np.argsort(low * len(particles) + high, kind="stable")
    if far_share(ends[springs], WINDOW) > 0.5 * given:
        return None
    return Ordering(renumbered(model, particles, springs), particles, inverse, springs)
