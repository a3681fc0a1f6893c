"""Gravity (seed Eq. 3): a uniform acceleration, constant force, no Jacobian."""

import taichi as ti

from .base import ParticleTerm


class Gravity(ParticleTerm):
    """f_i = m_i g: ``dev.gravity`` (m/s^2, one vector)."""

    name = "gravity"
    differentiable = True
    uniform = True

    @staticmethod
    @ti.func
    def acceleration(dev):
        return dev.gravity[None]

    @staticmethod
    @ti.func
    def force(i, dev, x, v):
        return dev.mass[i] * dev.gravity[None]

    @staticmethod
    @ti.func
    def rhs(i, dev, x, v):
        return dev.mass[i] * dev.gravity[None]

    @staticmethod
    @ti.func
    def potential_change(i, dev, dx):
        """-m g . dx (J) for a displacement dx (m)."""
        return -dev.mass[i] * dev.gravity[None].dot(dx)
