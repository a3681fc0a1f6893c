"""Force terms, host side: for each term, its Model parameters, when a model has it and
the device arrays it reads; its ``ti.func``s are a class in ``kernels/terms/`` that the
term names as ``kernel`` (as a collider names its kind class).

A scene's forces are the tuple of active terms (``active_terms(model)``); the device
config holds their kernel classes, compiled into the kernels with ``ti.static`` loops,
so a term a scene does not have costs no code, no loop and no array. Adding a force
term means its class of ``ti.func``s in ``kernels/terms/``, its class here and one
entry in ``TERMS``.

Parameters: a term's own Model arguments are ``Parameter`` records in its
``parameters`` (drag's ``drag`` and ``wind``), with ``check(values)`` refusing a
combination; ``Model``, ``Model.from_mesh``, scene files, the f32 range check and the
fingerprint take them from ``parameters()``, so a new term's data needs no edit there.

Data: ``arrays(model)`` maps array names to ``(per, values)``, ``per`` one of
"spring" (one value per spring), "particle" (per particle), "vector" (one 3-vector
for the scene) or "scalar". The device bundle holds them in the run's precision
under those names (``dev.<name>``); 0-D ones are read as ``dev.<name>[None]``.

A uniform acceleration a (f_i = m_i a: gravity; its kernel class sets ``uniform``)
gives a twice: ``acceleration(dev)`` in its kernel class and ``model_acceleration(model)``
here. Whatever needs the external acceleration sums such terms and names none:
``kernels.terms.uniform_acceleration`` in the kernels, ``uniform_accelerations`` on the
host (``Model.energy``, ``Model.external_acceleration``, ``Model.external_work``).
"""

from dataclasses import dataclass

import numpy as np

from massspring.kernels import terms as kernels
from massspring.support.text import brief
from massspring.support.validate import real_array


@dataclass(frozen=True)
class Parameter:
    """A Model argument of a force term: a number >= 0 (``default`` a float) or a
    3-vector (``default`` a 3-tuple), in ``unit``. ``Model``, ``Model.from_mesh``, scene
    files (a key of every form's [model] table and ``--set``), the f32 range check and the
    fingerprint take it from here; ``doc`` is its line in ``Model``'s docstring."""

    name: str
    default: float | tuple
    unit: str
    doc: str

    @property
    def vector(self) -> bool:
        return isinstance(self.default, tuple)

    def check(self, value):
        """``value`` as a float >= 0 or a read-only (3,) float64 array; ValueError naming the parameter."""
        arr = real_array(self.name, value)
        if self.vector:
            if arr.shape != (3,):
                raise ValueError(f"{self.name}: expected 3 components, got shape {arr.shape}")
            arr = np.array(arr, dtype=np.float64)
            arr.setflags(write=False)
            return arr
        if arr.shape != () or not arr >= 0:
            raise ValueError(f"{self.name}: expected a number >= 0 ({self.unit}), got {brief(value)}")
        return float(arr)

    def is_default(self, value) -> bool:
        return bool(np.all(np.asarray(value) == np.asarray(self.default)))


@dataclass(frozen=True)
class Gradient:
    """A Model argument that ``massspring.gradient`` differentiates (a ``wrt`` name):
    ``per`` is the shape of its gradient, "spring" (m,), "particle" (n,), "vector" (3,)
    or "scalar"; ``field`` is its accumulator in the adjoint bundle (a value per spring,
    per particle, or a 3-vector per particle for "vector"; "vector" and "scalar" ones are
    summed over the particles when read); ``absent``: if given, it is asked only of a
    model in which its term is active, and the error otherwise says "the model has no
    <absent>" (drag's need drag > 0). A term lists its records in
    ``gradients``, the Model its own (``model.GRADIENTS``), so a term registered with
    records is differentiable in them by name."""

    name: str
    per: str
    field: str
    absent: str = ""


class Term:
    """A force term's host side. ``kernel``: its class of ``ti.func``s (``kernels.terms``),
    whose ``name``, ``kind`` ("spring" or "particle") and ``uniform`` the term takes."""

    kernel = None
    name = ""
    kind = ""
    uniform = False
    parameters = ()  # Parameter records: the term's own Model arguments
    gradients = ()  # Gradient records: the Model arguments of the term that gradients take

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        cls.name, cls.kind, cls.uniform = cls.kernel.name, cls.kernel.kind, cls.kernel.uniform

    @staticmethod
    def check(values):
        """Refuse (ValueError) a combination of the term's checked ``values`` (name -> value)."""

    @staticmethod
    def active(model) -> bool:
        raise NotImplementedError

    @staticmethod
    def arrays(model) -> dict:
        raise NotImplementedError


class Springs(Term):
    kernel = kernels.Springs
    gradients = (Gradient("stiffness", "spring", "gks"), Gradient("rest_lengths", "spring", "gl0"))

    @staticmethod
    def active(model):
        return model.n_springs > 0

    @staticmethod
    def arrays(model):
        return {"ks": ("spring", model.stiffness), "l0": ("spring", model.rest_lengths)}


class SpringDamping(Term):
    """Active when any spring has kd > 0."""

    kernel = kernels.SpringDamping
    gradients = (Gradient("damping", "spring", "gkd"),)  # also where kd = 0: the gradient of adding damping

    @staticmethod
    def active(model):
        return model.has_damping

    @staticmethod
    def arrays(model):
        return {"kd": ("spring", model.damping)}


class Gravity(Term):
    """Active when g != 0."""

    kernel = kernels.Gravity
    gradients = (Gradient("gravity", "vector", "gg"),)

    @staticmethod
    def active(model):
        return model.has_gravity

    @staticmethod
    def arrays(model):
        return {"gravity": ("vector", model.gravity)}

    @staticmethod
    def model_acceleration(model):
        return model.gravity


class Drag(Term):
    """Active when drag > 0; wind needs drag."""

    kernel = kernels.Drag
    gradients = (Gradient("drag", "scalar", "gdrag", "air drag (drag = 0); give it drag > 0"),
                 Gradient("wind", "vector", "gwind", "air drag (drag = 0); give it drag > 0"))
    parameters = (
        Parameter("drag", 0.0, "N s/m", "Linear air drag on every particle: f_i = -drag (v_i - wind)."),
        Parameter("wind", (0.0, 0.0, 0.0), "m/s",
                  "The air's velocity; non-zero only with drag > 0 (it acts through drag alone)."),
    )

    @staticmethod
    def check(values):
        if any(values["wind"] != 0) and values["drag"] == 0:
            raise ValueError("wind: has no effect without drag (drag = 0): give drag > 0 or no wind")

    @staticmethod
    def active(model):
        return model.drag > 0

    @staticmethod
    def arrays(model):
        return {"drag": ("scalar", model.drag), "wind": ("vector", model.wind)}


TERMS = (Springs, SpringDamping, Gravity, Drag)  # the order forces are summed in


def active_terms(model) -> tuple:
    """The terms of ``model``, in ``TERMS`` order."""
    return tuple(term for term in TERMS if term.active(model))


def gradients() -> dict:
    """name -> (``Gradient``, its term) of every term's differentiable Model arguments, in ``TERMS`` order."""
    return {g.name: (g, term) for term in TERMS for g in term.gradients}


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
