"""Defaults of the two kinds of force term (see ``kernels.terms``)."""

import taichi as ti


class SpringTerm:
    kind = "spring"
    name = ""
    uniform = False

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
    # A uniform acceleration a (f_i = m_i a, one a for every particle: gravity) sets
    # ``uniform`` and gives a as ``acceleration(dev)`` (a ``ti.func``, the run's precision);
    # its host side gives it as ``model_acceleration(model)`` (``massspring.terms``).
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
