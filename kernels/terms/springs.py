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
    differentiable = True

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
    def adjoint(s, dev, adj, u, d, r, n, length):
        """d/d(d) of u . ks (l - l0) n = ks ((u.n) n + (l - l0)/l (u - (u.n) n)); adds
        (l - l0) u.n to ``adj.gks[s]`` and -ks u.n to ``adj.gl0[s]``."""
        un = u.dot(n)
        stretch = length - dev.l0[s]
        adj.gks[s] = adj.gks[s] + stretch * un
        adj.gl0[s] = adj.gl0[s] - dev.ks[s] * un
        return dev.ks[s] * (un * n + stretch / length * (u - un * n)), d * 0

    @staticmethod
    @ti.func
    def rhs_adjoint(s, dev, adj, u, d, r, n, length):
        """The elastic force is all of this term's share of f - D v: ``adjoint``."""
        return Springs.adjoint(s, dev, adj, u, d, r, n, length)

    @staticmethod
    @ti.func
    def operator_adjoint(s, dev, adj, u, p, d, n, length, h, fix: ti.template()):
        """E = k (-c u.p + (1 + c)(u.n)(p.n)), k = h^2 ks, c = l0/l - 1 (clamped to 0 where
        ``fix`` and c > 0, where then dc/dl = 0; -1 for l0 = 0): dE/dd = k dc/dl
        ((u.n)(p.n) - u.p) n + k (1 + c)((p.n)(u - (u.n) n) + (u.n)(p - (p.n) n)) / l;
        dE/dks = E / ks, dE/dl0 = k dc/dl0 (-(u.p) + (u.n)(p.n)), dc/dl0 = 1/l unclamped."""
        k = h * h
        up = u.dot(p)
        grad = d * 0
        if dev.l0[s] == 0:
            adj.gks[s] = adj.gks[s] - k * up  # a = k ks: K_ii = -ks I at every length
            if n.dot(n) > 0:  # c = l0/l - 1 as l0 grows from 0
                adj.gl0[s] = adj.gl0[s] - k * dev.ks[s] / length * (u.dot(n) * p.dot(n) - up)
        elif n.dot(n) > 0:
            c = dev.l0[s] / length - 1
            slope = -dev.l0[s] / (length * length)
            per_l0 = 1 / length
            if ti.static(fix):
                if c > 0:
                    c = c * 0
                    slope = slope * 0
                    per_l0 = per_l0 * 0
            un = u.dot(n)
            pn = p.dot(n)
            both = un * pn
            ks = dev.ks[s]
            adj.gks[s] = adj.gks[s] - k * (-c * up + (1 + c) * both)
            adj.gl0[s] = adj.gl0[s] - k * ks * per_l0 * (both - up)
            grad = k * ks * (slope * (both - up) * n + (1 + c) * (pn * (u - un * n) + un * (p - pn * n)) / length)
        return grad

    @staticmethod
    @ti.func
    def potential(s, dev, length):
        """ks/2 (l - l0)^2 (J)."""
        stretch = length - dev.l0[s]
        return 0.5 * dev.ks[s] * stretch * stretch

    @staticmethod
    @ti.func
    def potential_change(s, dev, old_length, new_length, change):
        """ks/2 ((l' - l0)^2 - (l - l0)^2) (J), from the length change l' - l given separately."""
        return 0.5 * dev.ks[s] * change * (new_length + old_length - 2 * dev.l0[s])
