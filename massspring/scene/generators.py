"""Scene generators: particles and springs of a spring, a chain, a cloth and a cube lattice.

Each generator takes keyword parameters (checked by ``scene.spec`` against
``PARAMETERS``) and returns the keyword arguments of :class:`massspring.Model`,
including the surface ``triangles`` a picture draws (none for a spring or chain).

Resolution scaling: a generator's ``mass`` is the total mass, shared equally by
its particles, and its ``stiffness`` and ``damping`` are moduli of the continuum
the springs stand for, so that changing the resolution keeps the physical
behaviour. With spacing h, each spring gets

    ks = stiffness * h**(d - 2),   kd = damping * h**(d - 2)

where d is the dimension of the lattice: a chain (d = 1) has stiffness in N
(force per unit strain: ks = EA / h), a cloth (d = 2) in N/m (per spring ks is
independent of resolution), a cube (d = 3) in N/m^2 (ks = E h).
"""

from __future__ import annotations

import numpy as np

from massspring.support.defaults import GRAVITY

# name -> {parameter: default}; the default's type is the parameter's type.
PARAMETERS = {
    "spring": {"length": 1.0, "displacement": 0.1, "mass": 1.0, "stiffness": 100.0,
               "damping": 0.5, "gravity": [0.0, 0.0, 0.0]},
    "chain": {"count": 20, "length": 1.0, "mass": 0.1, "stiffness": 1000.0, "damping": 0.0,
              "gravity": list(GRAVITY), "mass_ratio": 1.0, "rest_scale": 1.0, "spread": 1.0, "pin": "end"},
    "grid": {"resolution": 32, "size": 1.0, "mass": 1.0, "stiffness": 1e4, "damping": 0.0,
             "shear": 1.0, "bend": 0.1, "pin": "corners", "gravity": list(GRAVITY),
             "compress": 1.0, "crumple": 0.0, "seed": 0, "upright": False, "layers": 1,
             "spacing": 0.1, "turn": 0.0, "throw": [0.0, 0.0, 0.0]},
    "lattice": {"resolution": 6, "size": 0.5, "mass": 1.0, "stiffness": 2e4, "damping": 0.0,
                "squash": 0.8, "spin": 2.0, "gravity": list(GRAVITY)},
}

PIN_CHOICES = ("none", "corners", "edge", "side")
CHAIN_PINS = ("end", "none")


def spring(length, displacement, mass, stiffness, damping, gravity):
    """One spring along x: particle 0 fixed at the origin, particle 1 pulled to
    x = length + displacement. ``mass`` is particle 1's mass (kg); ``stiffness``
    (N/m) and ``damping`` (N s/m) are the spring's own ks and kd."""
    _positive("length", length)
    _positive("mass", mass)
    _not_negative(stiffness=stiffness, damping=damping)
    return dict(positions=[[0.0, 0.0, 0.0], [length + displacement, 0.0, 0.0]], springs=[[0, 1]],
                masses=[mass, mass], stiffness=stiffness, damping=damping, rest_lengths=length,
                gravity=gravity, fixed=[0])


def chain(count, length, mass, stiffness, damping, gravity, mass_ratio=1.0, rest_scale=1.0, spread=1.0, pin="end"):
    """A rope of ``count`` particles, initially straight along x from the origin, its first
    particle fixed (``pin`` "end"; "none": nothing fixed, it falls): it swings down under
    gravity. ``stiffness`` in N (EA), ``damping`` in N s.

    Extreme variants: ``mass_ratio`` is the last (free end) particle's mass over
    each other particle's (a heavy weight on a light rope; ``mass`` stays the
    total); ``rest_scale`` scales the springs' rest lengths (0: zero-length
    springs); ``spread`` scales the initial spacing (0: every particle starts at
    the fixed one, coincident)."""
    _at_least("count", count, 2)
    _positive("length", length)
    _positive("mass", mass)
    _positive("mass_ratio", mass_ratio)
    _at_least("rest_scale", rest_scale, 0.0)
    _at_least("spread", spread, 0.0)
    _not_negative(stiffness=stiffness, damping=damping)
    if pin not in CHAIN_PINS:
        raise ValueError(f"pin: expected one of {', '.join(CHAIN_PINS)}, got {pin!r}")
    h = length / (count - 1)
    x = np.zeros((count, 3))
    x[:, 0] = np.arange(count) * h * spread
    springs = np.stack([np.arange(count - 1), np.arange(1, count)], axis=1)
    masses = np.ones(count)
    masses[-1] = mass_ratio
    return dict(positions=x, springs=springs, masses=mass * masses / masses.sum(), stiffness=stiffness / h,
                damping=damping / h, rest_lengths=h * rest_scale, gravity=gravity, fixed=[0] if pin == "end" else [])


