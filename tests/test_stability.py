"""Stability: the spectrum estimate against exact and dense references, divergence
detection in every integrator (last good state kept), the extreme scenes, the CLI."""

import math

import numpy as np
import pytest

import massspring as ms
from massspring.analysis import stability
from massspring.cli import main
from massspring.scene import load_scene
from conftest import FULL, PATHS, dense_jacobians, dense_step, free_dofs, simulation


def dense_lambda_max(model, x):
    """Largest eigenvalue of M^-1 (-K) on the free DOFs, K of Eq. 13 as written (numpy)."""
    K, _ = dense_jacobians(model, x, definiteness_fix=False)
    free = free_dofs(model)
    w = 1.0 / np.sqrt(np.repeat(model.masses, 3))[free]
    sym = -K[np.ix_(free, free)] * w[:, None] * w[None, :]
    return float(np.linalg.eigvalsh(sym)[-1])


def test_one_spring_omega_and_explicit_growth():
    scene = load_scene("spring").with_params(damping=0.0)
    model = scene.model()
    pred = stability.predict(model)
    assert pred.omega_max == pytest.approx(math.sqrt(100.0 / 1.0), rel=1e-2)
    assert pred.symplectic_dt == pytest.approx(2.0 / 10.0, rel=1e-2)
    # Undamped 1D oscillator: explicit Euler multiplies v^2 + omega^2 u^2 by exactly rho^2 per step.
    dt = 0.02
    sim = scene.simulation("explicit", dt=dt)
    energies = []
    for _ in range(20):
        e = sim.energy()
        energies.append(e["kinetic"] + e["spring"])
        sim.step(1)
    measured = np.sqrt(np.array(energies[1:]) / np.array(energies[:-1]))
    assert measured == pytest.approx(pred.explicit_growth(dt), rel=1e-9)
    assert pred.explicit_growth(dt) == pytest.approx(math.sqrt(1 + (10 * dt) ** 2), rel=1e-9)


def test_one_spring_damped_growth_matches_prediction():
    scene = load_scene("spring")  # kd = 0.5: c = kd / m = 0.5 1/s
    pred = stability.predict(scene.model())
    assert pred.damping_rate == pytest.approx(0.5, rel=1e-6)
    dt, steps = 0.01, 400
    sim = scene.simulation("explicit", dt=dt)
    e0 = sum(sim.energy()[k] for k in ("kinetic", "spring"))
    sim.step(steps)
    e1 = sum(sim.energy()[k] for k in ("kinetic", "spring"))
    # over many steps the amplitude grows as rho^steps (up to a bounded phase factor)
    assert (e1 / e0) ** (1 / (2 * steps)) == pytest.approx(pred.explicit_growth(dt), rel=2e-3)
    assert pred.explicit_growth(dt) > 1 > pred.explicit_growth(0.5 * pred.explicit_stable_dt)


@pytest.mark.parametrize("settle", [0, 40])
def test_chain_omega_matches_dense_eigenvalue(settle):
    scene = load_scene("chain").with_params(count=8)
    sim = scene.simulation("implicit")
    sim.step(settle)  # 40 steps: a swinging, stretched state (transverse terms of Eq. 13 matter)
    x = sim.positions
    spec = stability.spectrum(sim.model, x)
    dense = dense_lambda_max(sim.model, x)
    assert spec.lambda_max == pytest.approx(dense, rel=1e-6)
    assert spec.omega_max == pytest.approx(math.sqrt(dense), rel=1e-6)
    assert spec.residual <= 1e-6 * dense  # the Lanczos estimate says how far it may be off


def test_stiff_cloth_omega_matches_dense_eigenvalue():
    model = load_scene("stiffcloth").with_params(resolution=6).model()
    spec = stability.spectrum(model)
    dense = dense_lambda_max(model, model.positions)
    assert spec.lambda_max == pytest.approx(dense, rel=1e-6)
    assert spec.residual <= 1e-6 * dense


def assert_last_good_state(sim, exc, fresh):
    """After ``exc`` the simulation holds the state of step exc.step - 1: the same bits
    as ``fresh`` (an identical new Simulation) stepped exc.step - 1 times one by one."""
    assert sim.steps == exc.step - 1 and sim.time == pytest.approx((exc.step - 1) * sim.dt)
    assert np.all(np.isfinite(sim.positions)) and np.all(np.isfinite(sim.velocities))
    for _ in range(exc.step - 1):
        fresh.step(1)
    np.testing.assert_array_equal(sim.positions, fresh.positions)
    np.testing.assert_array_equal(sim.velocities, fresh.velocities)


