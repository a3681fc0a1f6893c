"""Model.from_mesh: spring families counted by hand on known meshes, lumped masses by hand,
pins, a flat mesh at rest, and refused input naming the face or vertex."""

import numpy as np
import pytest

import massspring as ms
from massspring.integrators import INTEGRATORS
from massspring.model import mesh
from massspring.scene import generators

SQUARE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])


def icosahedron():
    p = (1.0 + 5.0 ** 0.5) / 2.0
    v = np.array([[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p], [0, -1, -p], [0, 1, -p],
                  [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]], dtype=float)
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6],
         [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
         [8, 6, 7], [9, 8, 1]]
    return v, np.array(f)


def families(vertices, faces):
    triangles, _, inner = mesh.triangulate(*mesh.faces_array(faces, len(vertices)))
    return {name: pairs.tolist() for name, pairs in mesh.mesh_springs(triangles, inner).items()}


def test_quad_as_two_triangles_has_5_edges_and_1_bending_spring():
    springs = families(SQUARE, [[0, 1, 2], [0, 2, 3]])
    assert springs == {"structural": [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]], "shear": [], "bend": [[1, 3]]}
    model = ms.Model.from_mesh(SQUARE, [[0, 1, 2], [0, 2, 3]], stiffness=200.0, damping=3.0, bend=0.25)
    assert model.n_springs == 6
    bending = np.flatnonzero((model.springs == [1, 3]).all(axis=1))
    assert model.stiffness[bending].tolist() == [50.0] and model.damping[bending].tolist() == [0.75]
    assert sorted(model.stiffness.tolist()) == [50.0] + [200.0] * 5
    assert model.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_quad_face_has_4_sides_and_2_shear_diagonals():
    assert families(SQUARE, [[0, 1, 2, 3]]) == {"structural": [[0, 1], [0, 3], [1, 2], [2, 3]],
                                                "shear": [[0, 2], [1, 3]], "bend": []}
    model = ms.Model.from_mesh(SQUARE, [[0, 1, 2, 3]], stiffness=100.0, shear=0.5)
    assert sorted(model.stiffness.tolist()) == [50.0, 50.0, 100.0, 100.0, 100.0, 100.0]
    assert ms.Model.from_mesh(SQUARE, [[0, 1, 2, 3]], shear=0.0).n_springs == 4


def test_pentagon_shear_springs_are_the_fan_diagonals_and_the_springs_across_them():
    angles = 2 * np.pi * np.arange(5) / 5
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros(5)], axis=1)
    springs = families(ring, [[0, 1, 2, 3, 4]])
    assert springs["structural"] == [[0, 1], [0, 4], [1, 2], [2, 3], [3, 4]]
    assert springs["shear"] == [[0, 2], [0, 3], [1, 3], [2, 4]]  # fan (0, 2), (0, 3); across them (1, 3), (2, 4)
    assert springs["bend"] == []


def test_closed_icosahedron_has_30_edges_and_30_bending_springs():
    v, f = icosahedron()
    springs = families(v, f)
    assert len(springs["structural"]) == 30 and len(springs["bend"]) == 30 and springs["shear"] == []
    edge = np.linalg.norm(v[0] - v[11])
    lengths = ms.Model.from_mesh(v, f).rest_lengths
    # every edge has the same length, every bending pair (two edges apart) the golden ratio times it
    assert np.allclose(lengths[:30], edge) and np.allclose(lengths[30:], edge * (1 + 5 ** 0.5) / 2)


def test_tetrahedron_bending_pairs_are_its_edges_and_are_not_doubled():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]
    assert {k: len(s) for k, s in families(v, f).items()} == {"structural": 6, "shear": 0, "bend": 0}


def test_quad_grid_mesh_has_the_grid_generators_springs():
    # an independent reference: the grid generator's structural and shear springs
    r = 4
    grid = generators.grid(resolution=r, size=1.0, mass=1.0, stiffness=1.0, damping=0.0, shear=1.0, bend=0.0,
                           pin="none", gravity=[0.0, 0.0, 0.0])
    idx = np.arange(r * r).reshape(r, r)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
    model = ms.Model.from_mesh(grid["positions"], quads, bend=0.0)
    assert sorted(map(sorted, model.springs.tolist())) == sorted(map(sorted, grid["springs"].tolist()))


