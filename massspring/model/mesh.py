"""The keyword arguments of a Model from a polygon mesh: springs on its edges and across them, lumped
masses, pins.

Plain numpy, like the generators in ``scene/generators.py``: vertices (n, 3) float in
m, faces as vertex indices (0-based). A face with more than three vertices is split
into a fan of triangles (v0, v[i], v[i+1]); the triangles become the Model's
surface (``Model.triangles``).

Springs, in this order (each family's springs sorted by their end indices):

* structural: one per unique edge of the faces, ks = ``stiffness``, kd = ``damping``;
* shear: the diagonals of the faces of four or more vertices (the fan's own
  diagonals and the spring across each of them, e.g. both diagonals of a quad),
  ``shear`` x ``stiffness`` and ``shear`` x ``damping``; a triangle mesh has none;
* bending: across every other edge that exactly two triangles share, between the two
  vertices opposite it, ``bend`` x ``stiffness`` and ``bend`` x ``damping``. An edge
  of one triangle only (the boundary) or of three or more (non-manifold) gets none;
  a pair that is already a spring is not added again.

Rest lengths are the initial distances. ``stiffness`` is in N/m per spring, as for
the grid generator's cloth (d = 2: ks does not change with the mesh resolution), and
``shear``/``bend`` scale it like the grid's ``shear``/``bend``. A factor of 0 leaves
that family out.

Masses are lumped from the faces, not from the fan: each face gives each of its
corners the part of its area nearer to it, the quadrilateral of the corner, the
midpoints of its two edges and the face's centroid (a third of a triangle, a quarter
of a parallelogram, whatever the triangulation), times ``density`` (kg/m^2), or
scaled so that they sum to ``mass`` (kg). Every vertex
must belong to a face (else it would have no mass) and no triangle may be degenerate
(a repeated vertex or zero area).
"""

from __future__ import annotations


import numpy as np

from massspring.support.defaults import GRAVITY
from massspring.support.validate import MAX_MAGNITUDE, real_array, real_number

# [model] parameters of a mesh scene (``scene/spec.py``) and their defaults; None: not given.
PARAMETERS = {"mesh": "", "density": None, "mass": None, "stiffness": 1e4, "damping": 0.0, "bend": 0.1,
              "shear": 1.0, "fixed": [], "pin_box": None, "gravity": list(GRAVITY)}
# The types of the parameters whose default does not tell (spec.py checks them).
TYPES = {"density": float, "mass": float, "fixed": "indices", "pin_box": "box"}
DEFAULT_MASS = 1.0       # kg, total, when neither density nor mass is given
AREA_RTOL = 1e-12        # a triangle is degenerate if |cross| <= AREA_RTOL * (bounding box extent)^2


def faces_array(faces, n):
    """``faces`` as (indices (sum of sizes,) int64, sizes (f,) int64), checked.

    ``faces``: an (f, k) int array (k >= 3), or a sequence of faces, each a sequence of
    at least 3 vertex indices within 0..n-1, none repeated. Raises ValueError naming
    the face."""
    if isinstance(faces, np.ndarray):
        if faces.ndim != 2:
            raise ValueError(f"faces: expected shape (f, k) or a list of faces, got shape {faces.shape}")
        rows, sizes, indices = faces, np.full(len(faces), faces.shape[1], dtype=np.int64), faces.reshape(-1)
    else:
        try:
            rows = list(faces)
            sizes = np.array([len(row) for row in rows], dtype=np.int64)
            indices = np.array([i for row in rows for i in row])
        except TypeError:
            raise ValueError("faces: expected an (f, k) array or a list of faces (lists of vertex indices)") from None
    if not len(sizes):
        raise ValueError("faces: the mesh has no faces")
    few = np.flatnonzero(sizes < 3)
    if few.size:
        raise ValueError(f"faces: face {few[0]} = {_show(rows[few[0]])} needs at least 3 vertex indices")
    if indices.dtype.kind not in "iu":
        raise ValueError(f"faces: vertex indices must be integers, got {indices.dtype} values")
    indices = indices.astype(np.int64)
    starts = np.cumsum(sizes) - sizes
    outside = np.flatnonzero((indices < 0) | (indices >= n))
    if outside.size:
        k = int(np.searchsorted(starts, outside[0], side="right")) - 1
        raise ValueError(f"faces: face {k} = {_show(rows[k])} has an index outside 0..{n - 1}")
    for size in np.unique(sizes):  # a vertex twice in a face; the faces of one size at a time
        group = np.flatnonzero(sizes == size)
        block = np.sort(indices[starts[group, None] + np.arange(size)], axis=1)
        repeated = np.flatnonzero(np.any(block[:, 1:] == block[:, :-1], axis=1))
        if repeated.size:
            k = int(group[repeated[0]])
            raise ValueError(f"faces: face {k} = {_show(rows[k])} repeats a vertex")
    return indices, sizes


