"""The preconditioner protocol."""

from __future__ import annotations


class Preconditioner:
    """z = P r for the CG solve of Eq. 15 (P symmetric positive definite).

    Two kinds, both driven by ``cg.solve`` without it knowing which it has:

    * pointwise: ``kernel`` is a class of ``ti.func``s (``kernels/preconditioners.py``)
      that the CG kernels call per particle: set up in the same loop that refreshes
      the operator, applied inside the CG updates (no launch of its own);
    * global (``kernel`` None): ``setup()`` after each refresh and ``apply()`` (z = P r
      from ``dev.r`` into ``dev.z``, returning r.z) run kernels of their own.
    """

    name = ""
    kernel = None
    serial_below = None  # springs below which loops="auto" runs it serially (None: SERIAL_BELOW)

    def __init__(self, dev, model, settings):
        self.dev = dev

    @classmethod
    def declare(cls, layout, model, settings, cfg):
        """Add the fields this preconditioner needs to ``layout`` (``cfg``: the integrator's
        compile-time switches, ``device.Config``). A combination it cannot serve is a
        ValueError naming it, raised here: before any field is allocated or kernel run."""

    def bind(self, cfg):
        """The compile-time switches (``device.Config``) of the integrator's kernels."""

    def setup(self, dt):
        """Per step, after ``kernels.cg.cg_refresh`` (global preconditioners)."""

    def apply(self) -> float:
        """z = P r (global preconditioners); returns r.z."""
        raise NotImplementedError

    def release(self):
        """Hand back resources other than the simulation's bundle."""

    def describe(self) -> dict:
        """What it holds beyond the simulation's bundle, for ``Simulation.info``: "bytes"
        of its own fields, and anything else worth reporting."""
        return {"bytes": 0}
