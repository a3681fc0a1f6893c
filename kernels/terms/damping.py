"""Spring damping force (seed Eq. 2) and its Jacobian D (Eq. 14)."""

import taichi as ti

from .base import SpringTerm


class SpringDamping(SpringTerm):
    """f_i = kd ((v_j - v_i) . n) n: ``dev.kd`` (N s/m) per spring.

    D_ii = -kd n n^T (Eq. 14), so A gets b = dt kd. In Eq. 15's right-hand side
    the damping force is exactly D v, so f - D v gets nothing from this term.
    """

    name = "damping"
    differentiable = True
    rate_dependent = True

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
    def adjoint(s, dev, adj, u, d, r, n, length):
        """Gradients of u . kd (r.n) n: in d, kd/l ((u.n)(r - (r.n) n) + (r.n)(u - (u.n) n));
        in r, kd (u.n) n; adds (r.n) u.n to ``adj.gkd[s]`` (``rate_gradient``)."""
        SpringDamping.rate_gradient(s, adj, u, r, n)
        return SpringDamping.rate_stiffness_adjoint(s, dev, u, r, n, length), dev.kd[s] * u.dot(n) * n

    @staticmethod
    @ti.func
    def rate_stiffness_adjoint(s, dev, u, r, n, length):
        """kd/l ((u.n)(r - (r.n) n) + (r.n)(u - (u.n) n)): how n turns with d."""
        un = u.dot(n)
        rn = r.dot(n)
        return dev.kd[s] / length * (un * (r - rn * n) + rn * (u - un * n))

    @staticmethod
    @ti.func
    def operator_adjoint(s, dev, adj, u, p, d, n, length, h, fix: ti.template()):
        """E = h kd (u.n)(p.n): dE/dd = h kd ((p.n)(u - (u.n) n) + (u.n)(p - (p.n) n)) / l,
        -dE/dkd added to ``adj.gkd[s]`` (``operator_rate_gradient``)."""
        grad = d * 0
        if n.dot(n) > 0:
            un = u.dot(n)
            pn = SpringDamping.operator_rate_gradient(s, adj, u, p, n, h)
            grad = h * dev.kd[s] * (pn * (u - un * n) + un * (p - pn * n)) / length
        return grad

    @staticmethod
    @ti.func
    def operator_rate_gradient(s, adj, u, p, n, h):
        """Adds -h (u.n)(p.n), minus the gradient of u . S p in kd, to ``adj.gkd[s]``;
        returns p.n. Also run, alone, for a model with kd = 0 everywhere."""
        pn = p.dot(n)
        adj.gkd[s] = adj.gkd[s] - h * u.dot(n) * pn
        return pn

    @staticmethod
    @ti.func
    def rate_gradient(s, adj, u, r, n):
        """Adds u . (r.n) n, the gradient of u . f in kd, to ``adj.gkd[s]``; returns r.n.
        Also run, alone, for a model with kd = 0 everywhere (no damping term compiled)."""
        rn = r.dot(n)
        adj.gkd[s] = adj.gkd[s] + rn * u.dot(n)
        return rn

    @staticmethod
    @ti.func
    def dissipation_change(s, dev, n, old_rate, new_rate):
        """Change of the Rayleigh dissipation kd/2 (n . (v_j - v_i))^2 (W) between the end
        velocity differences ``old_rate`` and ``new_rate``, n held fixed."""
        a = n.dot(old_rate)
        b = n.dot(new_rate)
        return 0.5 * dev.kd[s] * (b - a) * (b + a)
