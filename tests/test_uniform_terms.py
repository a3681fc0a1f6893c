"""The uniform-acceleration seam: nothing but the term registry tells which forces are
uniform accelerations (``uniform`` terms of ``massspring.model.terms``), and everything that
needs the external acceleration sums them: the divergence check's work (every stepping
kernel, ``Model.external_work``), the implicit contact prediction, Newton's round-off
scale, ``Model.energy``, ``energy_ratio`` and the exact reference.

The tests register a second uniform acceleration p of their own (``Lift``, a term with
its ``Parameter`` "lift", its ``ti.func``s in ``LiftKernel``, by patching ``TERMS``) and
check that lift p without gravity steps to the bit as gravity p without lift, that
gravity g with lift p steps as gravity g + p to round-off, that the check's bound, the
energy and the contact prediction count its work, and that its parameter reaches
``Model``, ``from_mesh``, scene files, ``--set``, the f32 range check and the
fingerprint with no edit there.
"""

import numpy as np
import pytest
import taichi as ti

import massspring as ms
from massspring.analysis.reference import exact_spring
from massspring.analysis.stability import energy_ratio
from massspring.cli.run import format_energy
from massspring.integrators import INTEGRATORS
from massspring.model import terms
from massspring.kernels.terms import ParticleTerm
from massspring.model.terms import Parameter, Term
from massspring.scene import load_scene
from massspring.scene.spec import parse_scene

ALL = tuple(INTEGRATORS)
IMPLICIT = tuple(name for name, cls in INTEGRATORS.items() if cls.traits.linear_solver)  # contact predicted in the solve
NO_SPRINGS = np.zeros((0, 2), dtype=int)
G = np.array([0.0, 0.0, -9.81])
P = np.array([0.7, -0.3, 1.1])


class LiftKernel(ParticleTerm):
    """f_i = m_i p, p = ``dev.lift`` (m/s^2). A constant force like gravity: all of it in
    Eq. 15's right-hand side, potential -m p . x."""

    name = "lift"
    uniform = True

    @staticmethod
    @ti.func
    def acceleration(dev):
        return dev.lift[None]

    @staticmethod
    @ti.func
    def force(i, dev, x, v):
        return dev.mass[i] * dev.lift[None]

    @staticmethod
    @ti.func
    def rhs(i, dev, x, v):
        return dev.mass[i] * dev.lift[None]

    @staticmethod
    @ti.func
    def potential_change(i, dev, dx):
        return -dev.mass[i] * dev.lift[None].dot(dx)


class Lift(Term):
    """p = ``Model.lift`` (m/s^2); active when p != 0."""

    kernel = LiftKernel
    parameters = (Parameter("lift", (0.0, 0.0, 0.0), "m/s^2", "A uniform acceleration besides gravity."),)

    @staticmethod
    def active(model):
        return bool(np.any(model.lift != 0))

    @staticmethod
    def arrays(model):
        return {"lift": ("vector", model.lift)}

    @staticmethod
    def model_acceleration(model):
        return model.lift


@pytest.fixture
def lift(monkeypatch):
    """Registers ``Lift`` right after gravity (forces are summed in ``TERMS`` order, so a
    lift without gravity takes gravity's place); returns the registry without it."""
    before = terms.TERMS
    registry = list(before)
    registry.insert(registry.index(terms.Gravity) + 1, Lift)
    monkeypatch.setattr(terms, "TERMS", tuple(registry))
    return before


def chain(gravity, colliders=(), lift=(0.0, 0.0, 0.0)):
    """A damped 5-particle chain pinned at one end, swinging down from 0.5 m up."""
    x = np.stack([np.linspace(0.0, 1.0, 5), np.zeros(5), np.full(5, 0.5)], axis=1)
    return ms.Model(x, [[k, k + 1] for k in range(4)], masses=0.1, stiffness=400.0, damping=0.5,
                    velocities=np.tile([0.0, 0.3, 0.0], (5, 1)), fixed=[0], colliders=colliders,
                    gravity=tuple(gravity), lift=lift)


def run_chain(integrator, gravity, contact, lift=(0.0, 0.0, 0.0)):
    """(positions, velocities, check, cg iterations, energy) after 0.75 s (150 implicit steps
    or 1500 explicit ones); a run asked for again (gravity g + p alone, by both tests
    below) is the first one's, read only."""
    key = (integrator, tuple(np.asarray(gravity, dtype=float)), contact, tuple(np.asarray(lift, dtype=float)),
           terms.TERMS)  # the registry too: the terms a run has
    if key not in RUNS:
        RUNS[key] = _run_chain(integrator, gravity, contact, lift)
    return RUNS[key]


RUNS = {}


