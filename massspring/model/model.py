"""The static description of a mass-spring system: plain, validated numpy data.

A :class:`Model` compiles no kernel and allocates no field: it reads the force terms'
host side (``massspring.model.terms``) for its parameters and uniform accelerations. (Those
terms and the colliders name their classes of ``ti.func``s, so importing this module
imports Taichi.) Everything is checked in the constructor so that bad input fails with
a ``ValueError`` naming the argument before any kernel is compiled or launched.

Units are SI by convention (m, kg, s, N): positions in m, masses in kg, stiffness
in N/m, damping in N s/m, gravity in m/s^2. Nothing in the code depends on the
choice as long as it is consistent.
"""

from __future__ import annotations

import hashlib
import inspect
from dataclasses import dataclass

import numpy as np

from massspring.model import mesh
from massspring.support.defaults import GRAVITY
from massspring.model import terms
from massspring.model.terms import Gradient
from massspring.model.colliders import COLLIDERS, MAX_COLLIDERS, Collider
from massspring.model.controls import Controls
from massspring.model.self_collision import SelfCollision, check_thickness
from massspring.model.strain_limit import check as strain_limit_check
from massspring.support.text import brief
from massspring.support.validate import MAX_MAGNITUDE, real_array, real_number  # noqa: F401 (MAX_MAGNITUDE: documented here)


# The arrays that make up a model's physics (``Model.fingerprint``); ``triangles`` only draw it.
# "drag" and "wind" are term parameters kept here, where they were first hashed, so that
# saved states still restart; a later term's parameters join only when not at their defaults.
# The Model's own differentiable arguments besides its terms' (``terms.Gradient``): the
# initial state ("state": rows (n, 3), in ``lx``/``lv``), the masses and the pins' velocities
# ("pin": a row per pinned particle).
GRADIENTS = (Gradient("masses", "particle", "gm"), Gradient("positions", "state", "lx"),
             Gradient("velocities", "state", "lv"), Gradient("pin_velocity", "pin", "gp"))
PHYSICS = ("positions", "springs", "masses", "stiffness", "damping", "rest_lengths", "velocities", "gravity", "fixed",
           "pin_velocity", "drag", "wind")

def _per_item(name, value, count, what, low=None, low_text=""):
    """A scalar broadcast to ``count`` items, or an array of shape (count,); every
    value (the scalar too, even with no items) must be ``> low`` or ``>= low``."""
    arr = real_array(name, value)
    if arr.ndim != 0 and arr.shape != (count,):
        raise ValueError(f"{name}: expected a scalar or shape ({count},) (one per {what}), got shape {arr.shape}")
    if low is not None:
        bad = arr < low if low_text == ">=" else arr <= low
        if np.any(bad):
            if arr.ndim == 0:
                raise ValueError(f"{name}: must be {low_text} {low:g}, got {float(arr):g}")
            k = int(np.argmax(bad))
            raise ValueError(f"{name}: must be {low_text} {low:g}, {what} {k} has {arr[k]:g}")
    return np.full(count, float(arr)) if arr.ndim == 0 else arr


