"""Spring damping force (seed Eq. 2) and its Jacobian D (Eq. 14)."""

import taichi as ti

from .base import SpringTerm


class SpringDamping(SpringTerm):
    """f_i = kd ((v_j - v_i) . n) n: ``dev.kd`` (N s/m) per spring.

    D_ii = -kd n n^T (Eq. 14), so A gets b = dt kd. In Eq. 15's right-hand side
    the damping force is exactly D v, so f - D v gets nothing from this term.
    """

    name = "damping"

    @staticmethod
    @ti.func
    def tension(s, dev, i, j, x, v, n, length):
        return dev.kd[s] * (v[j] - v[i]).dot(n)

    @staticmethod
    @ti.func
    def coefficients(s, dev, n, length, h, fix: ti.template()):
        return 0, h * dev.kd[s]

    @staticmethod
    @ti.func
    def dissipation_change(s, dev, n, old_rate, new_rate):
        """Change of the Rayleigh dissipation kd/2 (n . (v_j - v_i))^2 (W) between the end
        velocity differences ``old_rate`` and ``new_rate``, n held fixed."""
        a = n.dot(old_rate)
        b = n.dot(new_rate)
        return 0.5 * dev.kd[s] * (b - a) * (b + a)