def _run_chain(integrator, gravity, contact, lift):
    plane = (ms.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), friction=0.3),) if contact else ()
    implicit = integrator in IMPLICIT
    sim = ms.Simulation(chain(gravity, plane, lift), integrator, dt=5e-3 if implicit else 5e-4)
    sim.step(150 if implicit else 1500)
    if contact:
        assert sim.positions[:, 2].min() > -1e-6 and sim.positions[-1, 2] < 0.05  # it reached the plane
    state = (sim.positions, sim.velocities, sim.check, sim.cg_iterations, sim.energy())
    sim.close()
    return state


@pytest.mark.fast_sample(contact=[False], integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ALL)
@pytest.mark.parametrize("contact", [False, True], ids=["free", "plane"])
def test_lift_alone_steps_as_gravity_to_the_bit(lift, integrator, contact):
    """Lift p without gravity is gravity p without lift for the force, the right-hand side
    and the line search's potential, and, through the sums, for the divergence check's
    work, the implicit contact prediction (a plane the chain swings onto) and Newton's
    round-off scale: every bit of the run agrees, and so do the energies."""
    xl, vl, cl, il, el = run_chain(integrator, (0.0, 0.0, 0.0), contact, lift=G + P)
    xg, vg, cg, ig, eg = run_chain(integrator, G + P, contact)
    assert np.array_equal(xl, xg) and np.array_equal(vl, vg) and cl == cg and il == ig
    assert list(el) == list(eg) == ["kinetic", "spring", "gravity", "lift", "total"]
    assert el["lift"] == eg["gravity"] and el["total"] == eg["total"] and el["gravity"] == eg["lift"] == 0


@pytest.mark.fast_sample(contact=[False], integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ALL)
@pytest.mark.parametrize("contact", [False, True], ids=["free", "plane"])
def test_gravity_and_lift_add(lift, integrator, contact):
    """Gravity g with lift p steps as gravity g + p alone, to round-off (m g + m p and
    m (g + p) differ in the last bits)."""
    x2, v2, c2, _, e2 = run_chain(integrator, G, contact, lift=P)
    x1, v1, c1, _, e1 = run_chain(integrator, G + P, contact)
    np.testing.assert_allclose(x2, x1, rtol=0, atol=1e-9)
    np.testing.assert_allclose(v2, v1, rtol=0, atol=1e-8)
    assert c2 == pytest.approx(c1, rel=1e-12, abs=1e-12)
    assert e2["gravity"] + e2["lift"] == pytest.approx(e1["gravity"], rel=1e-9)
    assert e2["total"] == pytest.approx(e1["total"], rel=1e-9, abs=1e-12)


def free_particle(gravity=(0.0, 0.0, 0.0), **lift):
    """Particle 0 (2 kg) free at rest at (0.2, -0.1, 0.3); particle 1 pinned."""
    return ms.Model([[0.2, -0.1, 0.3], [1.0, 0.0, 0.0]], NO_SPRINGS, masses=[2.0, 1.0], gravity=gravity, fixed=[1],
                    **lift)


def test_the_host_sums_count_lift(lift):
    """``Model.external_acceleration``, ``external_work``, ``energy`` and the check's gx0."""
    model = free_particle(G, lift=P)
    m, x = model.masses, model.positions
    assert np.array_equal(model.external_acceleration, G + P)
    assert model.external_work(x) == pytest.approx(float(np.sum(m * (x @ (G + P)))), abs=1e-15)
    assert ms.Simulation(model, "explicit", dt=1e-2).check[1] == model.external_work(x)
    e = model.energy(x, model.velocities)
    assert e["lift"] == pytest.approx(-float(np.sum(m * (x @ P))))
    assert e["total"] == e["kinetic"] + e["spring"] + e["gravity"] + e["lift"]
    assert ", gravity " in format_energy(e, e) and ", lift " in format_energy(e, e)


def test_with_gravity_alone_the_sums_are_gravity_to_the_bit():
    """Without a second term the registry's sums are gravity itself, bit for bit, and the
    energy has the keys it always had."""
    model = free_particle((-0.0, 0.0, -9.81))
    assert list(terms.uniform_accelerations(model)) == ["gravity"]
    a = model.external_acceleration
    assert np.array_equal(a, model.gravity) and np.array_equal(np.signbit(a), np.signbit(model.gravity))
    x = model.positions
    assert model.external_work(x) == -model.energy(x, model.velocities)["gravity"]
    assert list(model.energy(x, model.velocities)) == ["kinetic", "spring", "gravity", "total"]
    sim = ms.Simulation(model, "implicit", dt=1e-2)
    assert sim.stepper.cfg.uniform_terms == (terms.Gravity.kernel,)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ALL)