def _readonly(arr):
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Model:
    """Particles joined by damped springs (seed Eq. 1-3).

    Parameters
    ----------
    positions : (n, 3) float, m
        Initial particle positions.
    springs : (m, 2) int
        Particle indices of each spring's two ends.
    masses : float or (n,) float, kg
        Particle masses, all >= 1e-100 (fixed particles too: the value is unused for them).
    stiffness : float or (m,) float, N/m
        Spring constants ``ks`` (>= 0).
    damping : float or (m,) float, N s/m
        Spring damping constants ``kd`` (>= 0), acting along each spring (Eq. 2).
    rest_lengths : None, float or (m,) float, m
        Rest lengths ``l0`` (>= 0); ``None`` takes the initial distances.
    velocities : None or (n, 3) float, m/s
        Initial velocities (zero if None). A fixed particle's velocity is set to 0.
    gravity : (3,) float, m/s^2
        Uniform gravitational acceleration ``g`` (Eq. 3).
    fixed : None, indices (k,) int, or a bool mask (n,)
        Pinned particles: their velocity is exactly their pin velocity (0 by default) at all times.
    triangles : None or (t, 3) int
        Surface triangles (particle indices) for drawing, and for self-collision
        when it is on (otherwise the physics never reads them). Empty when None.
    colliders : sequence of colliders (``massspring.model.colliders.COLLIDERS``: ``Plane``, ``Sphere``, ``Box``)
        Obstacles the particles cannot enter (at most 31); stored as a tuple.
{term_parameters}    pin_velocity : None or (k, 3) float, m/s
        Kinematic pins: the constant velocity of each pinned particle, one row per
        entry of ``fixed`` in the order given (ascending indices for a mask); zero
        if None. Stored in the order of the stored ``fixed`` (sorted); a pinned
        particle's initial velocity is its pin velocity.
    self_collision : None or ``massspring.SelfCollision``
        Keeps the mesh of ``triangles`` from passing through itself (needs triangles);
        None: off.
    strain_limit : None or float > 0
        The largest stretch l / l0 - 1 of any spring after a step
        (``massspring.passes.strain_limit``: springs stretched further are shortened after each
        step, every integrator); None: no limit.
    controls : None or ``massspring.Controls``
        Time-varying inputs: keyframed pins (then ``pin_velocity`` is their first
        interval's velocity), wind (a model with drag) and actuated rest lengths per
        interval (``massspring.model.controls``). None: the values above hold throughout.

    The force terms' own parameters (``terms.parameters()``: {term_names}) are the
    keyword arguments listed after ``colliders``, each stored under its name as a float or
    a read-only (3,) array.

    All arrays are stored as read-only float64/int64 copies under the constructor's
    argument names; ``fixed`` is stored as sorted unique indices. Numbers must be
    real (not bools, strings or complex), finite, and of magnitude at most
    ``MAX_MAGNITUDE`` (1e100), so that the products the kernels form stay finite.
    """

    positions: np.ndarray
    springs: np.ndarray
    masses: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray
    rest_lengths: np.ndarray
    velocities: np.ndarray
    gravity: np.ndarray
    fixed: np.ndarray
    triangles: np.ndarray
    colliders: tuple
    pin_velocity: np.ndarray
    self_collision: object
    controls: object
    strain_limit: object

    def __init__(self, positions, springs, masses=1.0, stiffness=1e3, damping=0.0,
                 rest_lengths=None, velocities=None, gravity=GRAVITY, fixed=None, triangles=None,
                 colliders=(), pin_velocity=None, self_collision=None, controls=None, strain_limit=None,
                 **term_parameters):
        x = real_array("positions", positions)
        if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 1:
            raise ValueError(f"positions: expected shape (n, 3) with n >= 1, got shape {x.shape}")
        n = x.shape[0]

        try:
            s = np.array(springs)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"springs: cannot be read as an array of indices ({exc})") from None
        if s.size == 0 and s.dtype.kind in "iufb":
            s = s.reshape(0, 2)
        if s.ndim != 2 or s.shape[1] != 2:
            raise ValueError(f"springs: expected shape (m, 2), got shape {s.shape}")
        if s.dtype.kind == "f":
            if not np.all(np.isfinite(s)) or np.any(s != np.round(s)):
                raise ValueError("springs: particle indices must be integers")
        elif s.dtype.kind not in "iu":
            raise ValueError(f"springs: particle indices must be integers, got dtype {s.dtype}")
        s = s.astype(np.int64)
        m = s.shape[0]
        if m and (s.min() < 0 or s.max() >= n):
            k = int(np.argwhere((s < 0) | (s >= n))[0][0])
            raise ValueError(f"springs: spring {k} = {s[k].tolist()} has an index outside 0..{n - 1}")
        self_loops = np.flatnonzero(s[:, 0] == s[:, 1])
        if self_loops.size:
            k = int(self_loops[0])
            raise ValueError(f"springs: spring {k} joins particle {s[k, 0]} to itself")

        mass = _per_item("masses", masses, n, "particle", 1.0 / MAX_MAGNITUDE, ">=")
        ks = _per_item("stiffness", stiffness, m, "spring", 0.0, ">=")
        kd = _per_item("damping", damping, m, "spring", 0.0, ">=")
        if rest_lengths is None:
            l0 = np.linalg.norm(x[s[:, 1]] - x[s[:, 0]], axis=1) if m else np.zeros(0)
        else:
            l0 = _per_item("rest_lengths", rest_lengths, m, "spring", 0.0, ">=")

        if velocities is None:
            v = np.zeros((n, 3))
        else:
            v = real_array("velocities", velocities)
            if v.shape != (n, 3):
                raise ValueError(f"velocities: expected shape ({n}, 3), got shape {v.shape}")
            v = v.copy()

        g = real_array("gravity", gravity)
        if g.shape != (3,):
            raise ValueError(f"gravity: expected 3 components, got shape {g.shape}")

        fixed_idx = _fixed_indices(fixed, n)
        pins = _pin_velocities(pin_velocity, fixed, fixed_idx)
        if controls is not None and not isinstance(controls, Controls):
            raise ValueError(f"controls: expected a massspring.Controls, got {type(controls).__name__}")
        if controls is not None and controls.pin_targets is not None:
            if np.any(pins != 0):
                raise ValueError("pin_velocity: the pins follow controls.pin_targets; give one or the other")
            controls.check(m, fixed_idx, drag=True)  # the pins' rows, before they are read
            pins = controls.pin_velocities(x[fixed_idx])[0]
        v[fixed_idx] = pins
        tris = _triangles(triangles, n)
        unknown = sorted(set(term_parameters) - set(terms.parameters()))
        if unknown:
            raise TypeError(f"Model() got an unexpected keyword argument {unknown[0]!r}")
        forces = terms.check_parameters(term_parameters)

        for name, value in (("positions", x), ("springs", s), ("masses", mass), ("stiffness", ks),
                            ("damping", kd), ("rest_lengths", l0), ("velocities", v),
                            ("gravity", g), ("fixed", fixed_idx), ("triangles", tris), ("pin_velocity", pins)):
            object.__setattr__(self, name, _readonly(np.ascontiguousarray(value)))
        for name, value in forces.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "colliders", _colliders(colliders))
        if self.colliders:
            from massspring.model.colliders import check_start_outside

            check_start_outside(self.colliders, x, self.free_mask())
        object.__setattr__(self, "self_collision", _self_collision(self_collision, tris, x))
        if controls is not None:
            controls.check(m, fixed_idx, drag=self.has_drag)
        object.__setattr__(self, "controls", controls)
        object.__setattr__(self, "strain_limit", strain_limit_check(strain_limit, m))

    @classmethod
    def from_mesh(cls, vertices, faces, **parameters) -> Model:
        """A cloth or shell from a polygon mesh: structural springs on its edges, shear
        springs on the diagonals of its quads and larger faces, bending springs across
        its interior edges, masses lumped from the face areas, pins by index or by a
        box; the (fan-triangulated) faces become ``triangles``. Parameters and units:
        ``massspring.model.mesh.mesh_arguments``."""
        known = set(inspect.signature(mesh.mesh_arguments).parameters) | set(terms.parameters())
        unknown = sorted(set(parameters) - known)
        if unknown:
            raise TypeError(f"Model.from_mesh() got an unexpected keyword argument {unknown[0]!r}")
        return cls(**mesh.mesh_arguments(vertices, faces, **parameters))

    def fingerprint(self) -> str:
        """sha256 (hex) of the physics arrays (``PHYSICS``: names, dtypes, shapes and
        bytes): two models with the same fingerprint step identically."""
        digest = hashlib.sha256()
        for name in PHYSICS:
            arr = np.ascontiguousarray(getattr(self, name))
            digest.update(f"{name}:{arr.dtype.str}:{arr.shape}".encode())
            digest.update(arr.tobytes())
        for name, parameter in terms.parameters().items():  # a later term's, only when not its default
            value = getattr(self, name)
            if name not in PHYSICS and not parameter.is_default(value):
                digest.update(f"{name}:{np.asarray(value, dtype=np.float64).tobytes().hex()}".encode())
        digest.update(repr(self.colliders).encode())  # frozen dataclasses of floats: repr is exact
        if self.controls is not None:
            digest.update(self.controls.digest())
        if self.strain_limit is not None:
            digest.update(f"strain_limit:{self.strain_limit!r}".encode())
        if self.self_collision is not None:  # the triangles then take part in the physics
            digest.update(repr(self.self_collision).encode())
            digest.update(self.triangles.astype(np.int64).tobytes())
        return digest.hexdigest()

    @property
    def n_particles(self) -> int:
        return self.positions.shape[0]

    @property
    def n_springs(self) -> int:
        return self.springs.shape[0]

    @property
    def has_damping(self) -> bool:
        """True if any spring has kd > 0 (otherwise no damping term is compiled)."""
        return bool(np.any(self.damping > 0))

    @property
    def has_gravity(self) -> bool:
        return bool(np.any(self.gravity != 0))

    @property
    def external_acceleration(self) -> np.ndarray:
        """(3,) m/s^2: the sum of the uniform accelerations (``terms.uniform_accelerations``:
        gravity and any other such term), summed from the first (one alone is itself to the bit)."""
        first, *others = terms.uniform_accelerations(self).values()
        return sum(others, first)

    def external_work(self, positions) -> float:
        """sum_i m_i a . x_i (J), a = ``external_acceleration``, for positions (n, 3) m: minus
        the potential of the uniform forces, so its increase is the work they have done
        (what the divergence check's bound and ``energy_ratio`` count)."""
        x = np.asarray(positions, dtype=np.float64)
        return float(np.sum(self.masses * (x @ self.external_acceleration)))

    @property
    def has_fixed(self) -> bool:
        return self.fixed.size > 0

    @property
    def has_moving_pins(self) -> bool:
        """True if some pinned particle has a non-zero pin velocity or follows keyframes
        (``controls.pin_targets``)."""
        keyframed = self.controls is not None and self.controls.pin_targets is not None and self.has_fixed
        return keyframed or bool(np.any(self.pin_velocity != 0))

    @property
    def has_colliders(self) -> bool:
        return len(self.colliders) > 0

    @property
    def has_friction(self) -> bool:
        """Whether some collider has friction (mu > 0)."""
        return any(collider.friction > 0 for collider in self.colliders)

    @property
    def has_self_collision(self) -> bool:
        return self.self_collision is not None

    @property
    def has_strain_limit(self) -> bool:
        return self.strain_limit is not None

    @property
    def has_drag(self) -> bool:
        return terms.Drag.active(self)

    @property
    def term_parameters(self) -> dict:
        """name -> value of the force terms' parameters (``terms.parameters()``)."""
        return {name: getattr(self, name) for name in terms.parameters()}

    def replaced(self, **changes) -> Model:
        """A Model built from this one's arguments with ``changes`` (constructor
        arguments by name) in place of theirs, checked as any Model is."""
        args = dict(positions=self.positions, springs=self.springs, masses=self.masses, stiffness=self.stiffness,
                    damping=self.damping, rest_lengths=self.rest_lengths, velocities=self.velocities,
                    gravity=self.gravity, fixed=self.fixed, triangles=self.triangles, colliders=self.colliders,
                    pin_velocity=self.pin_velocity, self_collision=self.self_collision, controls=self.controls,
                    strain_limit=self.strain_limit, **self.term_parameters)
        unknown = sorted(set(changes) - set(args))
        if unknown:
            raise TypeError(f"Model.replaced() got an unexpected keyword argument {unknown[0]!r}")
        return Model(**{**args, **changes})

    def free_mask(self) -> np.ndarray:
        """(n,) bool: True for particles that move."""
        mask = np.ones(self.n_particles, dtype=bool)
        mask[self.fixed] = False
        return mask

    def energy(self, positions, velocities) -> dict:
        """Kinetic, spring and potential energy of each uniform force (J) of a state, and their total.

        The keys are "kinetic", "spring", then one per uniform acceleration a
        (``terms.uniform_accelerations``: "gravity", ...) for its potential
        ``-sum_i m_i a . x_i`` (zero at the origin), then "total"; fixed particles have
        zero velocity and constant potential.
        """
        x = np.asarray(positions, dtype=np.float64)
        v = np.asarray(velocities, dtype=np.float64)
        kinetic = 0.5 * float(np.sum(self.masses * np.sum(v * v, axis=1)))
        if self.n_springs:
            length = np.linalg.norm(x[self.springs[:, 1]] - x[self.springs[:, 0]], axis=1)
            spring = 0.5 * float(np.sum(self.stiffness * (length - self.rest_lengths) ** 2))
        else:
            spring = 0.0
        energy = {"kinetic": kinetic, "spring": spring}
        total = kinetic + spring
        for name, a in terms.uniform_accelerations(self).items():
            energy[name] = -float(np.sum(self.masses * (x @ a)))
            total += energy[name]
        energy["total"] = total
        return energy