def _show(row):
    return str(np.asarray(row).tolist())


def triangulate(indices, sizes):
    """Fan triangulation (v0, v[i], v[i+1]), i = 1..k-2, of faces as ``faces_array`` returns them.

    Returns (triangles (t, 3) int64, face_of (t,) int64: the face of each triangle,
    inner (t, 3) bool: whether edge j of a triangle, from its vertex j to vertex
    j + 1 (mod 3), is a diagonal inside its face rather than one of the face's sides).
    """
    starts = np.cumsum(sizes) - sizes
    per_face = sizes - 2
    face_of = np.repeat(np.arange(len(sizes)), per_face)
    i = np.arange(len(face_of)) - np.repeat(np.cumsum(per_face) - per_face, per_face) + 1
    base = starts[face_of]
    triangles = np.stack([indices[base], indices[base + i], indices[base + i + 1]], axis=1)
    inner = np.stack([i >= 2, np.zeros(len(i), dtype=bool), i + 1 <= sizes[face_of] - 2], axis=1)
    return triangles.astype(np.int64), face_of.astype(np.int64), inner


def degenerate_triangles(vertices, triangles, rtol=AREA_RTOL):
    """Indices of the triangles of zero area: |(b - a) x (c - a)| <= rtol * L^2, with L
    the largest extent of the vertices' bounding box."""
    x = np.asarray(vertices, dtype=np.float64)
    extent = float(np.ptp(x, axis=0).max())
    return np.flatnonzero(2.0 * triangle_areas(x, triangles) <= rtol * extent * extent)


def unused_vertices(n, triangles):
    """Indices of the vertices in no triangle."""
    used = np.zeros(n, dtype=bool)
    used[np.asarray(triangles).reshape(-1)] = True
    return np.flatnonzero(~used)


def _norms(rows):
    """Euclidean norms of the rows, without overflow where the squares would (rows of
    cross products of coordinates up to the model's 1e100 reach 1e200)."""
    scale = np.abs(rows).max(axis=1) if len(rows) else np.zeros(0)
    safe = np.where(scale > 0, scale, 1.0)
    return scale * np.linalg.norm(rows / safe[:, None], axis=1)


def triangle_areas(vertices, triangles):
    """(t,) areas (m^2) of the triangles."""
    x = np.asarray(vertices, dtype=np.float64)
    a, b, c = (x[triangles[:, i]] for i in range(3))
    return 0.5 * _norms(np.cross(b - a, c - a))


def corner_areas(vertices, indices, sizes):
    """(sum of sizes,) area (m^2) of each face corner's cell: the quadrilateral of the
    corner, the midpoints of its two edges and the face's centroid (the mean of its
    vertices), as two triangles. A convex planar face is the union of its cells.
    Faces as ``faces_array`` returns them."""
    x = np.asarray(vertices, dtype=np.float64)
    starts = np.repeat(np.cumsum(sizes) - sizes, sizes)
    size = np.repeat(sizes, sizes)
    k = np.arange(len(indices)) - starts                   # each corner's place in its face
    corner = x[indices]
    after = x[indices[starts + (k + 1) % size]]
    before = x[indices[starts + (k - 1) % size]]
    centroid = np.repeat(np.add.reduceat(corner, np.cumsum(sizes) - sizes) / sizes[:, None], sizes, axis=0)
    half = (after - corner) / 2, (centroid - corner), (before - corner) / 2
    return 0.5 * (_norms(np.cross(half[0], half[1])) + _norms(np.cross(half[1], half[2])))