def grid(resolution, size, mass, stiffness, damping, shear, bend, pin, gravity,
         compress=1.0, crumple=0.0, seed=0, upright=False, layers=1, spacing=0.1, turn=0.0,
         throw=(0.0, 0.0, 0.0)):
    """A square cloth of resolution x resolution particles in the z = 0 plane (``upright``:
    in the y = 0 plane, its y running up as z, like a flag), with structural, shear (diagonal)
    and bend (skip-one) springs. ``shear`` and ``bend`` scale their stiffness and
    damping relative to the structural springs. ``pin``: "corners" (the two corners at
    y = size), "edge" (the whole y = size edge), "side" (the whole x = 0 edge: a flag's
    pole when upright) or "none". ``stiffness`` in N/m, ``damping`` in N s/m.

    Extreme initial states (rest lengths stay those of the flat square of side
    ``size``): ``compress`` scales the initial positions about the pinned edge's
    middle (0.5: half the rest size, every spring compressed); ``crumple`` in [0, 1]
    blends each particle towards a uniformly random point of a cube of side
    ``size * compress`` (1: fully crumpled; pinned particles stay put), drawn from a
    generator seeded by ``seed``.

    ``layers`` sheets (>= 1), each a copy of the first raised by ``spacing`` (m) along
    the sheet's normal and turned by ``turn`` degrees more than the one below about the
    normal through the sheet's centre; pins hold the first (lowest) sheet only; ``mass``
    is each sheet's. ``throw`` (m/s, 3 numbers): the initial velocity of every sheet above
    the first, in world axes (a sheet thrown at a resting one)."""
    _at_least("resolution", resolution, 2)
    _at_least("layers", layers, 1)
    _positive("spacing", spacing)
    if not isinstance(turn, (int, float)) or isinstance(turn, bool) or not np.isfinite(turn):
        raise ValueError(f"turn: expected a finite number of degrees, got {turn!r}")
    _velocity("throw", throw)
    _positive("size", size)
    _positive("mass", mass)
    _positive("compress", compress)
    _at_least("seed", seed, 0)
    _not_negative(stiffness=stiffness, damping=damping, shear=shear, bend=bend)
    if not 0.0 <= crumple <= 1.0:
        raise ValueError(f"crumple: must be in [0, 1], got {crumple!r}")
    if pin not in PIN_CHOICES:
        raise ValueError(f"pin: expected one of {', '.join(PIN_CHOICES)}, got {pin!r}")
    r = resolution
    h = size / (r - 1)
    idx = np.arange(r * r).reshape(r, r)  # idx[row (y), column (x)]
    gx, gy = np.meshgrid(np.arange(r) * h, np.arange(r) * h)
    rest = np.stack([gx.ravel(), gy.ravel(), np.zeros(r * r)], axis=1)
    anchor = np.array([size / 2, size, 0.0])
    flat = anchor + compress * (rest - anchor)
    cube = anchor + compress * size * (np.random.default_rng(seed).random((r * r, 3)) - [0.5, 1.0, 0.5])
    x = (1.0 - crumple) * flat + crumple * cube
    pairs, factors = [], []
    for a, b, factor in (
        (idx[:, :-1], idx[:, 1:], 1.0), (idx[:-1, :], idx[1:, :], 1.0),           # structural
        (idx[:-1, :-1], idx[1:, 1:], shear), (idx[:-1, 1:], idx[1:, :-1], shear),  # shear
        (idx[:, :-2], idx[:, 2:], bend), (idx[:-2, :], idx[2:, :], bend),          # bend
    ):
        if factor > 0 and a.size:
            pairs.append(np.stack([a.ravel(), b.ravel()], axis=1))
            factors.append(np.full(a.size, float(factor)))
    springs = np.concatenate(pairs)
    factor = np.concatenate(factors)
    fixed = {"none": [], "corners": [idx[-1, 0], idx[-1, -1]], "edge": list(idx[-1, :]),
             "side": list(idx[:, 0])}[pin]
    x[fixed] = flat[fixed]  # pins are not crumpled
    rest_lengths = np.linalg.norm(rest[springs[:, 1]] - rest[springs[:, 0]], axis=1)
    triangles = _cell_triangles(idx)
    if layers > 1:
        x, springs, factor, rest_lengths, triangles = _stack(x, springs, factor, rest_lengths, triangles,
                                                            [size / 2, size / 2], layers, spacing, turn)
    if upright:
        x = x[:, [0, 2, 1]]  # (x, y, z) -> (x, z, y): the cloth stands in the y = 0 plane
    v = np.zeros_like(x)
    v[r * r:] = throw
    return dict(positions=x, springs=springs, masses=mass / (r * r), stiffness=stiffness * factor, velocities=v,
                damping=damping * factor, rest_lengths=rest_lengths, gravity=gravity,
                fixed=np.array(fixed, dtype=np.int64), triangles=triangles)


