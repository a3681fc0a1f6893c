"""Error-controlled steps (``Simulation(tol=...)``, ``massspring.engine.adaptive``):
the error at the end against the exact solution of a damped spring, landing on given
times and control boundaries, retries instead of divergence, the min_dt stop, and bad
input refused before anything is built."""

from __future__ import annotations

import math

import numpy as np
import pytest

import massspring as ms
from massspring.engine import adaptive
from massspring.engine.adaptive import StepSizeError
from massspring.integrators import INTEGRATORS

KS, KD, MASS, U0 = 100.0, 0.5, 1.0, 0.1  # the spring scene's


def spring_model():
    """One spring of rest length 1 m along x, its first particle pinned, the second pulled
    U0 out: a damped oscillator u'' = -(KS u + KD u') / MASS (no gravity)."""
    return ms.Model(positions=[[0, 0, 0], [1 + U0, 0, 0]], springs=[[0, 1]], masses=[MASS, MASS], stiffness=KS,
                    rest_lengths=[1.0],
                    damping=KD, fixed=[0], gravity=[0, 0, 0])


def exact_u(t):
    """The damped oscillator's displacement (m) at t (s), from u(0) = U0, u'(0) = 0."""
    rate = KD / (2 * MASS)
    omega = math.sqrt(KS / MASS - rate * rate)
    return U0 * math.exp(-rate * t) * (math.cos(omega * t) + rate / omega * math.sin(omega * t))


def end_error(sim, t):
    """The study's error: the moving particle's distance from the exact one over the
    scene's size (1.1 m)."""
    exact = np.array([1 + exact_u(t), 0, 0])
    return float(np.linalg.norm(sim.positions[1] - exact)) / 1.1


@pytest.mark.fast_sample(integrator=["bdf2", "rk4", "symplectic"])
@pytest.mark.parametrize("integrator", list(INTEGRATORS))
def test_the_error_at_the_end_follows_the_tolerance(integrator):
    """Asked for tol 1e-2 and 1e-3 over 1 s, every integrator ends within 0.03x to 30x of
    tol of the exact solution (the issue's band), and the smaller tol gives the smaller
    error; the run ends on 1 s exactly."""
    errors = []
    for tol in (1e-2, 1e-3):
        sim = ms.Simulation(spring_model(), integrator=integrator, dt=1e-3, tol=tol, horizon=1.0)
        sim.advance(1.0)
        assert sim.time == 1.0
        errors.append(end_error(sim, 1.0))
        assert 0.03 * tol <= errors[-1] <= 30 * tol, (tol, errors[-1])
        stats = sim.control_stats()
        assert stats["accepted"] == sim.steps
        assert stats["smallest_dt"] < stats["largest_dt"]  # it did choose its steps
    assert errors[1] < errors[0]


G, DROP, BOUNCE, WIDTH = 9.81, 0.2, 0.5, 0.1  # the bouncing dumbbell's gravity, height, restitution, length
MU = 0.5  # the ground's friction coefficient


def dumbbell_model():
    """A level spring of WIDTH at rest, DROP above a ground plane of restitution BOUNCE:
    it falls and bounces as one particle would (straight down: its friction, MU as the
    sliding test's so that both compile one set of kernels, takes nothing)."""
    ground = ms.Plane(point=[0, 0, 0], normal=[0, 0, 1], restitution=BOUNCE, friction=MU)
    return ms.Model(positions=[[0, 0, DROP], [WIDTH, 0, DROP]], springs=[[0, 1]], masses=[1.0, 1.0], stiffness=100.0,
                    damping=0.5, gravity=[0, 0, -G], colliders=[ground])


def bouncing_height(t):
    """The height (m) at t (s) of a point dropped from DROP that bounces with restitution
    BOUNCE: free flight between impacts, the normal speed times BOUNCE at each."""
    z, v, start = DROP, 0.0, 0.0
    while True:
        flight = (v + math.sqrt(v * v + 2 * G * z)) / G
        if start + flight >= t:
            s = t - start
            return z + v * s - 0.5 * G * s * s
        start, z, v = start + flight, 0.0, BOUNCE * (G * flight - v)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", list(INTEGRATORS))
