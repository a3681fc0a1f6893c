"""Time integrators: one module each, registered in ``INTEGRATORS``.

An integrator is a subclass of :class:`base.Integrator`: it declares the fields it
needs (``declare``), advances the simulation's bundle (``advance``), and suggests a
default time step from a stability prediction (``suggest_dt``) for scenes whose
``[dt]`` table does not name it. Adding one means a module here and an entry below.
"""

from .base import Integrator
from .explicit import ExplicitEuler
from .implicit import ImplicitEuler
from .midpoint import Midpoint
from .newton import BDF2, BackwardEuler
from .rk4 import RK4
from .symplectic import SymplecticEuler

INTEGRATORS = {cls.name: cls for cls in (ExplicitEuler, SymplecticEuler, ImplicitEuler, BackwardEuler, BDF2, Midpoint,
                                         RK4)}

__all__ = ["INTEGRATORS", "Integrator"]
