"""The multigrid cycle's finest level in f32 inside the run's f64 CG (mixed precision).

Level 0 (the particles) is the bulk of a V-cycle's bytes: its Chebyshev smoothing
streams the operator's coefficients (``kernels/operator.py``: ``coef``, 40 bytes per
adjacency entry in f64) and the cycle's vectors twice per degree and per CG iteration,
and its restriction and prolongation stream P. This preconditioner sets the hierarchy
up in the run's precision as ``multigrid`` does, then copies what level 0's part of
the cycle reads into f32 (``kernels.multigrid.narrow``: d_i, the coefficients in
adjacency order, the lagged ones of the Newton-solved steps, the contact filters,
D^-1 and P; ``Narrowed`` gives them the kernels' names) and smooths, restricts and
prolongs level 0 in f32. The coarse levels, their setup and the coarsest Cholesky
solve stay in the run's precision: built or factored in f32, the Galerkin operators
of a stiff cloth lose their softest modes (the rigid motions the coarse levels
exist for) to cancellation, and CG took 2.3 times the iterations at 256 x 256, ks 1e6
(``benchmarks/multigrid_precision.py``, where this variant was measured first). CG's
vectors, its operator products, its residual and its tolerance are the run's. The
cycle is a fixed linear operator rounded to f32: symmetric and positive definite to
that rounding, which CG needs (``tests/test_multigrid_f32.py``).

Not for self-collision pairs in the solve (their penalty rows are read in the run's
precision): refused when the fields are declared.
"""

from __future__ import annotations

import dataclasses

import taichi as ti

from massspring.kernels import multigrid as mg

from .multigrid import Multigrid


class MultigridF32(Multigrid):
    """``Multigrid`` with level 0's part of the cycle in f32 (see the module docstring)."""

    name = "multigrid-f32"

    @classmethod
    def declare(cls, layout, model, settings, cfg):
        if cfg.self_pairs:
            raise ValueError(f"preconditioner {cls.name!r}: self-collision pairs in the implicit solve need the "
                             "f64 cycle; use preconditioner 'multigrid'")
        layout.add("minv", layout.real, "particle", (3, 3))  # the setup's, in the run's precision
        layout.add("mg32_minv", ti.f32, "particle", (3, 3))
        for name in ("mg_x", "mg_res", "mg_d", "mg_d2"):
            layout.vectors(name, ti.f32)
        layout.add("mg32_diag", ti.f32, "particle")
        if model.n_springs:
            layout.vectors("mg32_coef", ti.f32, "entry", k=5)
        if cfg.lagged:
            layout.vectors("mg32_lag_coef", ti.f32, "entry", k=4)
        if cfg.contact_filter:
            layout.add("mg32_cfilter", ti.f32, "particle", (3, 3))

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        if getattr(dev, "narrowed", None) is None:  # kept with the pooled bundles: kernels compile once
            dev.narrowed = Narrowed(dev)
        if self.g is not None and getattr(self.g, "narrowed", None) is None:
            self.g.narrowed = NarrowedHierarchy(self.g)
        self.narrow_cfg = None

    def hierarchy_layout(self, real):
        layout = super().hierarchy_layout(real)
        layout.add("p0_f32", ti.f32, layout.decls["p0"][1][0], (3, 6))
        return layout

    def bind(self, cfg):
        super().bind(cfg)
        self.narrow_cfg = dataclasses.replace(cfg, real=ti.f32)

    def setup(self, dt):
        super().setup(dt)
        coarse = self.g is not None
        mg.narrow(self.dev, self.cfg, self.dev.narrowed, self.g, self.g.narrowed if coarse else None, coarse,
                  self.serial)

    def level0(self):
        return self.dev.narrowed, self.narrow_cfg, self.g.narrowed if self.g is not None else None


@ti.data_oriented
class Narrowed:
    """Level 0 as the f32 part of the cycle reads it: the bundle's f32 copies (``mg32_*``)
    under the names the kernels use, the cycle's own f32 vectors, and the run's index
    fields and CG vectors r and z (read and written in the run's precision)."""

    SHARED = ("size", "offsets", "other", "free", "contacts", "partial", "r", "z", "mg_x", "mg_res", "mg_d", "mg_d2")
    COPIES = ("minv", "diag", "coef", "lag_coef", "cfilter")

    def __init__(self, dev):
        for name in self.SHARED:
            if hasattr(dev, name):
                setattr(self, name, getattr(dev, name))
        for name in self.COPIES:
            if hasattr(dev, "mg32_" + name):
                setattr(self, name, getattr(dev, "mg32_" + name))


@ti.data_oriented
class NarrowedHierarchy:
    """The hierarchy's fields as level 0's f32 part of the cycle reads them: P0 in f32
    (``p0_f32``), the rest (index lists, the coarse right-hand side and solution) as they are."""

    def __init__(self, g):
        for name in ("pt0_rows", "pt0_block", "pt0_fine", "p0_rows", "p0_cols", "c_b", "c_x"):
            setattr(self, name, getattr(g, name))
        self.p0 = g.p0_f32