def _parameter_docs() -> str:
    lines = []
    for p in terms.parameters().values():
        kind = "(3,) float" if p.vector else "float >= 0"
        lines += [f"    {p.name} : {kind}, {p.unit} (default {p.default!r})", f"        {p.doc}"]
    return "\n".join(lines) + "\n"


Model.__doc__ = Model.__doc__.replace("{term_parameters}", _parameter_docs()).replace(
    "{term_names}", ", ".join(terms.parameters()))


def _fixed_indices(fixed, n):
    if fixed is None:
        return np.zeros(0, dtype=np.int64)
    try:
        arr = np.asarray(fixed)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"fixed: cannot be read as indices or a mask ({exc})") from None
    if arr.dtype == bool:
        if arr.shape != (n,):
            raise ValueError(f"fixed: a bool mask must have shape ({n},), got shape {arr.shape}")
        return np.flatnonzero(arr).astype(np.int64)
    arr = arr.reshape(-1)
    if arr.size == 0:
        return np.zeros(0, dtype=np.int64)
    if arr.dtype.kind not in "iu":
        raise ValueError(f"fixed: expected particle indices (int) or a bool mask, got dtype {arr.dtype}")
    if arr.min() < 0 or arr.max() >= n:
        bad = int(arr[(arr < 0) | (arr >= n)][0])
        raise ValueError(f"fixed: index {bad} is outside 0..{n - 1}")
    return np.unique(arr.astype(np.int64))