def _stack(x, springs, factor, rest_lengths, triangles, centre, layers, spacing, turn):
    """``layers`` copies of a sheet in the z = 0 plane, copy k raised by k spacing and
    turned by k turn degrees about the vertical through ``centre`` (x, y)."""
    n, centre = len(x), np.array([*centre, 0.0])
    copies = []
    for k in range(layers):
        angle = np.radians(k * turn)
        rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        copies.append(centre + (x - centre) @ rotation.T + [0.0, 0.0, k * spacing])
    return (np.concatenate(copies), np.concatenate([springs + k * n for k in range(layers)]),
            np.tile(factor, layers), np.tile(rest_lengths, layers),
            np.concatenate([triangles + k * n for k in range(layers)]))


def lattice(resolution, size, mass, stiffness, damping, squash, spin, gravity):
    """A jelly cube of resolution^3 particles with edge, face-diagonal and body-diagonal
    springs, free to fall. It starts squashed along z by the factor ``squash`` (1 =
    at rest) and spinning about z at ``spin`` rad/s, so it wobbles as it drops.
    ``stiffness`` in N/m^2, ``damping`` in N s/m^2."""
    _at_least("resolution", resolution, 2)
    _positive("size", size)
    _positive("mass", mass)
    _positive("squash", squash)
    _not_negative(stiffness=stiffness, damping=damping)
    r = resolution
    h = size / (r - 1)
    idx = np.arange(r ** 3).reshape(r, r, r)
    grid_axes = np.meshgrid(*(np.arange(r) * h,) * 3, indexing="ij")
    rest = np.stack([g.ravel() for g in grid_axes], axis=1) - size / 2
    pairs = []
    for offset in _neighbour_offsets():
        a = idx[_slices(offset, start=True)]
        b = idx[_slices(offset, start=False)]
        pairs.append(np.stack([a.ravel(), b.ravel()], axis=1))
    springs = np.concatenate(pairs)
    rest_lengths = np.linalg.norm(rest[springs[:, 1]] - rest[springs[:, 0]], axis=1)
    x = rest * np.array([1.0, 1.0, squash])
    v = spin * np.stack([-x[:, 1], x[:, 0], np.zeros(len(x))], axis=1)
    faces = (idx[0], idx[-1], idx[:, 0], idx[:, -1], idx[:, :, 0], idx[:, :, -1])
    return dict(positions=x, springs=springs, masses=mass / r ** 3, stiffness=stiffness * h,
                damping=damping * h, rest_lengths=rest_lengths, velocities=v, gravity=gravity,
                triangles=np.concatenate([_cell_triangles(face) for face in faces]))


def _neighbour_offsets():
    """Lattice offsets (one of each +-pair) with coordinates in {-1, 0, 1}: 13 directions."""
    out = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                o = (dx, dy, dz)
                if o > (0, 0, 0):
                    out.append(o)
    return out


def _slices(offset, start):
    """Index slices pairing each lattice site with its neighbour at ``offset``."""
    out = []
    for o in offset:
        if o == 0:
            out.append(slice(None))
        elif (o > 0) == start:
            out.append(slice(None, -1))
        else:
            out.append(slice(1, None))
    return tuple(out)


GENERATORS = {"spring": spring, "chain": chain, "grid": grid, "lattice": lattice}


def counts(generator, params):
    """(particles, springs) a generator will make with ``params``, without making them
    (so that a scene too large for memory is refused before any allocation)."""
    if generator == "spring":
        return 2, 1
    if generator == "chain":
        c = max(int(params["count"]), 0)
        return c, max(c - 1, 0)
    if generator == "grid":
        r = max(int(params["resolution"]), 0)
        springs = 2 * r * max(r - 1, 0)
        springs += 2 * max(r - 1, 0) ** 2 if params["shear"] > 0 else 0
        springs += 2 * r * max(r - 2, 0) if params["bend"] > 0 else 0
        layers = max(int(params.get("layers", 1)), 1)
        return layers * r * r, layers * springs
    r = max(int(params["resolution"]), 0)
    return r ** 3, sum(int(np.prod([max(r - abs(o), 0) for o in offset])) for offset in _neighbour_offsets())


def _cell_triangles(idx):
    """Two triangles per cell of a 2D index grid, split along the (0, 0)-(1, 1) diagonal
    (its edges are structural or shear springs)."""
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return np.concatenate([np.stack([a, b, c], axis=1), np.stack([a, c, d], axis=1)]).astype(np.int64)


def _positive(name, value):
    if not value > 0:
        raise ValueError(f"{name}: must be > 0, got {value!r}")


def _at_least(name, value, low):
    if not value >= low:
        raise ValueError(f"{name}: must be >= {low}, got {value!r}")


def _velocity(name, value):
    ok = isinstance(value, (list, tuple)) and len(value) == 3 and all(
        isinstance(c, (int, float)) and not isinstance(c, bool) and np.isfinite(c) for c in value)
    if not ok:
        raise ValueError(f"{name}: expected 3 finite numbers (m/s), got {value!r}")


def _not_negative(**moduli):
    """The moduli (stiffness, damping) and factors a generator scales its springs by are >= 0
    (checked here, by their names, rather than per spring by the Model)."""
    for name, value in moduli.items():
        if not value >= 0:
            raise ValueError(f"{name}: must be >= 0, got {value:g}")
