"""Self-collision of a model's triangle mesh: its settings and the mesh's edges.

``SelfCollision(thickness, friction=0.0, stiffness=None)`` turns it on:
``Model(..., triangles=..., self_collision=SelfCollision(0.005))``, or a scene's
``[self_collision]`` table with the same fields. Fields:

* ``thickness`` (m, > 0): pairs of the mesh closer than this repel each other;
* ``friction``: the Coulomb coefficient mu >= 0 between touching parts of the mesh;
* ``stiffness`` (N/m, > 0, or None: the median spring stiffness of the model): the
  repulsion spring that pushes a pair closer than ``thickness`` apart.

A frozen dataclass validated in its constructor; a bad field raises ``ValueError``
naming it. What a step does with it is in ``kernels/self_collision.py``: the guarantee
is that a step which starts with no edge of the mesh through a triangle it shares
no vertex with ends with none either (pinned particles held still).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from massspring.support.validate import real_number


@dataclass(frozen=True)
class SelfCollision:
    """Self-collision of the mesh: ``thickness`` (m), ``friction`` (mu), ``stiffness``
    (N/m, None: the model's median spring stiffness). See the module docstring."""

    thickness: float
    friction: float = 0.0
    stiffness: float | None = None

    def __post_init__(self):
        thickness = real_number("thickness", self.thickness, 0.0, ">")
        friction = real_number("friction", self.friction, 0.0, ">=")
        stiffness = None if self.stiffness is None else real_number("stiffness", self.stiffness, 0.0, ">")
        object.__setattr__(self, "thickness", thickness)
        object.__setattr__(self, "friction", friction)
        object.__setattr__(self, "stiffness", stiffness)

    def repulsion_stiffness(self, model) -> float:
        """``stiffness``, or the median spring stiffness of ``model`` (1 N/m without springs)."""
        if self.stiffness is not None:
            return self.stiffness
        positive = model.stiffness[model.stiffness > 0]
        return float(np.median(positive)) if positive.size else 1.0


def mesh_edges(triangles) -> np.ndarray:
    """(e, 2) int64: the distinct edges of ``triangles`` ((t, 3) particle indices), each
    as (low, high) index, sorted."""
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    pairs = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    pairs.sort(axis=1)
    return np.unique(pairs, axis=0) if len(pairs) else np.zeros((0, 2), dtype=np.int64)


SPACING_FRACTION = 0.5  # a thickness above this fraction of the mesh's spacing is refused


def mesh_spacing(positions, triangles) -> float:
    """The mesh's spacing (m): the median over its triangles of their smallest height
    (twice the area over the longest side) at ``positions`` (n, 3); 0 if that is 0 (no
    triangle, or most of them degenerate). A particle of a flat or gently curved mesh is
    about this far from the nearest triangle it is not a corner of (h / sqrt(2) on a
    grid of spacing h)."""
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(tris) == 0:
        return 0.0
    x = np.asarray(positions, dtype=np.float64)
    a, b, c = x[tris[:, 0]], x[tris[:, 1]], x[tris[:, 2]]
    twice_area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    longest = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                      np.linalg.norm(a - c, axis=1)], axis=0)
    heights = np.divide(twice_area, longest, out=np.zeros_like(twice_area), where=longest > 0)
    return float(np.median(heights))


def check_thickness(settings, positions, triangles):
    """ValueError naming ``thickness`` and the mesh's spacing if ``settings.thickness``
    is above ``SPACING_FRACTION`` of ``mesh_spacing``: every particle would then be
    within the thickness of the triangles next to its own, repelled by them at rest,
    and the pass would list pairs by the hundred per particle."""
    spacing = mesh_spacing(positions, triangles)
    if spacing > 0 and settings.thickness > SPACING_FRACTION * spacing:
        raise ValueError(f"self_collision: thickness {settings.thickness:g} m is more than half the mesh's spacing "
                         f"{spacing:.3g} m (the median height of its triangles): each particle would be within "
                         f"the thickness of the triangles around its own, pushed by them at rest, with hundreds "
                         f"of pairs to check a step; use a thickness of at most {SPACING_FRACTION * spacing:.3g} m "
                         f"or a coarser mesh")
