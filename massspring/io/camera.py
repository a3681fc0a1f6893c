"""The camera of a picture: where it looks from (``View``) and how the run fits the frame (``Framing``).

Plain numpy: positions (..., 3) in m in, screen coordinates out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

PROJECTIONS = ("orthographic", "perspective")
FRAMINGS = ("run", "follow", "last")
DEFAULT_FRAMING = "run"
PERSPECTIVE_DISTANCE = 3.0  # perspective camera distance from the run's centre, in bounding radii
MARGIN = 0.05               # fraction of the plot area's width and height kept free on each side


@dataclass(frozen=True)
class View:
    """A camera looking at the centre of the run from ``azimuth`` degrees about +z
    (0 = from +x, 90 = from +y) and ``elevation`` degrees above the xy plane (90 =
    from above), with an orthographic or perspective projection. +z is up on screen
    (for elevation 90, the screen's up is the horizontal direction away from the camera's azimuth)."""

    azimuth: float = -60.0
    elevation: float = 20.0
    projection: str = "orthographic"

    def __post_init__(self):
        for key in ("azimuth", "elevation"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"view.{key}: expected a finite number of degrees, got {value!r}")
            object.__setattr__(self, key, float(value))
        if not -90.0 <= self.elevation <= 90.0:
            raise ValueError(f"view.elevation: must be within [-90, 90] degrees, got {self.elevation:g}")
        if self.projection not in PROJECTIONS:
            raise ValueError(f"view.projection: unknown value {self.projection!r}, expected one of "
                             f"{', '.join(PROJECTIONS)}")

    def basis(self):
        """Unit vectors (right, up, toward) in world coordinates; ``toward`` points from
        the scene to the camera, so a larger ``p . toward`` is nearer."""
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        toward = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        right = np.array([-math.sin(az), math.cos(az), 0.0])
        up = np.cross(toward, right)
        return right, up, toward

    def project(self, points, centre, radius):
        """Camera coordinates of ``points`` (..., 3) around ``centre`` (3,): returns
        ``xy`` (..., 2) on the screen plane (m, +y up) and ``depth`` (...,) (m, larger
        is nearer). Perspective divides by the distance to a camera placed
        ``PERSPECTIVE_DISTANCE * radius`` from the centre, scaled to be exact at the centre."""
        right, up, toward = self.basis()
        p = np.asarray(points, dtype=np.float64) - centre
        xy = np.stack([p @ right, p @ up], axis=-1)
        depth = p @ toward
        if self.projection == "perspective":
            distance = PERSPECTIVE_DISTANCE * radius
            xy *= (distance / (distance - depth))[..., None]
        return xy, depth



@dataclass(frozen=True)
class Framing:
    """World -> pixel mapping of a run: ``view``'s projection around the run's bounding
    box, scaled uniformly to fit ``plot`` (left, top, width, height in pixels) with
    ``MARGIN`` kept free, and centred there.

    ``Framing.fit(..., mode)``: "run" fits every frame at once (nothing ever leaves
    the picture); "follow" keeps the scale that fits the largest frame but centres
    each frame on itself (``for_frame``: a falling body stays in the middle, at a
    constant size); "last" fits the last frame alone."""

    view: View
    centre: np.ndarray
    radius: float
    middle: np.ndarray
    scale: float
    plot: tuple
    follow: bool = False

    @classmethod
    def fit(cls, view, frames, plot, mode=DEFAULT_FRAMING):
        """The framing of ``frames`` (k, n, 3) for ``mode`` (see the class)."""
        if mode not in FRAMINGS:
            raise ValueError(f"framing: unknown value {mode!r}, expected one of {', '.join(FRAMINGS)}")
        frames = np.asarray(frames, dtype=np.float64)
        if mode == "last":
            return cls._fit(view, frames[-1:], plot)
        if mode == "follow":
            fits = [cls._fit(view, frame[None], plot) for frame in frames]
            smallest = min(fits, key=lambda f: f.scale)
            return cls(view, smallest.centre, smallest.radius, smallest.middle, smallest.scale, tuple(plot), True)
        return cls._fit(view, frames, plot)

    @classmethod
    def _fit(cls, view, frames, plot):
        """Their 3D box gives the centre and radius, their projections' 2D box the scale."""
        lo, hi = frames.reshape(-1, 3).min(axis=0), frames.reshape(-1, 3).max(axis=0)
        centre = (lo + hi) / 2
        radius = float(np.linalg.norm(hi - lo)) / 2 or 1.0
        xy, _ = view.project(frames, centre, radius)
        lo2, hi2 = xy.reshape(-1, 2).min(axis=0), xy.reshape(-1, 2).max(axis=0)
        extent = hi2 - lo2
        room = np.array(plot[2:], dtype=np.float64) * (1 - 2 * MARGIN)
        fits = [room[i] / extent[i] for i in range(2) if extent[i] > 1e-9 * radius]
        scale = min(fits) if fits else float(min(room)) / (2 * radius)
        return cls(view, centre, radius, (lo2 + hi2) / 2, scale, tuple(plot))

    def for_frame(self, positions):
        """The framing to draw ``positions`` (n, 3) with: itself, or when following, the
        same scale centred on that frame's box."""
        if not self.follow:
            return self
        x = np.asarray(positions, dtype=np.float64)
        centre = (x.min(axis=0) + x.max(axis=0)) / 2
        xy, _ = self.view.project(x, centre, self.radius)
        middle = (xy.min(axis=0) + xy.max(axis=0)) / 2
        return Framing(self.view, centre, self.radius, middle, self.scale, self.plot, True)

    def pixels(self, points):
        """Pixel coordinates (..., 2) (x right, y down; pixel (i, j) covers [i, i+1) x
        [j, j+1)) and depth (...,) (m, larger is nearer) of ``points`` (..., 3)."""
        xy, depth = self.view.project(points, self.centre, self.radius)
        left, top, width, height = self.plot
        px = left + width / 2 + (xy[..., 0] - self.middle[0]) * self.scale
        py = top + height / 2 - (xy[..., 1] - self.middle[1]) * self.scale
        return np.stack([px, py], axis=-1), depth
