"""Defaults of the two kinds of force term (see ``kernels.terms``), and the record of a
Model parameter that a term declares."""

from dataclasses import dataclass

import numpy as np
import taichi as ti

from massspring.text import brief
from massspring.validate import real_array


@dataclass(frozen=True)
class Parameter:
    """A Model argument of a force term: a number >= 0 (``default`` a float) or a
    3-vector (``default`` a 3-tuple), in ``unit``. ``Model``, ``Model.from_mesh``, scene
    files (a key of every form's [model] table and ``--set``), the f32 range check and the
    fingerprint take it from here; ``doc`` is its line in ``Model``'s docstring."""

    name: str
    default: float | tuple
    unit: str
    doc: str

    @property
    def vector(self) -> bool:
        return isinstance(self.default, tuple)

    def check(self, value):
        """``value`` as a float >= 0 or a read-only (3,) float64 array; ValueError naming the parameter."""
        arr = real_array(self.name, value)
        if self.vector:
            if arr.shape != (3,):
                raise ValueError(f"{self.name}: expected 3 components, got shape {arr.shape}")
            arr = np.array(arr, dtype=np.float64)
            arr.setflags(write=False)
            return arr
        if arr.shape != () or not arr >= 0:
            raise ValueError(f"{self.name}: expected a number >= 0 ({self.unit}), got {brief(value)}")
        return float(arr)

    def is_default(self, value) -> bool:
        return bool(np.all(np.asarray(value) == np.asarray(self.default)))


class SpringTerm:
    kind = "spring"
    name = ""
    parameters = ()  # Parameter records: the term's own Model arguments

    @staticmethod
    def check(values):
        """Refuse (ValueError) a combination of the term's checked ``values`` (name -> value)."""

    @staticmethod
    @ti.func
    def rhs_tension(s, dev, i, j, x, v, n, length):
        return 0

    @staticmethod
    @ti.func
    def coefficients(s, dev, n, length, h, fix: ti.template()):
        return 0, 0

    @staticmethod
    @ti.func
    def potential_change(s, dev, old_length, new_length, change):
        return 0

    @staticmethod
    @ti.func
    def dissipation_change(s, dev, n, old_rate, new_rate):
        return 0


class ParticleTerm:
    kind = "particle"
    name = ""
    parameters = ()  # Parameter records: the term's own Model arguments
    check = SpringTerm.check
    # A uniform acceleration a (f_i = m_i a, one a for every particle: gravity) sets
    # ``uniform`` and gives a twice: ``acceleration(dev)`` (a ``ti.func``, the run's
    # precision) and ``model_acceleration(model)`` ((3,) float64). The code that needs the
    # external acceleration sums them over such terms (``kernels.terms``).
    uniform = False

    @staticmethod
    @ti.func
    def diagonal(i, dev, h):
        return 0

    @staticmethod
    @ti.func
    def potential_change(i, dev, dx):
        return 0

    @staticmethod
    @ti.func
    def dissipation_change(i, dev, old_v, new_v):
        return 0