@FULL
@pytest.mark.parametrize("path", PATHS)
def test_symplectic_above_limit_raises_and_keeps_last_good_state(path):
    scene = load_scene("stiffchain").with_params(count=10)
    pred = stability.predict(scene.model())
    sim = simulation(scene.model(), path, integrator="symplectic", dt=1.5 * pred.symplectic_dt)
    with pytest.raises(ms.DivergenceError) as info:
        sim.step(500)
    exc = info.value
    assert isinstance(exc, RuntimeError) and exc.cause == "runaway" and exc.step <= 100
    assert f"step {exc.step}" in str(exc) and "t = " in str(exc)
    assert_last_good_state(sim, exc, simulation(scene.model(), path, integrator="symplectic",
                                                dt=1.5 * pred.symplectic_dt))
    # below the limit the same scene runs
    ok = simulation(scene.model(), path, integrator="symplectic", dt=0.9 * pred.symplectic_dt)
    ok.step(500)
    assert np.all(np.isfinite(ok.positions))


@FULL
@pytest.mark.parametrize("path", PATHS)
def test_explicit_far_above_doubling_dt_raises(path):
    scene = load_scene("stiffchain").with_params(count=10)
    pred = stability.predict(scene.model())
    dt = 1e4 * pred.explicit_doubling_dt
    assert pred.explicit_growth(dt) > 1.0
    sim = simulation(scene.model(), path, integrator="explicit", dt=dt)
    with pytest.raises(ms.DivergenceError) as info:
        sim.step(5000)
    assert_last_good_state(sim, info.value, simulation(scene.model(), path, integrator="explicit", dt=dt))


def test_explicit_serial_stops_at_the_failing_step_like_single_steps():
    scene = load_scene("stiffchain").with_params(count=10)
    dt = 1.5 * stability.predict(scene.model()).symplectic_dt
    many = scene.simulation("explicit", dt=dt)
    with pytest.raises(ms.DivergenceError) as a:
        many.step(500)
    one = scene.simulation("explicit", dt=dt)
    with pytest.raises(ms.DivergenceError) as b:
        for _ in range(500):
            one.step(1)
    assert a.value.step == b.value.step
    assert np.array_equal(many.positions, one.positions) and np.array_equal(many.velocities, one.velocities)


@FULL
@pytest.mark.parametrize("path", PATHS)
def test_implicit_far_above_symplectic_limit_stays_finite(path):
    scene = load_scene("stiffchain").with_params(count=10)
    pred = stability.predict(scene.model())
    sim = simulation(scene.model(), path, integrator="implicit", dt=100 * pred.symplectic_dt)
    sim.step(300)
    assert np.all(np.isfinite(sim.positions)) and np.all(np.isfinite(sim.velocities)) and sim.cg_failures == 0
    assert stability.energy_ratio(sim.model, sim.positions, sim.velocities, sim.check) <= 1.0


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
def test_implicit_rejected_step_restores_previous_state(path):
    """The stiff cloth without the definiteness fix runs away at step k > 1: the rejected
    step is undone exactly, to the bits of an independent run of k - 1 steps."""
    scene = load_scene("stiffcloth").with_params(resolution=8)
    sim = simulation(scene.model(), path, integrator="implicit", dt=scene.default_dt("implicit"),
                     definiteness_fix=False)
    with pytest.raises(ms.DivergenceError) as info:
        sim.step(50)
    k = info.value.step
    assert k > 1 and info.value.cause == "runaway" and sim.steps == k - 1
    again = simulation(scene.model(), path, integrator="implicit", dt=sim.dt, definiteness_fix=False)
    again.step(k - 1)
    assert np.array_equal(sim.positions, again.positions) and np.array_equal(sim.velocities, again.velocities)


