"""Time integrators: one module each, registered in ``INTEGRATORS``.

An integrator is a subclass of :class:`base.Integrator`: it declares the fields it
needs (``declare``), advances the simulation's bundle (``advance``), and suggests a
default time step from a stability prediction (``suggest_dt``) for scenes whose
``[dt]`` table does not name it; its capabilities are one ``base.Traits`` record
(``traits``), its solver's options ``options.Option`` records (``OPTIONS``). Adding one
means a module here and an entry below (and a row of ``analysis.hints`` if the stability
ladder or the study is to take it).
"""

from .base import Integrator, Traits
from .explicit import ExplicitEuler
from .implicit import ImplicitEuler
from .midpoint import Midpoint
from .newton import BDF2, BackwardEuler
from .rk4 import RK4
from .symplectic import SymplecticEuler

INTEGRATORS = {cls.name: cls for cls in (ExplicitEuler, SymplecticEuler, ImplicitEuler, BackwardEuler, BDF2, Midpoint,
                                         RK4)}

# The roles other modules ask for, so that no module outside this package names an integrator:
DEFAULT = ImplicitEuler.name  # Simulation's and a scene's default; no stability limit, one linear solve a step
REFERENCE = RK4.name  # the study's reference trajectories (fourth order)
STUDIED = (ExplicitEuler.name, SymplecticEuler.name, ImplicitEuler.name)  # the study's default lines
SMALLEST_DT = ExplicitEuler.name  # whose scene dt is the smallest: the study's reference starts from it

# Every integrator's solver options (``options.Option``), by name, in the registry's order.
OPTIONS = {option.name: option for cls in INTEGRATORS.values() for option in cls.options}


def takers(option: str) -> tuple:
    """The names of the integrators that take ``option``."""
    return tuple(name for name, cls in INTEGRATORS.items() if any(o.name == option for o in cls.options))


def taken(integrator: str, options: dict) -> dict:
    """The entries of ``options`` (name -> value) that ``integrator`` takes (a scene's
    [solver] table, or options meant for several integrators)."""
    names = {option.name for option in INTEGRATORS[integrator].options}
    return {name: value for name, value in options.items() if name in names}


def untaken(integrator: str, names) -> dict:
    """Of the option ``names``, those ``integrator`` does not take, grouped by what it
    lacks (``Option.lacking``, e.g. "has no linear solve"): lacking -> [names]."""
    taken = {option.name for option in INTEGRATORS[integrator].options}
    refused = {}
    for name in names:
        if name not in taken:
            refused.setdefault(OPTIONS[name].lacking, []).append(name)
    return refused


__all__ = ["DEFAULT", "INTEGRATORS", "OPTIONS", "REFERENCE", "SMALLEST_DT", "STUDIED", "Integrator", "Traits", "taken",
           "takers", "untaken"]
