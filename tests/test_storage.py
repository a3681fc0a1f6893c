"""Field storage and ndarray storage run the same kernels and give the same results."""

import numpy as np
import pytest

import massspring as ms


@pytest.fixture(scope="module")
def cloth():
    model = ms.load_scene("cloth").with_params(resolution=6).model()
    rng = np.random.default_rng(3)
    velocities = rng.normal(scale=0.1, size=model.positions.shape)
    return ms.Model(model.positions, model.springs, masses=model.masses, stiffness=model.stiffness,
                    damping=model.damping, velocities=velocities, gravity=model.gravity, fixed=model.fixed)


@pytest.mark.parametrize("integrator, dt", [("implicit", 1 / 60), ("symplectic", 1e-4)])
def test_field_and_ndarray_storage_agree(cloth, integrator, dt):
    runs = {}
    for storage in ("ndarray", "field"):
        sim = ms.Simulation(cloth, integrator=integrator, dt=dt, storage=storage)
        sim.step(5)
        assert sim.info()["storage"] == storage
        runs[storage] = (sim.positions, sim.velocities, list(sim.cg_iterations))
        sim.close()
    (x_nd, v_nd, it_nd), (x_f, v_f, it_f) = runs["ndarray"], runs["field"]
    assert it_nd == it_f
    # Same serial arithmetic; only the compiler's fusing of multiply-adds may differ.
    assert np.allclose(x_f, x_nd, rtol=0, atol=1e-12)
    assert np.allclose(v_f, v_nd, rtol=0, atol=1e-10 * np.abs(v_nd).max())


def test_closed_simulation_frees_fields_and_others_still_run(cloth):
    first = ms.Simulation(cloth, integrator="explicit", dt=1e-4, storage="field")
    first.step(2)
    first.close()
    first.close()  # idempotent
    second = ms.Simulation(cloth, integrator="explicit", dt=1e-4, storage="ndarray")
    second.step(2)
    assert np.all(np.isfinite(second.positions))


def test_bad_storage_and_loops_named():
    model = ms.Model([[0, 0, 0], [1, 0, 0]], [[0, 1]])
    with pytest.raises(ValueError, match="storage"):
        ms.Simulation(model, storage="disk")
    with pytest.raises(ValueError, match="loops"):
        ms.Simulation(model, loops="threads")


def test_released_fields_are_reused_by_the_next_simulation_of_that_size(cloth):
    from massspring.storage import POOL

    first = ms.Simulation(cloth, integrator="implicit", dt=1 / 60, storage="field")
    first.step(2)
    first.close()
    idle = len(POOL._idle)
    second = ms.Simulation(cloth, integrator="implicit", dt=1 / 60, storage="field")
    # model, state and CG arrays all came from the pool: no new fields, no new compilation
    assert len(POOL._idle) == idle - 3
    assert np.array_equal(second.positions, cloth.positions)  # refilled from the model
    assert not np.any(second._integrator.r.to_numpy())  # work arrays start at zero
    second.step(2)
    fresh = ms.Simulation(cloth, integrator="implicit", dt=1 / 60, storage="ndarray")
    fresh.step(2)
    assert np.allclose(second.positions, fresh.positions, rtol=0, atol=1e-12)
    second.close()


def test_simulations_are_garbage_collected():
    import gc
    import weakref

    model = ms.Model([[0, 0, 0], [1, 0, 0]], [[0, 1]], gravity=(0, 0, -1.0))
    refs = []
    for integrator in ("explicit", "implicit"):
        sim = ms.Simulation(model, integrator=integrator)
        sim.step(1)
        refs.append(weakref.ref(sim))
        del sim
    gc.collect()
    assert all(ref() is None for ref in refs)
