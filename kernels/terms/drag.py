"""Linear air drag: a force against each particle's velocity relative to the wind."""

import taichi as ti

from .base import Parameter, ParticleTerm


class Drag(ParticleTerm):
    """f_i = -drag (v_i - wind): ``dev.drag`` (N s/m, one scalar), ``dev.wind`` (m/s, one vector).

    Its Jacobian is D_ii = -drag I (Eq. 14's counterpart), so A gets dt drag on the
    diagonal, and its share of Eq. 15's f - D v is -drag (v - wind) + drag v = drag wind.
    A single particle under gravity reaches the terminal velocity m g / drag + wind.
    Active when drag > 0.
    """

    name = "drag"
    parameters = (
        Parameter("drag", 0.0, "N s/m", "Linear air drag on every particle: f_i = -drag (v_i - wind)."),
        Parameter("wind", (0.0, 0.0, 0.0), "m/s",
                  "The air's velocity; non-zero only with drag > 0 (it acts through drag alone)."),
    )

    @staticmethod
    def check(values):
        if any(values["wind"] != 0) and values["drag"] == 0:
            raise ValueError("wind: has no effect without drag (drag = 0): give drag > 0 or no wind")

    @staticmethod
    def active(model):
        return model.drag > 0

    @staticmethod
    def arrays(model):
        return {"drag": ("scalar", model.drag), "wind": ("vector", model.wind)}

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
