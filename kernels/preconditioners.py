"""Pointwise preconditioners of the CG (``cg``): z_i = P_i r_i, fused into its kernels.

Each is a class of ``ti.func``s used through ``cfg.precond``:
``setup_row(i, dev, cfg, A_ii)`` once per step (when ``needs_diagonal``), and
``apply_row(i, dev, cfg, r_i) -> z_i``.
"""

import taichi as ti


class Identity:
    """No preconditioning: z = r."""

    needs_diagonal = False

    @staticmethod
    @ti.func
    def setup_row(i, dev, cfg: ti.template(), block):
        pass

    @staticmethod
    @ti.func
    def apply_row(i, dev, cfg: ti.template(), r):
        return r


class BlockJacobi:
    """z_i = A_ii^-1 r_i, the inverse 3x3 diagonal blocks kept in ``dev.minv`` (n,) 3x3."""

    needs_diagonal = True

    @staticmethod
    @ti.func
    def setup_row(i, dev, cfg: ti.template(), block):
        dev.minv[i] = ti.cast(block.inverse(), cfg.real)  # inverse() divides in the default f64

    @staticmethod
    @ti.func
    def apply_row(i, dev, cfg: ti.template(), r):
        return dev.minv[i] @ r