@FULL
@pytest.mark.parametrize("path", PATHS)
def test_implicit_runaway_reports_the_rejected_states_energy_and_bound(path):
    """``run chain --dt 1``: the error names the rejected state's kinetic energy and the
    bound that state was held to (gravity's work measured at its own positions), as a
    dense numpy solve of Eq. 15 from the kept state gives them; so kinetic > bound."""
    scene = load_scene("chain")
    model = scene.model()
    sim = simulation(model, path, integrator="implicit", dt=1.0, cg_tol=1e-10)
    with pytest.raises(ms.DivergenceError) as info:
        sim.step(10)
    exc = info.value
    assert exc.cause == "runaway" and sim.steps == exc.step - 1
    v = dense_step(model, 1.0, True, sim.positions, sim.velocities)
    x = sim.positions + 1.0 * v
    kinetic = 0.5 * float(np.sum(model.masses * np.sum(v * v, axis=1)))
    base, gx0, factor = sim.check
    bound = factor * (base + max(0.0, float(np.sum(model.masses * (x @ model.gravity))) - gx0))
    assert exc.energy == pytest.approx(kinetic, rel=1e-6) and exc.bound == pytest.approx(bound, rel=1e-6)
    assert exc.energy > exc.bound and exc.kinetic == exc.energy and exc.measured == "kinetic energy"
    assert f"kinetic energy {kinetic:.3g} J above the bound {bound:.3g} J" in str(exc)


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", ["implicit", "backward-euler", "bdf2", "midpoint", "symplectic"])
def test_spring_energy_counts_in_the_implicit_steps_divergence_check(integrator):
    """A particle at rest on a stretched spring, stepped by 1 ns (the step changes
    nothing measurable), against a check whose bound is half the spring's energy: the
    Newton-solved steps, whose check holds kinetic and spring energy to the bound, refuse
    it and keep the start; the others check the kinetic energy alone (an explicit
    runaway swaps energy between the springs and the velocities within a period; the
    linearised step stores spring energy at a large dt that it then damps: `bigstep`'s
    first step at 1 s holds 3e6 J) and accept it."""
    model = ms.Model([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], [[0, 1]], stiffness=1e4, rest_lengths=0.5,
                     masses=1.0, gravity=(0, 0, 0), fixed=[0])
    spring = 0.5 * 1e4 * 0.5 ** 2
    sim = ms.Simulation(model, integrator=integrator, dt=1e-9)
    factor = sim.check[2]
    sim.stepper.dev.check[None] = (0.5 * spring / factor, 0.0, factor)  # the bound: spring / 2
    try:
        if integrator in ("symplectic", "implicit"):
            sim.step(1)
            assert sim.steps == 1
            return
        with pytest.raises(ms.DivergenceError) as info:
            sim.step(1)
        assert info.value.energy == pytest.approx(spring, rel=1e-6) and info.value.bound == pytest.approx(spring / 2)
        assert sim.steps == 0 and np.array_equal(sim.positions, model.positions)
    finally:
        sim.close()


def test_nonfinite_state_is_detected():
    model = ms.Model([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], [[0, 1]], stiffness=1e100, rest_lengths=0.5,
                     masses=1e-100, gravity=(0, 0, 0), fixed=[0])
    sim = ms.Simulation(model, integrator="explicit", dt=1e60)
    with pytest.raises(ms.DivergenceError) as info:
        sim.step(10)
    assert info.value.cause == "non-finite" and info.value.step == 1
    assert np.array_equal(sim.positions, model.positions)


EXTREME = {  # scene -> test-size overrides
    "stiffcloth": {"resolution": 8},
    "heavychain": {"count": 10},
    "zerolength": {"count": 8},
    "crumpled": {"resolution": 8},
    "compressed": {"resolution": 8},
    "bigstep": {"resolution": 8},
    "stiffchain": {"count": 10},
}


