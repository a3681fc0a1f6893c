"""A run as one USD stage (``run --export DIR --format usd``: ``DIR/frames.usdc``), by
``pxr`` (the ``usd-core`` package: the ``usd`` extra, ``extras.install_hint``).

The stage (Z up, 1 m per unit) holds, under its default prim ``/World``:

* ``/World/Body``: the model's particles as the points of a ``UsdGeom.Mesh`` of its
  surface triangles, or of a ``UsdGeom.Points`` for a model without a surface, whose
  springs then are ``/World/Springs``, linear ``UsdGeom.BasisCurves`` of two points
  each. ``points`` (m) and ``velocities`` (m/s) are time-sampled at every frame, with
  the ``extent``; USD stores them as float32, so they equal the float64 state to a
  relative 6e-8.
* ``/World/Colliders/<kind>_<k>``: each collider as the ``UsdGeom`` shape of its
  ``usd_shape``: a plane as a ``Plane`` (its solid side is behind its normal, drawn
  ``PLANE_SIZE`` times the body's size across), a sphere as a ``Sphere``, a box as a
  ``Cube`` scaled to its sides (its rounded edges are not drawn); a moving collider's
  ``xformOp:translate`` (to its ``origin``) is time-sampled with the frames.

Time codes are steps and ``timeCodesPerSecond`` is 1 / dt, so a viewer plays the
simulated time in real time; the start and end time codes are the first and last
frames' steps. ``customLayerData`` records the scene, dt and the massspring version.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from massspring.support.defaults import VERSION
from massspring.io.files import atomic_path

PLANE_SIZE = 4.0  # a drawn plane's side, in lengths of the body's initial bounding box diagonal


class StageWriter:
    """Frames of one run into a USD stage saved as ``path`` (.usdc or .usda): made at the
    first frame, ``sim``'s; ``add(sim)`` samples each frame, ``save()`` writes the stage
    atomically (OSError if it cannot)."""

    def __init__(self, path, sim, scene=""):
        from pxr import Gf, Usd, UsdGeom

        self.path, self.model, self.steps = Path(path), sim.model, []
        stage = self.stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(1.0 / sim.dt)
        stage.SetFramesPerSecond(1.0 / sim.dt)
        stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
        stage.GetRootLayer().customLayerData = {"massspring": VERSION, "scene": str(scene), "dt": float(sim.dt)}
        model = self.model
        if len(model.triangles):
            self.body = UsdGeom.Mesh.Define(stage, "/World/Body")
            self.body.CreateFaceVertexCountsAttr(_integers(np.full(len(model.triangles), 3)))
            self.body.CreateFaceVertexIndicesAttr(_integers(model.triangles.ravel()))
            self.body.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            self.body.CreateDoubleSidedAttr(True)
            self.springs = None
        else:
            self.body = UsdGeom.Points.Define(stage, "/World/Body")
            self.springs = UsdGeom.BasisCurves.Define(stage, "/World/Springs")
            self.springs.CreateTypeAttr(UsdGeom.Tokens.linear)
            self.springs.CreateCurveVertexCountsAttr(_integers(np.full(model.n_springs, 2)))
        extent = np.ptp(model.positions, axis=0)
        size = PLANE_SIZE * max(float(np.linalg.norm(extent)), 1e-3)
        self.colliders = []  # (collider, its prim's translate op)
        for k, collider in enumerate(model.colliders):
            translate = collider.usd_shape(stage, f"/World/Colliders/{collider.kind}_{k}", size)
            translate.Set(Gf.Vec3d(*collider.origin()))
            self.colliders.append((collider, translate))

    def add(self, sim):
        """Sample ``sim``'s current state at the time code of its step."""
        from pxr import Gf, Usd, Vt

        time = Usd.TimeCode(sim.steps)
        x, v = sim.positions, sim.velocities
        self.body.GetPointsAttr().Set(_vectors(x), time)
        self.body.CreateVelocitiesAttr().Set(_vectors(v), time)
        self.body.CreateExtentAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*x.min(axis=0)), Gf.Vec3f(*x.max(axis=0))]), time)
        if self.springs is not None:
            self.springs.GetPointsAttr().Set(_vectors(x[self.model.springs].reshape(-1, 3)), time)
        for collider, translate in self.colliders:
            if collider.moving:
                translate.Set(Gf.Vec3d(*collider.at(sim.time).origin()), time)
        self.steps.append(sim.steps)

    def save(self):
        """Write the stage (time codes from the first frame's step to the last's) to
        ``path``, through a temporary file renamed into place."""
        from pxr import Tf

        if self.steps:
            self.stage.SetStartTimeCode(self.steps[0])
            self.stage.SetEndTimeCode(self.steps[-1])
        with atomic_path(self.path) as tmp:
            named = tmp + self.path.suffix  # pxr picks the file format from the extension
            try:
                if not self.stage.GetRootLayer().Export(named):
                    raise OSError(f"USD could not write {named!r}")
                os.replace(named, tmp)
            except Tf.ErrorException as exc:
                raise OSError(str(exc).strip()) from None
            finally:
                Path(named).unlink(missing_ok=True)


def _vectors(array):
    from pxr import Vt

    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(array, dtype=np.float32))


def _integers(array):
    from pxr import Vt

    return Vt.IntArray.FromNumpy(np.ascontiguousarray(array, dtype=np.int32))

