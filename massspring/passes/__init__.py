"""Passes: what acts on a run's state between or after the steps of its integrator, one
module (or folder) each, all following one protocol (``base.Pass``). ``PASSES`` is
their registry, in the order their ``end`` runs after a step; a run holds those its
model wants (``for_model``). A new pass is its module and one entry here."""

from massspring.passes.base import Pass
from massspring.passes.self_collision.forward import SelfCollisionPass
from massspring.passes.strain_limit import StrainLimitPass

PASSES = {cls.name: cls for cls in (StrainLimitPass, SelfCollisionPass)}


def for_model(model) -> tuple:
    """The pass classes a run of ``model`` holds (a Model, or anything with the attributes
    their ``wanted`` reads: ``engine.footprint.Sketch``), in ``PASSES`` order."""
    return tuple(cls for cls in PASSES.values() if cls.wanted(model))


__all__ = ["PASSES", "Pass", "for_model"]
