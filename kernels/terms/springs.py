"""Elastic spring force (seed Eq. 1) and its stiffness K (Eq. 13)."""

import taichi as ti

from .base import SpringTerm


class Springs(SpringTerm):
    """f_i = ks (l - l0) n: ``dev.ks`` (N/m) and ``dev.l0`` (m) per spring.

    Stiffness block (Eq. 13, typo |x_i - x_i| read as |x_j - x_i|), with c = l0/l - 1:
    K_ii = ks (c I - (1 + c) n n^T), so A gets a = -dt^2 ks c, b = dt^2 ks (1 + c).
    Definiteness fix (Choi & Ko 2002): c -> min(c, 0) in the transverse part
    (a compressed spring's c > 0 makes A indefinite); the along-spring -ks n n^T stays.
    A zero-rest-length spring (l0 = 0: f_i = ks (x_j - x_i), linear) has K_ii = -ks I
    at every length, its ends coincident included; any other spring with no direction
    adds no stiffness (the zero-length rule).
    """

    name = "spring"

    @staticmethod
    @ti.func
    def tension(s, dev, i, j, x, v, n, length):
        return dev.ks[s] * (length - dev.l0[s])

    @staticmethod
    @ti.func
    def rhs_tension(s, dev, i, j, x, v, n, length):
        return dev.ks[s] * (length - dev.l0[s])

    @staticmethod
    @ti.func
    def coefficients(s, dev, n, length, h, fix: ti.template()):
        """(a, b); n = 0 when the spring has no direction (``forces.spring_direction``)."""
        k = h * h * dev.ks[s]
        a = k * 0
        b = k * 0
        if dev.l0[s] == 0:  # c = -1: K_ii = -ks I at every length, with a direction or without
            a = k
        elif n.dot(n) > 0:
            c = dev.l0[s] / length - 1
            if ti.static(fix):
                c = ti.min(c, 0)
            a = -k * c
            b = k * (1 + c)
        return a, b

    @staticmethod
    @ti.func
    def potential_change(s, dev, old_length, new_length, change):
        """ks/2 ((l' - l0)^2 - (l - l0)^2) (J), from the length change l' - l given separately."""
        return 0.5 * dev.ks[s] * change * (new_length + old_length - 2 * dev.l0[s])