def test_lumped_masses_by_hand():
    # right triangle with legs 3 and 4 (area 6) and, on its hypotenuse (length 5), a triangle of
    # height 4.8 standing straight up from the hypotenuse's middle (area 12)
    v = np.array([[0.0, 0, 0], [3, 0, 0], [0, 4, 0], [1.5, 2, 4.8]])
    area2 = 0.5 * np.linalg.norm(np.cross(v[1] - v[3], v[2] - v[3]))
    assert area2 == pytest.approx(12.0)
    masses = mesh.lumped_masses(v, np.array([0, 1, 2, 1, 3, 2]), np.array([3, 3]), density=0.5)
    assert masses == pytest.approx([1.0, 1.0 + 2.0, 1.0 + 2.0, 2.0], rel=1e-14)
    total = ms.Model.from_mesh(v, [[0, 1, 2], [1, 3, 2]], mass=3.6).masses
    assert total.sum() == pytest.approx(3.6, rel=1e-14) and total == pytest.approx(np.array([1, 3, 3, 2]) * 0.4)
    assert ms.Model.from_mesh(v, [[0, 1, 2], [1, 3, 2]]).masses.sum() == pytest.approx(mesh.DEFAULT_MASS)


@pytest.mark.parametrize("start", range(4))
def test_a_quad_lumps_its_area_evenly_whatever_its_fan(start):
    # a 2 x 1 rectangle: each corner a quarter of its 2 m^2; the fan from any corner alike
    v = np.array([[0.0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]])
    face = np.roll(np.arange(4), -start)
    masses = ms.Model.from_mesh(v, [face], density=0.5).masses
    assert masses == pytest.approx([0.25] * 4, rel=1e-14)


def test_a_polygon_lumps_the_cells_of_its_corners_by_hand():
    # a regular hexagon of side 1 (area 3 sqrt(3) / 2): six equal cells; a trapezoid
    # (0,0)-(4,0)-(3,1)-(1,1): centroid (2, 0.5), cells worked out by hand
    hexagon = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.arange(6) * np.pi / 3])
    masses = ms.Model.from_mesh(hexagon, [list(range(6))], density=2.0).masses
    assert masses == pytest.approx([np.sqrt(3) / 2] * 6, rel=1e-14)
    trapezoid = np.array([[0.0, 0, 0], [4, 0, 0], [3, 1, 0], [1, 1, 0]])
    # corner 0: triangles (0,0)-(2,0)-(2,0.5) and (0,0)-(2,0.5)-(0.5,0.5): 0.5 + 0.375
    # corner 2: (3,1)-(2,1)-(2,0.5) and (3,1)-(2,0.5)-(3.5,0.5): 0.25 + 0.375
    masses = ms.Model.from_mesh(trapezoid, [[0, 1, 2, 3]], density=1.0).masses
    assert masses == pytest.approx([0.875, 0.875, 0.625, 0.625], rel=1e-14)
    assert masses.sum() == pytest.approx(3.0, rel=1e-14)  # the trapezoid's area


@pytest.mark.parametrize("scale", [1e80, 5e99])
def test_a_mesh_at_the_largest_coordinates_lumps_finite_masses(scale, recwarn):
    """Coordinates up to the model's 1e100: the cells' areas (up to 1e200) come out
    finite and exact (no squares that overflow, no numpy warning); masses beyond 1e100
    from a density are refused naming density and saying why."""
    v = np.array([[0.0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]]) * scale
    masses = ms.Model.from_mesh(v, [[0, 1, 2, 3]], mass=4.0).masses
    assert masses == pytest.approx([1.0] * 4, rel=1e-14)
    assert mesh.triangle_areas(v, np.array([[0, 1, 2]])) == pytest.approx([scale * scale], rel=1e-14)
    with pytest.raises(ValueError, match=r"density: 0.2 kg/m\^2 times the mesh's cells .* beyond 1e\+100"):
        ms.Model.from_mesh(v, [[0, 1, 2, 3]], density=0.2)
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def test_icosahedron_masses_are_equal_and_sum_to_the_total():
    v, f = icosahedron()
    masses = ms.Model.from_mesh(v, f, mass=2.4).masses
    assert masses.sum() == pytest.approx(2.4, rel=1e-14) and np.allclose(masses, 0.2, rtol=1e-12)


def test_pins_by_index_and_by_box():
    v, f = icosahedron()
    model = ms.Model.from_mesh(v, f, fixed=[3], pin_box=[[-9, 1.0, -9], [9, 9, 9]])
    assert model.fixed.tolist() == sorted({3} | set(np.flatnonzero(v[:, 1] >= 1.0).tolist()))
    assert ms.Model.from_mesh(v, f, fixed=[2, 4]).fixed.tolist() == [2, 4]


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
def test_flat_mesh_at_rest_stays_at_rest_without_gravity(integrator):
    r = 5
    g = np.arange(r) * 0.25
    x = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    v = np.concatenate([x, np.zeros((r * r, 1))], axis=1)
    idx = np.arange(r * r).reshape(r, r)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
    model = ms.Model.from_mesh(v, quads, stiffness=1e3, damping=1.0, gravity=(0.0, 0.0, 0.0))
    sim = ms.Simulation(model, integrator=integrator, dt=1e-3)
    sim.step(50)
    assert np.abs(sim.positions - v).max() < 1e-12 and np.abs(sim.velocities).max() < 1e-9
    sim.close()


