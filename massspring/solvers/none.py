"""No preconditioning: plain CG."""

from __future__ import annotations

from massspring.kernels import preconditioners

from .base import Preconditioner


class NoPreconditioner(Preconditioner):
    name = "none"
    kernel = preconditioners.Identity
