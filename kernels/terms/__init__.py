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

A particle term that is a uniform acceleration a (f_i = m_i a: gravity) sets
``uniform`` and gives a (``acceleration(dev)`` in kernels, ``model_acceleration(model)``
on the host). Whatever needs the external acceleration takes the sum over such terms,
never one of them by name: ``uniform_acceleration`` in the kernels (the divergence
check's work, the implicit contact prediction, Newton's round-off scale) and
``uniform_accelerations`` on the host (``Model.energy``, a potential per such term;
``Model.external_acceleration`` and ``Model.external_work``: the exact reference, the
check's initial work, the energy ratio). A new one is its module, its entry here and
its data in ``Model``: nothing that sums them changes.

Parameters: a term's own Model arguments are ``Parameter`` records in its
``parameters`` (drag's ``drag`` and ``wind``), with ``check(values)`` refusing a
combination; ``Model``, ``Model.from_mesh``, scene files, the f32 range check and the
fingerprint take them from ``parameters()``, so a new term's data needs no edit there.

Data: ``arrays(model)`` maps array names to ``(per, values)``, ``per`` one of
"spring" (one value per spring), "particle" (per particle), "vector" (one 3-vector
for the scene) or "scalar". The device bundle holds them in the run's precision
under those names (``dev.<name>``); 0-D ones are read as ``dev.<name>[None]``.
"""

import taichi as ti

from .base import Parameter
from .damping import SpringDamping
from .drag import Drag
from .gravity import Gravity
from .springs import Springs

TERMS = (Springs, SpringDamping, Gravity, Drag)  # the order forces are summed in


def active_terms(model) -> tuple:
    """The terms of ``model``, in ``TERMS`` order."""
    return tuple(term for term in TERMS if term.active(model))


def parameters() -> dict:
    """name -> ``Parameter`` of every term's Model arguments, in ``TERMS`` order."""
    return {p.name: p for term in TERMS for p in term.parameters}


def check_parameters(given) -> dict:
    """name -> checked value (float or read-only (3,) array) of every term parameter,
    from ``given`` (name -> value; a missing one takes its default); ValueError naming
    the parameter. ``given`` must hold no other names."""
    values = {name: p.check(given.get(name, p.default)) for name, p in parameters().items()}
    for term in TERMS:
        term.check({p.name: values[p.name] for p in term.parameters})
    return values


def uniform_accelerations(model) -> dict:
    """name -> (3,) acceleration (m/s^2) of every uniform term in ``TERMS``, in that order,
    active or not (an inactive one's is 0, so the names do not depend on the model)."""
    return {term.name: term.model_acceleration(model) for term in TERMS
            if term.kind == "particle" and term.uniform}


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
