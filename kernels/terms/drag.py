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
    def dissipation_change(i, dev, old_v, new_v):
        """Change of the dissipation drag/2 |v - wind|^2 (W) from ``old_v`` to ``new_v``."""
        return 0.5 * dev.drag[None] * (new_v - old_v).dot(new_v + old_v - 2 * dev.wind[None])