@pytest.mark.parametrize("faces, kwargs, words", [
    ([[0, 1, 2], [0, 2, 2]], {}, ["face 1", "repeats"]),
    ([[0, 1, 2], [0, 2, 7]], {}, ["face 1", "outside 0..4"]),
    ([[0, 1, 2], [0, 1]], {}, ["face 1", "at least 3"]),
    ([[0, 1, 2], [0, 2, 3]], {}, ["vertex 4", "no face"]),
    ([[0, 1, 2], [0, 2, 3], [0, 2, 4]], {}, ["triangle 2", "zero area"]),  # 0, 2, 4 on one line
    ([[0, 1, 2], [0, 2, 3, 4]], {"density": 1.0, "mass": 1.0}, ["density, mass"]),
    ([[0, 1, 2], [0, 2, 3, 4]], {"bend": -1.0}, ["bend"]),
    ([[0, 1, 2], [0, 2, 3, 4]], {"mass": 0.0}, ["mass"]),
    ([[0, 1, 2], [0, 2, 3, 4]], {"pin_box": [[5, 5, 5], [6, 6, 6]]}, ["pin_box", "no vertex"]),
    ([[0, 1, 2], [0, 2, 3, 4]], {"pin_box": [[1, 1, 1], [0, 0, 0]]}, ["pin_box", "low corner"]),
    ([[0, 1, 2], [0, 2, 3, 4]], {"fixed": [9]}, ["fixed", "9"]),
    ([[0, 1, 2.0]], {}, ["faces", "integers"]),
    ([], {}, ["faces", "no faces"]),
])
def test_bad_meshes_are_refused_naming_the_face(faces, kwargs, words):
    v = np.concatenate([SQUARE, [[2.0, 2.0, 0.0]]])
    with pytest.raises(ValueError) as info:
        ms.Model.from_mesh(v, faces, **kwargs)
    for word in words:
        assert word in str(info.value), (word, str(info.value))


def test_from_mesh_takes_colliders_air_and_moving_pins():
    v, f = icosahedron()
    sphere = ms.Sphere((0.0, 0.0, -3.0), 1.0, friction=0.3)
    plain = ms.Model.from_mesh(v, f, fixed=[3], pin_box=[[-9, 1.0, -9], [9, 9, 9]])
    model = ms.Model.from_mesh(v, f, fixed=[3], pin_box=[[-9, 1.0, -9], [9, 9, 9]], colliders=[sphere], drag=0.2,
                               wind=(1.0, 0.0, 0.0), pin_velocity=(0.0, 0.0, 0.5))
    assert model.colliders == (sphere,) and model.drag == 0.2 and model.wind.tolist() == [1.0, 0.0, 0.0]
    assert model.fixed.tolist() == plain.fixed.tolist() and len(plain.fixed) > 1
    assert np.array_equal(model.pin_velocity, np.tile([0.0, 0.0, 0.5], (len(plain.fixed), 1)))
    # the same model as one made by hand from the plain mesh's arrays with those additions
    by_hand = ms.Model(plain.positions, plain.springs, plain.masses, plain.stiffness, plain.damping,
                       plain.rest_lengths, gravity=plain.gravity, fixed=plain.fixed, triangles=plain.triangles,
                       colliders=[sphere], drag=0.2, wind=(1.0, 0.0, 0.0),
                       pin_velocity=np.tile([0.0, 0.0, 0.5], (len(plain.fixed), 1)))
    assert model.fingerprint() == by_hand.fingerprint()
    # a row per pin: fixed first, then the box's vertices in ascending order
    box = np.flatnonzero(v[:, 1] >= 1.0)
    rows = np.arange(3 * (1 + len(box)), dtype=float).reshape(-1, 3)
    model = ms.Model.from_mesh(v, f, fixed=[3], pin_box=[[-9, 1.0, -9], [9, 9, 9]], pin_velocity=rows)
    order = np.argsort(np.concatenate([[3], box]))
    assert np.array_equal(model.pin_velocity, rows[order])
    with pytest.raises(TypeError, match=r"Model\.from_mesh\(\) got an unexpected keyword argument 'colour'"):
        ms.Model.from_mesh(v, f, colour="red")