def lumped_masses(vertices, indices, sizes, density=None, mass=None):
    """(n,) particle masses (kg): each vertex gets its corners' cells (``corner_areas``)
    of the faces (as ``faces_array`` returns them) times ``density`` (kg/m^2), or a
    share of ``mass`` (kg) in proportion to them; give at most one (neither:
    ``DEFAULT_MASS``)."""
    if density is not None and mass is not None:
        raise ValueError("density, mass: give one of them, not both")
    share = np.bincount(indices, weights=corner_areas(vertices, indices, sizes), minlength=len(vertices))
    if density is not None:
        masses = _positive("density", density) * share
        if masses.max(initial=0.0) > MAX_MAGNITUDE:
            raise ValueError(f"density: {density:g} kg/m^2 times the mesh's cells (up to {share.max():.3g} m^2) gives "
                             f"masses up to {masses.max():.3g} kg, beyond {MAX_MAGNITUDE:g}: scale the mesh down, "
                             f"lower the density or give the total mass")
        return masses
    total = DEFAULT_MASS if mass is None else _positive("mass", mass)
    return total * (share / share.sum())


def _positive(name, value):
    return real_number(name, value, 0.0, ">")


def _unique_pairs(a, b, n):
    """Rows (min, max) of the vertex pairs (a, b), each once, sorted."""
    pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1).reshape(-1, 2)
    _, first = np.unique(pairs[:, 0] * n + pairs[:, 1], return_index=True)
    return pairs[first]


def _in_sorted(values, table):
    """Whether each of ``values`` is in the sorted array ``table``."""
    if not len(table):
        return np.zeros(len(values), dtype=bool)
    position = np.minimum(np.searchsorted(table, values), len(table) - 1)
    return table[position] == values


def mesh_springs(triangles, inner=None):
    """The springs of a triangulated mesh by family: a dict of (k, 2) int64 arrays
    "structural", "shear" and "bend" (see the module docstring), each sorted.
    ``inner``: which triangle edges are diagonals inside a face, as ``triangulate``
    returns it (None: every triangle is a face of its own, so there is no shear)."""
    triangles = np.asarray(triangles, dtype=np.int64)
    n = int(triangles.max()) + 1
    a, b = triangles.reshape(-1), np.roll(triangles, -1, axis=1).reshape(-1)  # edge j of triangle j // 3
    opposite = np.roll(triangles, 1, axis=1).reshape(-1)                     # the vertex off that edge
    keys = np.minimum(a, b) * n + np.maximum(a, b)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    first = np.flatnonzero(np.concatenate([[True], sorted_keys[1:] != sorted_keys[:-1]]))
    count = np.diff(np.append(first, len(keys)))
    edge = order[first]  # one triangle edge per unique edge
    side = np.ones(len(keys), dtype=bool) if inner is None else ~np.asarray(inner, dtype=bool).reshape(-1)
    diagonal = np.add.reduceat(side[order], first) == 0  # every triangle edge on it is inside a face
    two = count == 2
    other = order[np.minimum(first + 1, len(order) - 1)]
    structural = _unique_pairs(a[edge[~diagonal]], b[edge[~diagonal]], n)
    across = two & diagonal
    shear = _unique_pairs(np.concatenate([a[edge[diagonal]], opposite[edge[across]]]),
                          np.concatenate([b[edge[diagonal]], opposite[other[across]]]), n)
    across = two & ~diagonal
    bend = _unique_pairs(opposite[edge[across]], opposite[other[across]], n)
    bend = bend[bend[:, 0] != bend[:, 1]]  # two copies of one triangle: the same vertex opposite
    taken = np.sort(np.concatenate([structural, shear]) @ np.array([n, 1]))
    bend = bend[~_in_sorted(bend @ np.array([n, 1]), taken)]
    return {"structural": structural, "shear": shear, "bend": bend}


def pins_in_box(vertices, pin_box):
    """Indices of the vertices inside ``pin_box`` ((low corner), (high corner)) in m,
    bounds included; an empty selection is an error (a box that misses the mesh)."""
    box = real_array("pin_box", pin_box)
    if box.shape != (2, 3):
        raise ValueError(f"pin_box: expected two corners [[x, y, z], [x, y, z]], got shape {box.shape}")
    if np.any(box[0] > box[1]):
        raise ValueError(f"pin_box: the low corner {box[0].tolist()} exceeds the high one {box[1].tolist()}")
    x = np.asarray(vertices, dtype=np.float64)
    inside = np.flatnonzero(np.all((x >= box[0]) & (x <= box[1]), axis=1))
    if not inside.size:
        raise ValueError(f"pin_box: no vertex lies in the box {box.tolist()} (the mesh spans "
                         f"{x.min(axis=0).tolist()} to {x.max(axis=0).tolist()})")
    return inside