def _pin_velocities(pin_velocity, fixed, fixed_idx):
    """(k, 3) pin velocities in the order of the sorted ``fixed_idx``, from rows given in the
    order of ``fixed`` as passed (a pin listed twice must get the same velocity twice)."""
    if pin_velocity is None:
        return np.zeros((fixed_idx.size, 3))
    fixed = np.asarray([] if fixed is None else fixed)
    given = np.flatnonzero(fixed) if fixed.dtype == bool else fixed.reshape(-1).astype(np.int64)
    rows = real_array("pin_velocity", pin_velocity)
    if rows.shape != (given.size, 3):
        raise ValueError(f"pin_velocity: expected shape ({given.size}, 3) (one row per entry of fixed), "
                         f"got shape {rows.shape}")
    out = np.zeros((fixed_idx.size, 3))
    out[np.searchsorted(fixed_idx, given)] = rows
    clash = np.flatnonzero(np.any(out[np.searchsorted(fixed_idx, given)] != rows, axis=1))
    if clash.size:
        raise ValueError(f"pin_velocity: particle {given[clash[0]]} is listed in fixed more than once "
                         "with different velocities")
    return out


def _self_collision(value, triangles, positions):
    if value is None:
        return None
    if not isinstance(value, SelfCollision):
        raise ValueError(f"self_collision: expected a massspring.SelfCollision or None, got {brief(value)}")
    if len(triangles) == 0:
        raise ValueError("self_collision: needs the model's triangles (a mesh, a grid or a cloth generator, or "
                         "triangles=...); this model has none")
    check_thickness(value, positions, triangles)
    return value