LINEARISATION_GAIN = pytest.mark.xfail(strict=True, reason=(
    "known limitation: the seed's linearised implicit step (one Newton step of backward Euler) "
    "stretches the springs of the stiff chain as it swings down, adding up to ~5x (count 10) / "
    "~40x (count 20) the energy gravity supplied in the first 0.3 s, dissipated later; "
    "backward-euler (solved by Newton) passes"))


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", ["implicit", "backward-euler"])
@pytest.mark.parametrize("name", sorted(EXTREME))
def test_extreme_scene_implicit_bounded(name, integrator, request):
    if (name, integrator) == ("stiffchain", "implicit"):
        request.applymarker(LINEARISATION_GAIN)
    scene = load_scene(name).with_params(**EXTREME[name])
    sim = scene.simulation(integrator)
    model = sim.model
    gravity0 = float(np.sum(model.masses * (model.positions @ model.gravity)))
    e0 = model.energy(model.positions, model.velocities)
    for _ in range(10):
        sim.step(20)
        x, v = sim.positions, sim.velocities
        assert np.all(np.isfinite(x)) and np.all(np.isfinite(v))
        work = float(np.sum(model.masses * (x @ model.gravity))) - gravity0
        e = model.energy(x, v)
        assert e["kinetic"] + e["spring"] <= (e0["kinetic"] + e0["spring"] + work) * (1 + 1e-9) + 1e-12
    # Newton from the crushed starts of compressed and crumpled converges linearly (ratio ~0.9: the
    # definiteness fix holds nearly every spring's stiffness), so their first step or two reach
    # newton_max_iter; every other step converges
    assert sim.cg_failures <= (2 if integrator == "backward-euler" and name in ("compressed", "crumpled") else 0)


@pytest.mark.parametrize("name", sorted(set(EXTREME) - {"zerolength"}))
def test_extreme_scene_explicit_above_limit_detected(name):
    scene = load_scene(name).with_params(**EXTREME[name])
    pred = stability.predict(scene.model())
    sim = scene.simulation("explicit", dt=3 * pred.symplectic_dt)
    with pytest.raises(ms.DivergenceError):
        sim.step(2000)
    assert np.all(np.isfinite(sim.positions))


def test_zerolength_predicted_coincident_and_after_it_unfolds():
    """All particles coincident: no spring has a direction, yet each zero-rest-length
    spring has K_ii = -ks I, so the stiffest mode is there at t = 0 (as the dense K says)."""
    scene = load_scene("zerolength").with_params(count=8)
    model = scene.model()
    assert np.all(model.rest_lengths == 0) and np.ptp(model.positions, axis=0).max() == 0
    start = stability.predict(model).omega_max
    assert start > 0 and start == pytest.approx(math.sqrt(dense_lambda_max(model, model.positions)), rel=1e-6)
    settle = scene.simulation("implicit")
    settle.step(50)
    pred = stability.predict(settle.model, settle.positions)
    assert pred.omega_max == pytest.approx(math.sqrt(dense_lambda_max(settle.model, settle.positions)), rel=0.03)


def test_compressed_cloth_definiteness_fix_keeps_cg_converging():
    scene = load_scene("compressed").with_params(resolution=8)
    on = stability.run_case(scene, "implicit", 1 / 60, definiteness_fix=True, duration=0.5)
    off = stability.run_case(scene, "implicit", 1 / 60, definiteness_fix=False, duration=0.5)
    assert on["outcome"] == "stable" and on["cg_failures"] == 0
    assert off["cg_failures"] > 0


def test_cli_run_divergence_exit_3_writes_out(tmp_path, capsys):
    out = tmp_path / "state.npz"
    code = main(["run", "stiffchain", "--set", "count=10", "--integrator", "symplectic", "--dt", "1e-4",
                 "--steps", "500", "--quiet", "--out", str(out)])
    assert code == 3
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "diverged at step" in err and "Traceback" not in err
    data = np.load(out)
    assert 0 < data["steps"] < 500 and np.all(np.isfinite(data["positions"]))


@FULL
def test_cli_stability_writes_table(tmp_path, capsys):
    prefix = tmp_path / "st"
    code = main(["stability", "spring", "--out", str(prefix), "--max-steps", "50"])
    assert code == 0
    text = capsys.readouterr().out
    assert "omega_max                10 rad/s" in text and "symplectic stable below" in text
    import json
    data = json.loads((tmp_path / "st.json").read_text())
    outcomes = {(r["integrator"], round(r["dt_ratio"], 6)): r["outcome"] for r in data["runs"]}
    assert outcomes[("symplectic", 0.9)] == "stable"
    assert outcomes[("symplectic", 3.0)].startswith("diverged")
    assert (tmp_path / "st.csv").read_text().startswith("integrator,definiteness_fix,dt")


def test_cli_stability_rejects_bad_options(capsys):
    assert main(["stability", "spring", "--max-steps", "0"]) == 2
    assert "--max-steps" in capsys.readouterr().err