def mesh_arguments(vertices, faces, *, density=None, mass=None, stiffness=1e4, damping=0.0, bend=0.1, shear=1.0,
                   fixed=None, pin_box=None, gravity=GRAVITY, velocities=None, colliders=(), pin_velocity=None,
                   self_collision=None, strain_limit=None, **term_parameters):
    """The keyword arguments of :class:`Model` for a cloth or shell from a polygon mesh
    (see the module docstring); ``Model.from_mesh`` builds it.

    Parameters
    ----------
    vertices : (n, 3) float, m
    faces : (f, k) int with k >= 3, or a sequence of faces of any sizes >= 3
        Vertex indices (0-based) of each face; faces of more than 3 vertices are
        fan-triangulated.
    density : float, kg/m^2, or None
        Surface density: each particle gets a third of its triangles' areas times it.
    mass : float, kg, or None
        Total mass, shared in proportion to those areas (give density or mass, not
        both; neither: 1 kg).
    stiffness : float, N/m (default 1e4)
        ks of the structural springs (one per edge).
    damping : float, N s/m (default 0)
        kd of the structural springs.
    bend : float >= 0 (default 0.1)
        ks and kd of the bending springs (across each interior edge) relative to the structural ones.
    shear : float >= 0 (default 1)
        ks and kd of the shear springs (diagonals of faces of 4 or more vertices), relative.
    fixed : None or indices (k,) int
        Pinned particles (vertex indices).
    pin_box : None or ((x, y, z), (x, y, z)), m
        Also pin every vertex inside this axis-aligned box (bounds included; it must hold one).
    gravity : (3,) float, m/s^2 (default (0, 0, -9.81))
    velocities : None or (n, 3) float, m/s
    colliders, self_collision, strain_limit, and the force terms' parameters (drag, wind, ...) : as for :class:`Model`
    pin_velocity : None, (3,) or (k, 3) float, m/s
        The pins' velocity: one for every pin, or a row per pin (``fixed``, then the
        vertices in ``pin_box`` in ascending order).

    Bad input raises ValueError naming the argument (and the face or vertex).
    """
    x = real_array("vertices", vertices)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 3:
        raise ValueError(f"vertices: expected shape (n, 3) with n >= 3, got shape {x.shape}")
    indices, sizes = faces_array(faces, len(x))
    triangles, _, inner = triangulate(indices, sizes)
    bad = degenerate_triangles(x, triangles)
    if bad.size:
        raise ValueError(f"faces: triangle {bad[0]} = {triangles[bad[0]].tolist()} has zero area")
    unused = unused_vertices(len(x), triangles)
    if unused.size:
        raise ValueError(f"vertices: vertex {unused[0]} belongs to no face (it would have no mass)")
    factors = {"structural": 1.0, "shear": real_number("shear", shear, 0.0, ">="),
               "bend": real_number("bend", bend, 0.0, ">=")}
    families = mesh_springs(triangles, inner)
    kept = [name for name in factors if factors[name] > 0]
    factor = np.concatenate([np.full(len(families[name]), factors[name]) for name in kept])
    pins = [np.asarray(fixed).reshape(-1)] if fixed is not None and np.size(fixed) else []
    if pin_box is not None:
        pins.append(pins_in_box(x, pin_box))
    pins = np.concatenate(pins) if pins else None
    if pin_velocity is not None and np.shape(pin_velocity) == (3,):  # one velocity for every pin
        pin_velocity = np.tile(real_array("pin_velocity", pin_velocity), (0 if pins is None else len(pins), 1))
    return dict(positions=x, springs=np.concatenate([families[name] for name in kept]),
                masses=lumped_masses(x, indices, sizes, density, mass),
                stiffness=real_number("stiffness", stiffness, 0.0, ">=") * factor,
                damping=real_number("damping", damping, 0.0, ">=") * factor, gravity=gravity,
                fixed=pins, triangles=triangles, velocities=velocities, colliders=colliders,
                pin_velocity=pin_velocity, self_collision=self_collision, strain_limit=strain_limit,
                **term_parameters)
