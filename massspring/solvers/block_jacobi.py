"""Block-Jacobi: z_i = A_ii^-1 r_i with the 3x3 diagonal blocks of A."""

from __future__ import annotations

from massspring.kernels import preconditioners

from .base import Preconditioner


class BlockJacobi(Preconditioner):
    """Pointwise; ``dev.minv`` holds the inverse blocks, formed in the operator's refresh."""

    name = "block-jacobi"
    kernel = preconditioners.BlockJacobi

    @classmethod
    def declare(cls, layout, model, settings, cfg):
        layout.add("minv", layout.real, "particle", (3, 3))
