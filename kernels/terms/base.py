"""Defaults of the two kinds of force term (see ``kernels.terms``)."""

import taichi as ti


class SpringTerm:
    kind = "spring"
    name = ""
    uniform = False
    differentiable = False  # gives ``adjoint``, ``rhs_adjoint``, ``operator_adjoint`` (``massspring.gradients``)
    rate_dependent = False  # its tension depends on the rates r: ``rate_stiffness_adjoint`` is not zero

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
    def potential(s, dev, length):
        """The term's potential energy (J) at the spring's ``length`` (m)."""
        return 0

    @staticmethod
    @ti.func
    def potential_change(s, dev, old_length, new_length, change):
        return 0

    @staticmethod
    @ti.func
    def dissipation_change(s, dev, n, old_rate, new_rate):
        return 0

    @staticmethod
    @ti.func
    def adjoint(s, dev, adj, u, d, r, n, length):
        """For a weight ``u`` (the adjoint of the force on end i minus that on end j): the
        gradients of u . (tension n) in d = x_j - x_i and in r = v_j - v_i (two vec3), and
        u's products with the gradients in the term's parameters added to ``adj``'s
        per-spring arrays (``massspring.gradient``). Called only where length > tiny."""
        return d * 0, d * 0

    @staticmethod
    @ti.func
    def rhs_adjoint(s, dev, adj, u, d, r, n, length):
        """``adjoint`` for ``rhs_tension`` (Eq. 15's f - D v): zero by default."""
        return d * 0, d * 0

    @staticmethod
    @ti.func
    def rate_stiffness_adjoint(s, dev, u, r, n, length):
        """The gradient in d of u . (tension n) through n alone, of a term whose tension
        depends on the rates r: its force's x-derivative that Eq. 15's operator leaves out
        (nonsymmetric; the Newton-solved steps take n at their prediction, and their
        adjoint sends this to it, ``kernels/newton_adjoint.py``). Zero by default."""
        return u * 0

    @staticmethod
    @ti.func
    def operator_adjoint(s, dev, adj, u, p, d, n, length, h, fix: ti.template()):
        """For weights u (on end i minus end j) and p (a velocity difference, end i minus
        end j): the gradient in d = x_j - x_i of E = u . S p, S = a I + b n n^T the
        term's block of Eq. 15's matrix (``coefficients``), with -dE/d(parameter)
        added to ``adj``'s per-spring arrays. n = 0 where the spring has no direction."""
        return d * 0


class ParticleTerm:
    kind = "particle"
    name = ""
    differentiable = False  # the gradients' kernels handle it (``massspring.gradients``)
    # A uniform acceleration a (f_i = m_i a, one a for every particle: gravity) sets
    # ``uniform`` and gives a as ``acceleration(dev)`` (a ``ti.func``, the run's precision);
    # its host side gives it as ``model_acceleration(model)`` (``massspring.model.terms``).
    uniform = False

    @staticmethod
    @ti.func
    def diagonal(i, dev, h):
        return 0

    @staticmethod
    @ti.func
    def adjoint(i, dev, adj, w, x, v):
        """For a weight ``w`` (vec3): the gradients of w . force in x_i and v_i (two vec3),
        and w's products with the gradients in the term's parameters added to ``adj``'s
        per-particle arrays (``massspring.gradients``). A uniform term's share is
        ``adj.gg`` (the kernels add it by ``uniform``)."""
        return w * 0, w * 0

    @staticmethod
    @ti.func
    def rhs_adjoint(i, dev, adj, u, x, v):
        """``adjoint`` for ``rhs`` (Eq. 15's f - D v): its gradient in x_i (v enters Eq.
        15's right-hand side through M v alone); the parameters' shares added."""
        return u * 0

    @staticmethod
    @ti.func
    def operator_adjoint(i, dev, adj, u, p, h):
        """For weights u, p (vec3): the gradient in x_i of u . (``diagonal`` p), with
        -d/d(parameter) of it added to ``adj``'s per-particle arrays."""
        return u * 0

    @staticmethod
    @ti.func
    def potential_change(i, dev, dx):
        return 0

    @staticmethod
    @ti.func
    def dissipation_change(i, dev, old_v, new_v):
        return 0
