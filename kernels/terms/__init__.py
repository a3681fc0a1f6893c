"""Force terms: each a class of ``ti.func``s plus the device arrays it reads.

A scene's forces are the tuple of active terms (``active(model)``), compiled into
the kernels with ``ti.static`` loops: a term a scene does not have is not in the
tuple, so it costs no code, no loop and no array. Adding a force term means one
module here and one entry in ``TERMS``.

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

Data: ``arrays(model)`` maps array names to ``(per, values)``, ``per`` one of
"spring" (one value per spring), "particle" (per particle), "vector" (one 3-vector
for the scene) or "scalar". The device bundle holds them in the run's precision
under those names (``dev.<name>``); 0-D ones are read as ``dev.<name>[None]``.
"""

from .damping import SpringDamping
from .drag import Drag
from .gravity import Gravity
from .springs import Springs

TERMS = (Springs, SpringDamping, Gravity, Drag)  # the order forces are summed in


def active_terms(model) -> tuple:
    """The terms of ``model``, in ``TERMS`` order."""
    return tuple(term for term in TERMS if term.active(model))
