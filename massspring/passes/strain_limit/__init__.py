"""The strain limit as a pass: the forward pass after each step (``forward.py``) and, beside
it, its run backwards in a gradient's run (``backward.py``). Its value is
``Model(strain_limit=...)``, checked by ``massspring.model.strain_limit``."""

from massspring.passes.strain_limit.forward import ITERATIONS, TOLERANCE, StrainLimitPass

__all__ = ["ITERATIONS", "TOLERANCE", "StrainLimitPass"]