def test_impacts_are_stepped_across_within_the_tolerance(integrator):
    """Through two impacts (at 0.20 s and 0.40 s) to 0.45 s, every integrator ends within
    0.03x to 30x of tol of the exact bounce, smaller with the smaller tol, without
    stopping: at an impact the estimate of a smooth solution is replaced by the impact's
    own error (``Estimator.error``). Before, BDF2 and RK4 ended 47x and 124x tol 1e-3
    off. Second-order and higher at tol 1e-2 and 1e-3, first-order (about 1 / tol steps:
    free fall is their largest error) at 2e-2 and 5e-3."""
    end = 0.45
    tols = (1e-2, 1e-3) if INTEGRATORS[integrator].traits.order > 1 else (2e-2, 5e-3)
    errors = []
    for tol in tols:
        sim = ms.Simulation(dumbbell_model(), integrator=integrator, dt=1e-3, tol=tol, horizon=end)
        sim.advance(end)
        errors.append(float(np.sqrt(np.mean((sim.positions[:, 2] - bouncing_height(end)) ** 2))) / WIDTH)
        assert 0.03 * tol <= errors[-1] <= 30 * tol, (tol, errors[-1])
        assert np.all(sim.positions[:, 2] >= -1e-12)
    assert errors[1] < errors[0]


@pytest.mark.full
def test_self_collision_impulses_do_not_shrink_the_steps():
    """The sheets scene at 6 x 6, its upper sheet landing on the lower one by 0.4 s, at tol
    3e-2: the self-collision pass moves a close pair apart by a fraction of its gap within
    a step whatever the step's size, so its velocity change grows as 1 / h and is no error
    a shorter step reduces (``Estimator.error``'s ``moved``). Before, each rejection
    shortened the step, each shorter step's impulses put in more energy, and the run
    stopped below min_dt at t = 0.234 s, the divergence check refusing every try. Now it
    runs through with the pass acting and no crossing."""
    from crossings import crossings
    from massspring.model.self_collision import mesh_edges

    scene = ms.load_scene("sheets").with_params(resolution=6)
    sim = scene.simulation(tol=3e-2, horizon=scene.duration)
    sim.advance(0.4)
    assert sim.time == pytest.approx(0.4, abs=1e-12)
    assert sim.self_collision_stats["passes"] > 0 and sim.control_stats()["rejected"]["divergence"] == 0
    model = sim.model
    assert crossings(sim.positions, model.triangles, mesh_edges(model.triangles)) == 0


SLIDE = 2.0  # the sliding dumbbell's initial speed (m/s)


def sliding_model():
    """The dumbbell lying on a plane of friction MU, sliding along its length at SLIDE:
    Coulomb friction decelerates it at MU G until it stops at SLIDE / (MU G) = 0.41 s."""
    ground = ms.Plane(point=[0, 0, 0], normal=[0, 0, 1], restitution=0.0, friction=MU)
    return ms.Model(positions=[[0, 0, 0], [WIDTH, 0, 0]], springs=[[0, 1]], masses=[1.0, 1.0], stiffness=100.0,
                    damping=0.5, gravity=[0, 0, -G], colliders=[ground], velocities=[[SLIDE, 0, 0]] * 2)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", list(INTEGRATORS))
def test_sliding_contact_follows_the_tolerance(integrator):
    """Sliding to 0.3 s at tol 1e-2 and 1e-3, every integrator ends within 0.03x to 30x of tol of the exact
    x = SLIDE t - MU G t^2 / 2 (smaller at the smaller tol): a particle in contact at
    both ends of a step takes the first-order companion's estimate, as the contact
    response is first order. Counting no error for them (a7a7cce), RK4 ended 42x tol
    1e-3 off; keeping its fourth-order estimate of the response's smooth trajectory,
    78x: neither sees the response's first-order error."""
    end = 0.3
    exact = SLIDE * end - 0.5 * MU * G * end * end
    errors = []
    for tol in (1e-2, 1e-3):
        sim = ms.Simulation(sliding_model(), integrator=integrator, dt=1e-3, tol=tol, horizon=end)
        sim.advance(end)
        errors.append(float(np.sqrt(np.mean((sim.positions[:, 0] - [0, WIDTH] - exact) ** 2))) / WIDTH)
        assert 0.03 * tol <= errors[-1] <= 30 * tol, (tol, errors[-1])
    assert errors[1] < errors[0]


