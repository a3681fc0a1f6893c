"""Linear air drag: a force against each particle's velocity relative to the wind."""

import taichi as ti

from .base import ParticleTerm


class Drag(ParticleTerm):
    """f_i = -drag (v_i - wind): ``dev.drag`` (N s/m, one scalar), ``dev.wind`` (m/s, one vector).

    Its Jacobian is D_ii = -drag I (Eq. 14's counterpart), so A gets dt drag on the
    diagonal, and its share of Eq. 15's f - D v is -drag (v - wind) + drag v = drag wind.
    A single particle under gravity reaches the terminal velocity m g / drag + wind.
    """

    name = "drag"
    differentiable = True

    @staticmethod
    @ti.func
    def force(i, dev, x, v):
        return -dev.drag[None] * (v[i] - dev.wind[None])

    @staticmethod
    @ti.func
    def rhs(i, dev, x, v):
        return dev.drag[None] * dev.wind[None]

    @staticmethod
    @ti.func
    def diagonal(i, dev, h):
        return h * dev.drag[None]

    @staticmethod
    @ti.func
    def adjoint(i, dev, adj, w, x, v):
        """w . f: gradient -drag w in v_i; adds -w . (v_i - wind) to ``adj.gdrag[i]`` and
        drag w to ``adj.gwind[i]``."""
        adj.gdrag[i] = adj.gdrag[i] - w.dot(v[i] - dev.wind[None])
        adj.gwind[i] = adj.gwind[i] + dev.drag[None] * w
        return w * 0, -dev.drag[None] * w

    @staticmethod
    @ti.func
    def rhs_adjoint(i, dev, adj, u, x, v):
        """u . drag wind: adds u . wind to ``adj.gdrag[i]``, drag u to ``adj.gwind[i]``."""
        adj.gdrag[i] = adj.gdrag[i] + u.dot(dev.wind[None])
        adj.gwind[i] = adj.gwind[i] + dev.drag[None] * u
        return u * 0

    @staticmethod
    @ti.func
    def operator_adjoint(i, dev, adj, u, p, h):
        """u . h drag p: adds -h u . p to ``adj.gdrag[i]``."""
        adj.gdrag[i] = adj.gdrag[i] - h * u.dot(p)
        return u * 0

    @staticmethod
    @ti.func
    def dissipation_change(i, dev, old_v, new_v):
        """Change of the dissipation drag/2 |v - wind|^2 (W) from ``old_v`` to ``new_v``."""
        return 0.5 * dev.drag[None] * (new_v - old_v).dot(new_v + old_v - 2 * dev.wind[None])