def _colliders(colliders):
    kinds = " or ".join(cls.__name__ for cls in COLLIDERS.values())
    try:
        items = tuple(colliders)
    except TypeError:
        raise ValueError(f"colliders: expected a sequence of {kinds}, got {brief(colliders)}") from None
    for k, item in enumerate(items):
        if not isinstance(item, Collider):
            raise ValueError(f"colliders: item {k} is not a {kinds}: {brief(item)}")
    if len(items) > MAX_COLLIDERS:
        raise ValueError(f"colliders: at most {MAX_COLLIDERS}, got {len(items)}")
    return items


def _triangles(triangles, n):
    if triangles is None:
        return np.zeros((0, 3), dtype=np.int64)
    try:
        arr = np.asarray(triangles)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"triangles: cannot be read as an array of indices ({exc})") from None
    if arr.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"triangles: expected shape (t, 3), got shape {arr.shape}")
    if arr.dtype.kind not in "iu":
        raise ValueError(f"triangles: expected particle indices (int), got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    if arr.min() < 0 or arr.max() >= n:
        k = int(np.argwhere((arr < 0) | (arr >= n))[0][0])
        raise ValueError(f"triangles: triangle {k} = {arr[k].tolist()} has an index outside 0..{n - 1}")
    repeated = np.flatnonzero((arr[:, 0] == arr[:, 1]) | (arr[:, 1] == arr[:, 2]) | (arr[:, 0] == arr[:, 2]))
    if repeated.size:
        k = int(repeated[0])
        raise ValueError(f"triangles: triangle {k} = {arr[k].tolist()} repeats a particle")
    return arr
