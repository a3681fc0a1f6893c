"""Force terms, device side: each a class of ``ti.func``s reading the device arrays its
host side (``massspring.model.terms``: parameters, ``active``, ``arrays``) declares.

Two kinds:

* ``SpringTerm``: acts along each spring's unit direction n (from end i to end j),
  evaluated once per spring: the force on end i is ``tension * n`` (N), on end j its
  opposite. ``rhs_tension`` is its share of f - D v in Eq. 15's right-hand side
  (equal to ``tension`` unless the term depends on velocity), and
  ``coefficients`` its share (a, b) of the spring's block S = a I + b n n^T of
  A = M - dt D - dt^2 K (Eq. 13-15), added to (i,i), (j,j) and subtracted from
  (i,j), (j,i).
* ``ParticleTerm``: a force on each particle on its own (``force``, N), its share
  of f - D v (``rhs``), and of the diagonal of A (``diagonal``, a multiple of I).

For the line search of the Newton-solved integrators (``kernels/newton.py``) each
term also gives its change of potential energy (``potential_change``, J: a
conservative force is minus its gradient) or of Rayleigh dissipation
(``dissipation_change``, W: a damping force is minus its gradient in the
velocities); the defaults are 0 (a term with neither adds nothing there).

A particle term that is a uniform acceleration a (f_i = m_i a: gravity) sets
``uniform`` and gives a as ``acceleration(dev)``. Whatever needs the external
acceleration in the kernels takes the sum over such terms, never one of them by name:
``uniform_acceleration`` (the divergence check's work, the implicit contact
prediction, Newton's round-off scale).
"""

import taichi as ti

from .base import ParticleTerm, SpringTerm  # noqa: F401 (the bases of a term's class)
from .damping import SpringDamping
from .drag import Drag
from .gravity import Gravity
from .springs import Springs


@ti.func
def uniform_acceleration(dev, cfg: ti.template()):
    """a = the sum of the active uniform terms' ``acceleration(dev)`` (``cfg.uniform_terms``;
    m/s^2, a float64 vec3; 0 without any). Summed from the first term on, so that with
    one term a is that term's value to the bit."""
    a = ti.Vector.zero(ti.f64, 3)
    for k, term in ti.static(enumerate(cfg.uniform_terms)):
        if ti.static(k == 0):
            a = ti.cast(term.acceleration(dev), ti.f64)
        else:
            a += ti.cast(term.acceleration(dev), ti.f64)
    return a