def test_ladder_has_every_integrator_that_declares_one():
    """The ladder comes from the integrators' rows of ``analysis.hints``: the Newton-solved ones
    are in it (with the fix only), the linearised step with and without the fix, symplectic first."""
    from massspring.analysis.hints import hints
    from massspring.integrators import INTEGRATORS

    names = [row[0] for row in stability.LADDER]
    assert names[0] == "symplectic"
    assert {name for name in INTEGRATORS if hints(name).ladder} == set(names) >= {"backward-euler", "bdf2"}
    assert [row[1] for row in stability.LADDER if row[0] == "implicit"] == [True, False]
    assert [row[1] for row in stability.LADDER if row[0] == "bdf2"] == [True]


def test_every_row_of_the_hints_names_an_integrator_and_what_it_has():
    """``analysis.hints``: each row is a registered integrator's, its ladder is relative to
    a ``Prediction`` field, its swept option is one the integrator takes and has a sweep
    for; an integrator without a row gets no ladder and no sweep, a name that is not an
    integrator is refused."""
    import dataclasses

    from massspring.analysis.hints import HINTS, NO_HINTS, hints
    from massspring.integrators import INTEGRATORS, OPTIONS

    assert set(HINTS) <= set(INTEGRATORS)
    fields = {f.name for f in dataclasses.fields(stability.Prediction)}
    for name, row in HINTS.items():
        if row.ladder is not None:
            assert row.ladder[0] in fields and all(m > 0 for m in row.ladder[1]), (name, row)
        if row.swept is not None:
            assert row.swept in {o.name for o in INTEGRATORS[name].options} and OPTIONS[row.swept].sweep, (name, row)
    assert hints("rk4") is NO_HINTS and "rk4" not in HINTS
    with pytest.raises(ValueError, match="integrator: unknown value 'no-such'"):
        hints("no-such")


def test_rk4_stable_dt_meets_rk4s_region_on_both_axes_and_for_overdamped_modes():
    from massspring.integrators.rk4 import RK4_IMAGINARY_LIMIT, rk4_amplification, rk4_stable_dt

    assert rk4_stable_dt(1.0, 0.0) == pytest.approx(RK4_IMAGINARY_LIMIT, rel=1e-9)  # undamped: the imaginary axis
    assert rk4_stable_dt(0.0, 1.0) == pytest.approx(2.785293563405282, rel=1e-9)  # pure decay: the real axis
    omega, rate = 2601.14, 7163.0  # the cube's stiffest mode: overdamped, limited by its fast real root
    fast = (rate + (rate ** 2 - 4 * omega ** 2) ** 0.5) / 2
    limit = rk4_stable_dt(omega, rate)
    assert limit == pytest.approx(2.785293563405282 / fast, rel=1e-9) and limit < RK4_IMAGINARY_LIMIT / omega
    assert rk4_amplification(-fast * limit * 1.01) > 1 > rk4_amplification(-fast * limit * 0.99)


def test_stability_prints_rk4s_limit(capsys):
    from massspring.integrators.rk4 import rk4_stable_dt

    assert main(["stability", "cube", "--predict-only"]) == 0
    prediction = stability.predict(load_scene("cube").model())
    assert f"rk4 stable below         dt = {rk4_stable_dt(prediction.omega_max, prediction.damping_rate):.4g} s" \
        in capsys.readouterr().out


@FULL
@pytest.mark.parametrize("name", ["cube", "heavychain"])
def test_rk4_default_dt_holds_on_heavily_damped_scenes(name):
    """Before, the RK4 default ignored damping: cube diverged at step 14, heavychain at 3."""
    sim = ms.load_scene(name).simulation("rk4")
    sim.step(300)
    assert np.all(np.isfinite(sim.positions))


@FULL
def test_a_divergence_at_the_estimated_dt_suggests_a_smaller_one(capsys):
    # rk4's estimate at the coincident start, 0.00239 s, sees no damping (it acts along
    # springs, which have no direction yet); the unfolded chain's damping needs less
    assert main(["run", "zerolength", "--integrator", "rk4", "--dt", "0.002", "--quiet"]) == 3
    err = capsys.readouterr().err
    assert "try --dt 0.0005 (a quarter of this run's" in err and "did not hold" in err