def test_a_long_lift_does_not_trip_the_divergence_check(lift, integrator):
    """Lift only, 30 s: kinetic energy reaches m (p t)^2 / 2 ~ 1.6e3 J, over 100 times the
    check's base (so over its bound without the lift's work); the kinetic energy is the
    lift's work, and the energy ratio 1."""
    model = free_particle(lift=P)
    sim = ms.Simulation(model, integrator, dt=1e-2)
    steps = 3000
    sim.step(steps)
    e = sim.energy()
    assert e["kinetic"] > 100 * sim.check[0]
    t = steps * 1e-2
    assert e["kinetic"] == pytest.approx(0.5 * 2.0 * float(P @ P) * t * t, rel=1e-9)  # v = p t exactly
    assert e["kinetic"] == pytest.approx(model.external_work(sim.positions) - sim.check[1], rel=1e-3)  # x: O(dt / t)
    assert energy_ratio(model, sim.positions, sim.velocities, sim.check) == pytest.approx(1.0, rel=1e-3)


def test_runaway_is_still_caught_under_lift(lift):
    """The bound grows with the lift's work, not without limit: an explicit spring far
    beyond its stability limit still diverges."""
    model = ms.Model([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], [[0, 1]], stiffness=1e6, rest_lengths=0.9,
                     gravity=(0.0, 0.0, 0.0), fixed=[0], lift=(1.0, 0.0, 0.0))
    sim = ms.Simulation(model, "explicit", dt=1e-2)
    with pytest.raises(ms.DivergenceError):
        sim.step(200)


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", IMPLICIT)
def test_implicit_contact_prediction_counts_lift(lift, integrator):
    """A particle at rest 10 um above a plane, lifted into it with no gravity: the implicit
    step predicts x + dt (v + dt p), inside the plane, so the contact holds its normal
    velocity to 0 in that very step. A prediction that missed the lift (x + dt v, outside)
    would leave it v = dt p into the plane for a step."""
    model = ms.Model([[0.0, 0.0, 1e-5]], NO_SPRINGS, gravity=(0.0, 0.0, 0.0), lift=(0.0, 0.0, -9.81),
                     colliders=[ms.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))])
    sim = ms.Simulation(model, integrator, dt=1e-2)
    sim.step()
    assert np.all(sim.velocities[0] == 0) and np.all(sim.positions[0] == 0)


def test_exact_spring_reference_counts_lift(lift):
    """The exact one-spring reference takes a lift along the axis as it takes gravity, and
    refuses one off the axis (the motion would leave it)."""
    times = np.linspace(0.1, 1.0, 10)

    def spring(gravity, lift=(0.0, 0.0, 0.0)):
        return ms.Model([[0.0, 0.0, 0.0], [0.0, 0.0, -1.1]], [[0, 1]], stiffness=50.0, damping=0.3,
                        rest_lengths=1.0, fixed=[0], gravity=gravity, lift=lift)

    by_gravity = exact_spring(spring(G), times)
    assert np.array_equal(exact_spring(spring((0.0, 0.0, 0.0), G), times).positions, by_gravity.positions)
    assert exact_spring(spring((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)), times) is None


def test_the_parameter_reaches_model_mesh_and_scenes(lift):
    """The term's ``Parameter`` is all it takes: ``Model`` and ``from_mesh`` take and check
    it, every scene form's [model] table and ``--set`` take it (with its default), and a
    bad value is refused naming it."""
    assert np.array_equal(free_particle(lift=P).lift, P) and np.array_equal(free_particle().lift, np.zeros(3))
    assert not free_particle().lift.flags.writeable
    with pytest.raises(ValueError, match=r"^lift: expected 3 components"):
        free_particle(lift=(1.0, 2.0))
    square = ms.Model.from_mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2, 3]], lift=P)
    assert np.array_equal(square.lift, P)
    assert np.array_equal(load_scene("chain").model().lift, np.zeros(3))
    pushed = load_scene("chain").with_settings([f"lift={P.tolist()}"]).model()
    assert np.array_equal(pushed.lift, P) and pushed.external_acceleration == pytest.approx(pushed.gravity + P)
    data = {"description": "t", "integrator": "implicit", "duration": 1.0,
            "model": {"generator": "chain", "count": 3, "lift": [0.0, 1.0, 0.0]}}
    assert np.array_equal(parse_scene(data, "t", "t.toml").model().lift, [0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match=r"--set lift: expected 3 numbers"):
        load_scene("chain").with_settings(["lift=[1, 2]"])


def test_the_parameter_joins_the_fingerprint_only_when_set(lift):
    """At its default the new parameter leaves the fingerprint as it was before the term
    existed (saved states still restart); set, it changes it. The f32 range check names it."""
    with_term, patched = free_particle().fingerprint(), terms.TERMS
    terms.TERMS = lift  # the registry before Lift
    without_term = free_particle().fingerprint()
    terms.TERMS = patched
    assert with_term == without_term
    assert free_particle(lift=P).fingerprint() != with_term
    with pytest.raises(ValueError, match=r"^lift: 1e\+39 is beyond what an f32 run holds"):
        ms.Simulation(free_particle(lift=(1e39, 0.0, 0.0)), "explicit", dt=1e-2, precision="f32")