def test_without_tol_a_run_is_fixed_dt():
    """No tol: steps of dt, time steps x dt, no control statistics."""
    sim = ms.Simulation(spring_model(), integrator="bdf2", dt=0.01)
    sim.advance(0.5)
    assert sim.steps == 50 and sim.time == 50 * 0.01 and sim.control_stats() is None and sim.tol is None


def test_a_fixed_dt_advance_must_be_whole_steps():
    sim = ms.Simulation(spring_model(), integrator="symplectic", dt=0.01)
    with pytest.raises(ValueError, match="^seconds: "):
        sim.advance(0.015)


@pytest.mark.parametrize("kwargs, message", [
    ({"tol": 0.0}, "^tol: "), ({"tol": -1e-3}, "^tol: "), ({"tol": math.nan}, "^tol: "),
    ({"tol": math.inf}, "^tol: "), ({"tol": "1e-3"}, "^tol: "), ({"tol": 1e-15}, "^tol: .*below 1e-14"),
    ({"min_dt": 1e-6}, "^min_dt: only"), ({"max_dt": 1e-2}, "^max_dt: only"), ({"horizon": 2.0}, "^horizon: only"),
    ({"tol": 1e-3, "min_dt": 0.1, "max_dt": 0.01}, "^min_dt: .*above max_dt"),
    ({"tol": 1e-3, "newton_tol": 1e-4}, "^newton_tol: .*derives it from tol"),
    ({"tol": 1e-3, "cg_tol": 1e-8}, "^cg_tol: .*derives it from tol"),
])
def test_bad_tolerances_are_refused_naming_the_argument(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ms.Simulation(spring_model(), integrator="backward-euler", dt=0.01, **kwargs)


def test_a_diverging_step_is_retried_smaller():
    """Symplectic Euler at a first step 10x its stability limit on a stiff spring (omega
    = 1000 rad/s, limit 2 / omega = 2e-3 s), max_dt given (no bound from the predicted
    limit): a fixed-dt run diverges, the error-controlled one shrinks and ends on time,
    rejections counted."""
    model = ms.Model(positions=[[0, 0, 0], [1.1, 0, 0]], springs=[[0, 1]], masses=[1.0, 1.0], stiffness=1e6, rest_lengths=[1.0],
                     damping=0.0, fixed=[0], gravity=[0, 0, 0])
    with pytest.raises(ms.DivergenceError):
        ms.Simulation(model, integrator="symplectic", dt=2e-2).step(200)
    sim = ms.Simulation(model, integrator="symplectic", dt=2e-2, tol=1e-2, horizon=0.01, max_dt=1.0)
    sim.advance(0.01)
    assert sim.time == 0.01
    stats = sim.control_stats()
    assert sum(stats["rejected"].values()) >= 1 and stats["largest_dt"] < 2e-3
    sizes = sim.step_sizes  # the accepted steps only, in order
    assert len(sizes) == sim.steps and math.isclose(math.fsum(sizes), 0.01, rel_tol=1e-12)
    assert sizes.max() == stats["largest_dt"]
    assert np.all(np.abs(sim.positions[1] - [1.0, 0, 0]) <= 0.1 + 1e-9)  # energy kept: |u| <= U0


def test_below_min_dt_it_stops_naming_time_step_and_cause():
    """A min_dt above what the stiff spring allows: StepSizeError (a DivergenceError, the
    CLI's exit 3) naming the time, the step and the cause; the state kept is the last good one."""
    model = ms.Model(positions=[[0, 0, 0], [1.1, 0, 0]], springs=[[0, 1]], masses=[1.0, 1.0], stiffness=1e6, rest_lengths=[1.0],
                     damping=0.0, fixed=[0], gravity=[0, 0, 0])
    sim = ms.Simulation(model, integrator="explicit", dt=1e-2, tol=1e-3, min_dt=1e-3, horizon=0.1)
    with pytest.raises(StepSizeError, match=r"stopped at t = 0 s .*below min_dt") as info:
        sim.advance(0.1)
    assert isinstance(info.value, ms.DivergenceError)
    assert info.value.time == 0.0 and info.value.dt < 1e-3
    assert sim.steps == 0 and np.array_equal(sim.positions, model.positions)
    assert "by default" not in str(info.value)
    # a default min_dt (1e-9 of the horizon) is said to be one, with how to go lower
    far = ms.Simulation(model, integrator="bdf2", dt=1e-2, tol=1e-3, horizon=1e7)
    with pytest.raises(StepSizeError, match=r"below min_dt 1/100 s \(by default 1e-09 of the horizon, 1e\+07 s: "
                                            r"give min_dt for smaller steps\)"):
        far.advance(1.0)


def test_controls_boundaries_are_landed_on():
    """Keyframed pins: an error-controlled run's steps end on each interval's end, where
    the pin stands exactly at its target (to round-off), as a fixed-dt run's do."""
    model = ms.Model(positions=[[0, 0, 0], [1, 0, 0]], springs=[[0, 1]], masses=[1.0, 1.0], stiffness=100.0,
                     damping=1.0, fixed=[0], gravity=[0, 0, -9.81],
                     controls=ms.Controls(interval=0.3, pin_targets=[[[0, 0, 0.5]], [[0.5, 0, 0.5]]]))
    sim = ms.Simulation(model, integrator="symplectic", dt=0.07, tol=1e-3, horizon=0.9)
    sim.advance(0.3)
    assert sim.time == 0.3
    np.testing.assert_allclose(sim.positions[0], [0, 0, 0.5], atol=1e-12)
    sim.advance(0.3)
    np.testing.assert_allclose(sim.positions[0], [0.5, 0, 0.5], atol=1e-12)
    sim.advance(0.3)
    np.testing.assert_allclose(sim.positions[0], [0.5, 0, 0.5], atol=1e-12)
    np.testing.assert_array_equal(sim.velocities[0], [0, 0, 0])


def test_frames_of_run_for_are_at_their_times():
    """``run(sim, duration=...)`` calls on_frame at each given instant, the run landing there."""
    sim = ms.Simulation(spring_model(), integrator="bdf2", dt=1e-2, tol=1e-3, horizon=0.5)
    seen = []
    ms.run(sim, duration=0.5, frames=[0.0, 0.125, 0.25, 0.5], on_frame=lambda s: seen.append(s.time))
    np.testing.assert_allclose(seen, [0.0, 0.125, 0.25, 0.5], rtol=0, atol=1e-15)
    # run_for's progress points (1/200 of the run) are not landed on: the steps of
    # sim.advance(0.5), which lands once
    again = ms.Simulation(spring_model(), integrator="bdf2", dt=1e-2, tol=1e-3, horizon=0.5)
    ms.run(again, duration=0.5, progress=lambda done, total: None)
    alone = ms.Simulation(spring_model(), integrator="bdf2", dt=1e-2, tol=1e-3, horizon=0.5).advance(0.5)
    assert again.steps == alone.steps < 200 and np.array_equal(again.step_sizes, alone.step_sizes)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic", "rk4"])
def test_calm_steps_held_at_max_dt_go_in_batches(integrator, monkeypatch, capsys):
    """The spring held at max_dt 2e-4 s, where its estimate is a small fraction of its
    bound: most steps go in batches (``engine.adaptive``, "Batches"), the run takes the
    steps the one-by-one run takes (the same count and sizes, the same end state to
    round-off), lands on its end time, ends within 30x tol of the exact solution, and
    ``step(n)`` takes n steps."""
    from massspring.engine import adaptive

    runs = []
    for calm_tries in (adaptive.CALM_TRIES, 10**9):
        with monkeypatch.context() as patch:
            patch.setattr(adaptive, "CALM_TRIES", calm_tries)
            sim = ms.Simulation(spring_model(), integrator=integrator, dt=1e-4, tol=1e-2, horizon=1.0, max_dt=2e-4)
            sim.advance(1.0)
            runs.append(sim)
    batched, single = runs
    stats = batched.control_stats()
    assert stats["batched"] > 0.5 * batched.steps and single.control_stats()["batched"] == 0
    assert batched.steps == single.steps and np.allclose(batched.step_sizes, single.step_sizes, rtol=1e-12)
    assert batched.time == single.time == 1.0
    np.testing.assert_allclose(batched.positions, single.positions, rtol=0, atol=1e-12)
    assert end_error(batched, 1.0) <= 30 * 1e-2
    sim = ms.Simulation(spring_model(), integrator=integrator, dt=1e-4, tol=1e-2, horizon=1.0, max_dt=2e-4)
    sim.step(1000)
    assert sim.steps == 1000 and sim.control_stats()["batched"] > 500
    assert sim.time == pytest.approx(sum(sim.step_sizes), rel=1e-12)
    if integrator == "explicit":  # its estimate on the chain over the scene's 3 s is not calm at tol 1e-2
        return
    from massspring.cli import main  # the summary says so: the chain, held at its stability bound

    assert main(["run", "chain", "--integrator", integrator, "--tol", "1e-2", "--duration", "0.2", "--quiet"]) == 0
    assert " in calm batches)" in capsys.readouterr().out


def test_a_restart_continues_from_its_time():
    """``set_state(..., time=)`` of an error-controlled run: the clock continues from it,
    and the run ends within tolerance of the exact solution (BDF2 with its carried
    previous state and step)."""
    sim = ms.Simulation(spring_model(), integrator="bdf2", dt=1e-3, tol=1e-3, horizon=1.0)
    sim.advance(0.4)
    x, v, t, carried = sim.positions, sim.velocities, sim.time, sim.carried_state()
    assert "h_prev" in carried
    again = ms.Simulation(spring_model(), integrator="bdf2", dt=1e-3, tol=1e-3, horizon=1.0)
    again.set_state(x, v, sim.steps, carried, time=t)
    assert again.time == t
    again.advance(0.6)
    assert abs(again.time - 1.0) < 1e-12
    assert end_error(again, again.time) <= 30 * 1e-3
    with pytest.raises(ValueError, match="^time: only"):
        ms.Simulation(spring_model(), integrator="bdf2", dt=1e-2).set_state(x, v, 10, time=0.1)


@pytest.mark.fast_sample(integrator=["bdf2", "symplectic"])
@pytest.mark.parametrize("integrator", list(INTEGRATORS))
def test_a_restart_with_its_control_state_continues_to_the_bit(integrator):
    """``set_state(..., time=, control=control_state())`` continues an error-controlled
    run to the bit: the same steps, states and controller statistics as the unbroken
    run (in two parts, the first landing where the restart starts); without ``control``
    the estimate starts afresh and the run is another one."""
    def start():
        return ms.Simulation(spring_model(), integrator=integrator, dt=1e-3, tol=1e-3, horizon=1.0)

    whole = start().advance(0.4)
    x, v, t, carried, control = (whole.positions, whole.velocities, whole.time, whole.carried_state(),
                                 whole.control_state())
    assert sorted(control) == sorted(adaptive.CONTROL_KEYS) and control["est_y"].shape[1:] == (1, 6)
    again = start().set_state(x, v, whole.steps, carried, time=t, control=control)
    afresh = start().set_state(x, v, whole.steps, carried, time=t)
    for sim in (whole, again, afresh):
        sim.advance(0.6)
    assert again.steps == whole.steps and again.time == whole.time == 1.0
    assert np.array_equal(again.positions, whole.positions) and np.array_equal(again.velocities, whole.velocities)
    assert again.control_stats() == whole.control_stats()
    assert afresh.control_stats() != whole.control_stats()
    with pytest.raises(ValueError, match=r"^control: only for an error-controlled run"):
        ms.Simulation(spring_model(), integrator=integrator, dt=1e-3).set_state(x, v, control=control)
    with pytest.raises(ValueError, match=r"^control: expected the keys"):
        start().set_state(x, v, time=t, control={"controller": control["controller"]})
    with pytest.raises(ValueError, match=r"^control\['est_y'\]: expected shape"):
        start().set_state(x, v, time=t, control={**control, "est_y": control["est_y"][:, :, :3]})
    with pytest.raises(ValueError, match=r"^control\['controller'\]: expected 15 finite numbers"):
        start().set_state(x, v, time=t, control={**control, "controller": control["controller"][:-1]})


def test_the_cli_restarts_an_error_controlled_run_at_its_time(capsys, tmp_path):
    """`run --restart` of a state saved by an error-controlled run continues from the
    saved time (not steps x dt) to the scene's end, to the bit as the unbroken run (its
    controller saved with it); fixed steps are refused it (exit 2, naming --restart and
    --tol), and a fixed run's state continues under --tol too."""
    from massspring.cli import main

    state, fixed = tmp_path / "half.npz", tmp_path / "fixed.npz"
    assert main(["run", "spring", "--tol", "1e-2", "--duration", "0.5", "--out", str(state), "--quiet"]) == 0
    saved = np.load(state)
    assert float(saved["time"]) == pytest.approx(0.5, abs=1e-12) and int(saved["steps"]) * 0.01 != 0.5
    capsys.readouterr()
    end = tmp_path / "end.npz"
    assert main(["run", "spring", "--tol", "1e-2", "--restart", str(state), "--quiet", "--out", str(end)]) == 0
    out = capsys.readouterr().out
    assert f"from the restart at step {int(saved['steps'])} to step " in out and "(t = 0.5 to 5 s)" in out, out
    unbroken = ms.load_scene("spring").simulation(tol=1e-2).advance(0.5).advance(4.5)  # as the CLI's, to the bit
    assert int(np.load(end)["steps"]) == unbroken.steps and np.array_equal(np.load(end)["positions"],
                                                                            unbroken.positions)
    assert main(["run", "spring", "--restart", str(state), "--steps", "3", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"massspring: error: --restart: {state} is at t = 0.5 s after ") and "give --tol" in err
    assert main(["run", "spring", "--steps", "20", "--out", str(fixed), "--quiet"]) == 0
    assert main(["run", "spring", "--tol", "1e-2", "--restart", str(fixed), "--duration", "0.1", "--quiet"]) == 0
    assert "(t = 0.2 to 0.3 s)" in capsys.readouterr().out


def test_the_cli_runs_a_scene_to_a_tolerance(capsys):
    """`massspring run spring --tol 1e-3`: exit 0, to the scene's duration, the summary
    naming the tolerance and the steps' range."""
    from massspring.cli import main

    assert main(["run", "spring", "--integrator", "bdf2", "--tol", "1e-3", "--duration", "0.5", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "tol 0.001 (dt " in out and "(0.5 s simulated)" in out and "from --tol" in out


def test_a_scene_with_a_tol_runs_to_it_unless_fixed_steps_are_asked_for(capsys):
    """`zerolength` ships [tol] backward-euler = 0.1: its default run is error-controlled
    to the scene's duration; --steps, --dt and --newton-tol run fixed steps; `info`
    names the tol; another integrator keeps the scene's fixed dt."""
    from massspring.cli import main

    assert main(["run", "zerolength", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "backward-euler, tol 0.1 (dt " in out and "(2 s simulated)" in out
    for fixed in (["--steps", "3"], ["--dt", "0.02", "--duration", "0.06"], ["--newton-tol", "1e-4", "--steps", "3"]):
        assert main(["run", "zerolength", "--quiet", *fixed]) == 0, fixed
        out = capsys.readouterr().out
        assert "tol" not in out.split("integrator", 1)[1].split("\n", 1)[0] and "steps       3 (" in out, fixed
    assert main(["info", "zerolength"]) == 0
    out = capsys.readouterr().out
    assert "backward-euler, tol 0.1 (error-controlled steps, the first dt = 1/100 s)" in out
    assert "tol defaults backward-euler 0.1 (" in out
    assert main(["info", "zerolength", "--integrator", "bdf2"]) == 0
    assert "bdf2, dt = 1/100 s" in capsys.readouterr().out


def test_a_run_held_to_tiny_steps_is_named_before_it_starts(capsys, monkeypatch):
    """Explicit Euler on the undamped stiff chain is held below 2.3e-11 s (half its
    predicted stability limit; the default min_dt, 1e-9 x the horizon, above it): `run`
    says so, with the steps ahead, before the run (here, with the warning's threshold
    lowered, on symplectic Euler's 125 steps of at most 8.1e-6 s over 1 ms)."""
    import argparse

    from massspring.cli import main, run

    scene = ms.load_scene("stiffchain")
    # the Lanczos prediction's last digits depend on the CPU: the text is checked against it
    explicit, symplectic = (INTEGRATORS[name].suggest_dt(scene.prediction()) for name in ("explicit", "symplectic"))
    assert 2.2e-11 < explicit < 2.4e-11 and 8.0e-6 < symplectic < 8.3e-6
    sim = scene.simulation("explicit", tol=1e-3, horizon=0.2)
    note = run.bound_note(argparse.Namespace(max_dt=None), sim, 0.2)
    assert note.startswith(f"explicit's steps are held at most 2e-10 s (--min-dt, above the {explicit:.3g} s of half "
                           "its stability limit predicted here): at least 1e+09 steps for the 0.2 s"), note
    given = scene.simulation("explicit", tol=1e-3, horizon=0.2, max_dt=1e-9)
    assert "at most 1e-09 s (--max-dt): at least 2e+08 steps" in run.bound_note(argparse.Namespace(max_dt=1e-9),
                                                                                 given, 0.2)
    for quiet in (scene.simulation("backward-euler", tol=1e-3, horizon=0.2), scene.simulation("explicit")):
        assert run.bound_note(argparse.Namespace(max_dt=None), quiet, 0.2) is None
    for s in (sim, given):
        s.close()
    monkeypatch.setattr(run, "LONG_RUN_STEPS", 100)
    assert main(["run", "stiffchain", "--integrator", "symplectic", "--tol", "1e-3", "--duration", "1e-3"]) == 0
    assert (f"massspring: run stiffchain: symplectic's steps are held at most {symplectic:.3g} s (half its stability "
            f"limit predicted here): at least {1e-3 / symplectic:.3g} steps for the 0.001 s") in capsys.readouterr().err


def test_an_obj_mesh_runs_as_a_scene_to_a_tolerance(capsys, tmp_path):
    """An OBJ file where a scene goes: the mesh scene with the defaults (implicit, 2 s, no
    dt table); `massspring run my.obj --tol 1e-2` runs it with the steps it picks."""
    from pathlib import Path

    from massspring.cli import main

    mesh = tmp_path / "my.obj"
    mesh.write_bytes((Path(__file__).resolve().parents[1] / "examples" / "cloth.obj").read_bytes())
    scene = ms.load_scene(str(mesh))
    assert (scene.integrator, scene.duration, scene.dt, scene.model().n_particles) == ("implicit", 2.0, {}, 144)
    assert main(["run", str(mesh), "--tol", "1e-2", "--duration", "0.05", "--quiet",
                 "--set", "pin_box=[[-0.01,0.99,-0.01],[1.01,1.01,0.01]]"]) == 0
    out = capsys.readouterr().out
    assert "implicit, tol 0.01 (dt " in out and "(0.05 s simulated)" in out


@pytest.mark.parametrize("args, flag", [
    (["--tol", "0"], "--tol"), (["--tol", "1e-20"], "--tol"), (["--min-dt", "1e-6"], "--min-dt"),
    (["--max-dt", "1e-2"], "--max-dt"), (["--tol", "1e-3", "--newton-tol", "1e-4"], "--newton-tol"),
    (["--tol", "1e-3", "--steps", "10"], "--steps"),
    (["--tol", "1e-3", "--export", "frames-dir", "--every", "2"], "--every"),
])
def test_the_cli_refuses_bad_tolerances_in_one_line(capsys, tmp_path, monkeypatch, args, flag):
    """Exit 2, one line naming the flag, nothing run or written."""
    from conftest import one_line_error
    from massspring.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["run", "spring", "--integrator", "bdf2", "--quiet", *args]) == 2
    one_line_error(capsys, flag)
    assert not (tmp_path / "frames-dir").exists()


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ["rk4", "symplectic"])
def test_explicit_steps_stay_below_the_predicted_stability_limit(integrator):
    """A free-falling rope (rope-drop with 10 particles, before it lands at 0.32 s) is
    integrated almost exactly, so the estimate let RK4's steps grow past its stability
    limit until the rope vibrated and the run stopped at 0.11 s with StepSizeError (the
    divergence check refusing every step; symplectic Euler's steps reached 0.008 s with
    180 rejections). Without max_dt, an
    explicit integrator's steps stay at most its ``suggest_dt`` of the model: the run
    ends with no step refused by the divergence check; with max_dt given, that bound
    is the user's."""
    from massspring.analysis.stability import predict

    scene = ms.load_scene("rope-drop").with_params(count=10)
    limit = INTEGRATORS[integrator].suggest_dt(predict(scene.model()))
    sim = scene.simulation(integrator, tol=1e-2, horizon=0.3)
    sim.advance(0.3)
    stats = sim.control_stats()
    assert sim.time == 0.3 and stats["rejected"]["divergence"] == 0 and stats["largest_dt"] <= limit
    assert np.abs(sim.velocities).max() < 4.0  # the free fall's 2.9 m/s, no vibration
    given = scene.simulation(integrator, tol=1e-2, horizon=0.3, max_dt=4 * limit, dt=4 * limit)
    given.step(1)
    assert given.control_stats()["largest_dt"] > limit


@pytest.mark.full
def test_the_linearised_steps_stay_within_a_frame():
    """The linearised step's estimate does not see the error of linearising the step,
    which grows with it: on the 8 x 8 flag at tol 0.1 its steps grew to 0.33 s, and the
    state that step ended in took 27,360 steps (down to 2.6e-6 s) to get through 3 s.
    Without max_dt, its steps stay at most its ``suggest_dt``, a frame: the run ends
    with none refused and no more steps than a fixed dt of a frame needs (180); with
    max_dt given, that bound is the user's."""
    scene = ms.load_scene("flag").with_params(resolution=8)
    frame = INTEGRATORS["implicit"].suggest_dt(None)
    sim = scene.simulation("implicit", tol=0.1, horizon=3.0)
    sim.advance(3.0)
    stats = sim.control_stats()
    assert sim.settings.max_dt == frame and sim.time == 3.0 and stats["largest_dt"] <= frame * (1 + 1e-9)
    assert sum(stats["rejected"].values()) <= 10 and stats["accepted"] <= 3.0 / frame * 1.1
    assert scene.simulation("implicit", tol=0.1, horizon=3.0, max_dt=0.5).settings.max_dt == 0.5


def test_a_step_that_keeps_diverging_stops_naming_divergence():
    """Symplectic Euler from a first step of 0.1 s on a spring of omega = 1e6 rad/s: 0.1,
    0.025 and 0.00625 s each multiply its energy by about (h omega)^2 > 1e7 in one step
    (the divergence check refuses them), and the next try, 0.0016 s, is below min_dt
    2e-3 s: the stop names divergence as the cause."""
    model = ms.Model(positions=[[0, 0, 0], [1.1, 0, 0]], springs=[[0, 1]], masses=[1.0, 1.0], stiffness=1e12,
                     rest_lengths=[1.0], damping=0.0, fixed=[0], gravity=[0, 0, 0])
    sim = ms.Simulation(model, integrator="symplectic", dt=1e-1, tol=1e-3, min_dt=2e-3, max_dt=1.0, horizon=1.0)
    with pytest.raises(StepSizeError, match="the state diverged"):
        sim.advance(1.0)
    assert sim.control_stats()["rejected"]["divergence"] == 3


def test_the_cli_exits_3_below_min_dt(capsys):
    """A min_dt the run cannot keep to: exit 3, the message naming the time and min_dt."""
    from massspring.cli import main

    code = main(["run", "stiffchain", "--integrator", "explicit", "--tol", "1e-3", "--min-dt", "1e-3",
                 "--duration", "0.1", "--quiet"])
    assert code == 3
    err = capsys.readouterr().err
    assert "below min_dt 1 ms" in err or "below min_dt" in err


def test_a_run_whose_short_steps_diverged_is_told_to_bound_its_steps():
    """Where the last tries diverged however short (``flag`` at tol 0.1 after a 0.52 s
    linearised step: docs/solvers.md), a smaller min_dt or a looser tol cannot help;
    the command line's advice names --max-dt first. Where the estimate refused them, not."""
    from massspring.cli.run import adaptive_hint

    diverged = StepSizeError(188, 2.05, 8e-10, 3e-9, "the state diverged", "implicit")
    refused = StepSizeError(76, 0.17, 8e-10, 3e-9, "error estimate 52.1 x its bound", "implicit")
    assert adaptive_hint(diverged).startswith("give a --max-dt below the largest step")
    assert "--max-dt" not in adaptive_hint(refused) and "--min-dt" in adaptive_hint(refused)
