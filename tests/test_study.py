"""The work-precision study: errors against independent exact solutions, the RK4
reference and its self-check, divergence handling, and the CSV/JSON outputs."""

import csv
import dataclasses
import json

import numpy as np
import pytest

from conftest import FULL
import massspring as ms
from massspring.analysis import fits, reference, report, study
from massspring.cli import main

REQUIRED = ("integrator", "dt", "cg_tol", "error", "error_over_time", "energy_error", "wall_s",
            "steps", "cg_iterations", "diverged")

# The spring scene: particle 1 (m = 1 kg) on a spring ks = 100 N/m, kd = 0.5 N s/m, l0 = 1 m,
# pulled to x = 1.1 m, particle 0 fixed at the origin; the scene's size is 1.1 m.
KS, KD, M, L0, U0, SIZE = 100.0, 0.5, 1.0, 1.0, 0.1, 1.1
END = 0.8
SPRING_LADDERS = {"explicit": [1e-3, 5e-4, 2.5e-4], "symplectic": [1e-3, 5e-4, 2.5e-4],
                  "implicit": [8e-3, 4e-3, 2e-3]}


def exact_state(t):
    """(u, w) of m u'' = -ks u - kd u' by the eigen-decomposition of the 2x2 system."""
    a = np.array([[0.0, 1.0], [-KS / M, -KD / M]])
    lam, vec = np.linalg.eig(a)
    z = vec @ (np.exp(lam * t) * np.linalg.solve(vec, [U0, 0.0]))
    return z.real


def discrete_state(integrator, dt, steps):
    """(u, w) after ``steps`` steps of each integrator's exact 1D map, as a 2x2 matrix power."""
    k, c = dt * KS / M, dt * KD / M
    if integrator == "explicit":      # u' = u + dt w, w' = w + dt (-ks u - kd w) / m
        step = [[1.0, dt], [-k, 1.0 - c]]
    elif integrator == "symplectic":  # w' first, then u' = u + dt w'
        step = [[1.0 - dt * k, dt * (1.0 - c)], [-k, 1.0 - c]]
    else:                             # (m + dt kd + dt^2 ks) w' = m w - dt ks u, u' = u + dt w'
        d = 1.0 + c + dt * k
        step = [[1.0 - dt * k / d, dt / d], [-k / d, 1.0 / d]]
    return np.linalg.matrix_power(np.array(step), steps) @ [U0, 0.0]


@pytest.fixture(scope="module")
def spring_study():
    scene = ms.load_scene("spring")
    return study.run_study(scene, duration=END, ladders=SPRING_LADDERS, cg_tols=[1e-10], repeats=1,
                           use_cache=False)


def test_spring_errors_match_the_exact_solution(spring_study):
    """Every reported error equals |u_discrete - u_exact| / size, both computed here."""
    s = spring_study
    assert s.reference.method == "exact"
    assert s.size == pytest.approx(SIZE)
    assert len(s.runs) == 9
    u_ref, w_ref = exact_state(END)
    energy_scale = 0.5 * KS * U0 ** 2  # largest kinetic + spring energy: the initial one
    for run in s.runs:
        steps = int(round(END / run.dt))
        assert run.steps == steps and not run.diverged and run.status == "ok"
        u, w = discrete_state(run.integrator, run.dt, steps)
        assert run.error == pytest.approx(abs(u - u_ref) / SIZE, rel=1e-6)
        energy = 0.5 * M * w ** 2 + 0.5 * KS * u ** 2
        energy_ref = 0.5 * M * w_ref ** 2 + 0.5 * KS * u_ref ** 2
        assert run.energy_error == pytest.approx(abs(energy - energy_ref) / energy_scale, rel=1e-6)
        # over time: RMS over the save instants of the same quantity
        per_instant = []
        for t in s.times:
            k = int(round(t / run.dt))
            per_instant.append(discrete_state(run.integrator, run.dt, k)[0] - exact_state(t)[0])
        assert run.error_over_time == pytest.approx(np.sqrt(np.mean(np.square(per_instant))) / SIZE, rel=1e-6)
        assert run.wall_s > 0 and run.timed_runs == 1
        assert (run.cg_iterations > 0) == (run.integrator == "implicit")


def test_spring_orders_are_about_one(spring_study):
    orders = fits.integrator_orders(spring_study.orders)
    assert set(orders) == {"explicit", "symplectic", "implicit"}
    for name, order in orders.items():
        assert 0.8 <= order <= 1.2, (name, order)


def test_exact_spring_solution_all_regimes():
    """The closed form against the eigen-decomposition for under-, over- and (near) critical damping."""
    t = np.linspace(0, 2, 7)
    for kd in (0.5, 25.0, 20.0 + 1e-6):
        lam, vec = np.linalg.eig(np.array([[0.0, 1.0], [-KS / M, -kd / M]]))
        want = np.array([(vec @ (np.exp(lam * ti) * np.linalg.solve(vec, [U0, 0.3]))).real for ti in t])
        u, w = reference.damped_oscillator(U0, 0.3, M, KS, kd, 0.0, t)
        np.testing.assert_allclose(u, want[:, 0], atol=1e-9)
        np.testing.assert_allclose(w, want[:, 1], atol=1e-8)
    u, w = reference.damped_oscillator(U0, 0.3, M, KS, 20.0, 0.0, t)  # exactly critical
    np.testing.assert_allclose(u, (U0 + (0.3 + 10 * U0) * t) * np.exp(-10 * t), atol=1e-15)


# ---- RK4 reference on a chain ------------------------------------------------


def tiny_chain(count=4, damping=0.5):
    return ms.load_scene("chain").with_params(count=count, damping=damping)


def numpy_rk4(model, dt, steps):
    """RK4 of Eq. 4 with dense numpy forces: an independent implementation."""
    ends, ks, kd, l0 = model.springs, model.stiffness, model.damping, model.rest_lengths
    moving = model.free_mask()[:, None]

    def accel(x, v):
        d = x[ends[:, 1]] - x[ends[:, 0]]
        length = np.linalg.norm(d, axis=1)
        n = d / length[:, None]
        rel = np.sum((v[ends[:, 1]] - v[ends[:, 0]]) * n, axis=1)
        f_spring = (ks * (length - l0) + kd * rel)[:, None] * n  # on end 0
        f = np.zeros_like(x)
        np.add.at(f, ends[:, 0], f_spring)
        np.add.at(f, ends[:, 1], -f_spring)
        return moving * (f / model.masses[:, None] + model.gravity)

    x, v = model.positions.copy(), model.velocities.copy()
    for _ in range(steps):
        k1x, k1v = v, accel(x, v)
        k2x, k2v = v + dt / 2 * k1v, accel(x + dt / 2 * k1x, v + dt / 2 * k1v)
        k3x, k3v = v + dt / 2 * k2v, accel(x + dt / 2 * k2x, v + dt / 2 * k2v)
        k4x, k4v = v + dt * k3v, accel(x + dt * k3x, v + dt * k3v)
        x = x + dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v = v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return x, v


@FULL
def test_rk4_kernel_matches_numpy_rk4_and_is_cached(tmp_path):
    model = tiny_chain().model()
    dt, times = 1e-4, np.array([0.01, 0.02])
    traj = reference.rk4(model, times, dt, cache=tmp_path)
    x, v = numpy_rk4(model, dt, 200)
    np.testing.assert_allclose(traj.positions[-1], x, atol=1e-12)
    np.testing.assert_allclose(traj.velocities[-1], v, atol=1e-10)
    files = list(tmp_path.glob("rk4-*.npz"))
    assert len(files) == 1
    again = reference.rk4(model, times, dt, cache=tmp_path)  # read back from the cache
    np.testing.assert_array_equal(again.positions, traj.positions)
    other = reference.rk4(model, times, dt / 2, cache=tmp_path)  # another dt is another entry
    assert len(list(tmp_path.glob("rk4-*.npz"))) == 2
    assert np.abs(other.positions - traj.positions).max() < 1e-10
    with pytest.raises(ValueError, match="times"):
        reference.rk4(model, [0.01, 0.015], 4e-3, use_cache=False)


CHAIN_LADDERS = {"explicit": [2e-5, 1e-5], "symplectic": [1e-4, 5e-5], "implicit": [2e-3, 1e-3]}


@pytest.fixture(scope="module")
def chain_study(tmp_path_factory):
    return study.run_study(tiny_chain(), duration=0.04, ladders=CHAIN_LADDERS, cg_tols=[1e-8], repeats=1,
                           cache=tmp_path_factory.mktemp("cache"))


@FULL
def test_chain_reference_agrees_with_half_its_dt(chain_study, tmp_path):
    check = chain_study.reference
    assert check.method == "rk4" and check.passed
    assert check.smallest == min(min(r.error, r.error_over_time) for r in chain_study.runs)
    # the check, redone here: RK4 at the reported dt against RK4 at twice it
    model = tiny_chain().model()
    fine = reference.rk4(model, chain_study.times, check.dt, use_cache=False)
    coarse = reference.rk4(model, chain_study.times, 2 * check.dt, use_cache=False)
    moving = model.free_mask()
    diff = (fine.positions - coarse.positions)[:, moving]
    assert np.sqrt(np.mean(np.sum(diff ** 2, axis=-1))) / chain_study.size < 1e-3 * check.smallest
    assert "PASS" in report.report(chain_study)


@pytest.mark.full
@pytest.mark.parametrize("integrator", ["explicit", "rk4"])
def test_a_timed_run_compiles_nothing_after_its_warm_up(integrator, monkeypatch):
    """The study times stepping, not compiling: after ``_warm_up`` the steps of the measured
    run and of its repeats compile no kernel, at odd and even step counts (before, a run
    that stepped an odd count compiled the many-step kernel again for its states' other
    order, and the first rung of a ladder was timed with that compile in it). Readbacks
    between the timed calls may compile (they are not timed)."""
    from taichi.lang import kernel_impl

    model = ms.load_scene("spring").model()
    dt = 1e-3
    compiled, stepping = [], []
    materialize, step = kernel_impl.Kernel.materialize, ms.Simulation.step

    def counting(self, key=None, args=None, arg_features=None):
        if stepping and (key is None or key not in self.compiled_kernels):
            compiled.append(self.func.__name__)
        return materialize(self, key, args, arg_features)

    def timed_step(self, n=1):
        stepping.append(n)
        try:
            return step(self, n)
        finally:
            stepping.pop()

    study._warm_up(model, integrator, dt, None)
    monkeypatch.setattr(kernel_impl.Kernel, "materialize", counting)
    monkeypatch.setattr(ms.Simulation, "step", timed_step)
    times = np.array([3, 8, 15]) * dt
    run = study._measure(model, integrator, dt, {}, None, times, 1.0)
    walls = [study._time(model, integrator, dt, {}, None, times) for _ in range(2)]
    assert not run.diverged and run.steps == 15 and run.timed_runs == 1 and min(walls) > 0
    assert compiled == []


def test_repeats_are_timed_in_rounds_over_every_run(monkeypatch):
    """Issue 60: a run's repeats came one after the other, so a shared machine's load that
    drifted over a study fell on some runs and not others. Now the measured runs come
    first, then each round times every run once more in the study's order: with
    ``repeats`` 3, runs A B C D are timed A B C D, A B C D, A B C D; each run's time is
    the least of its three."""
    order = []
    fake = np.linspace(8e-9, 1e-9, 8)  # below any measured run's time: the least is the last round's
    walls = iter(fake)

    def timed(model, integrator, dt, tol, preconditioner, times):
        order.append((integrator, dt))
        return float(next(walls))

    monkeypatch.setattr(study, "_time", timed)
    ladders = {"symplectic": [1e-3, 5e-4], "explicit": [1e-3, 5e-4]}
    result = study.run_study(ms.load_scene("spring"), integrators=["symplectic", "explicit"], duration=0.02,
                             ladders=ladders, repeats=3, time_budget=60.0, use_cache=False)
    runs = [(r.integrator, r.dt) for r in result.runs]
    assert len(runs) == 4 and order == runs + runs
    assert [r.timed_runs for r in result.runs] == [3, 3, 3, 3]
    assert [r.wall_s for r in result.runs] == list(fake[4:])


@FULL
def test_reference_check_failure_is_reported(tmp_path):
    """A ratio no RK4 can meet: the check fails after its halvings, and says so."""
    s = study.run_study(tiny_chain(), duration=0.01, integrators=["symplectic"],
                        ladders={"symplectic": [1e-4, 5e-5]}, repeats=1, cache=tmp_path,
                        reference_ratio=1e-20)
    check = s.reference
    assert check.method == "rk4" and not check.passed
    assert check.change >= 1e-20 * check.smallest
    assert check.dt == pytest.approx(s.times[0] / round(s.times[0] / 2e-5) / 2 ** (study.REFERENCE_HALVINGS + 1))
    assert "FAIL" in report.report(s) and json.loads(json.dumps(s.summary()))["reference"]["passed"] is False


# ---- divergence -------------------------------------------------------------


@pytest.mark.full
def test_diverged_runs_are_marked_and_not_fitted(tmp_path):
    """Explicit Euler far above its stable dt on the chain blows up; it must be marked,
    carry no error or time, and leave the fitted slope to the good runs."""
    s = study.run_study(tiny_chain(damping=0.0), duration=0.12,
                        integrators=["explicit"], ladders={"explicit": [8e-3, 2e-5, 1e-5, 5e-6]},
                        repeats=1, cache=tmp_path)
    bad, *good = s.runs
    assert bad.dt == 8e-3 and bad.diverged and bad.status.startswith("diverged")
    assert bad.error is None and bad.error_over_time is None and bad.wall_s is None
    assert not any(r.diverged for r in good)
    entry = s.orders["explicit"]
    assert entry["points"] == 3
    want = np.polyfit(np.log([r.dt for r in good]), np.log([r.error for r in good]), 1)[0]
    assert entry["order"] == pytest.approx(want)
    assert 0.8 <= entry["order"] <= 1.2


def test_fit_ignores_diverged_runs_even_with_an_error():
    runs = [study.Run("explicit", dt, None, error=3.0 * dt, wall_s=dt) for dt in (1e-3, 5e-4, 2.5e-4)]
    runs.append(study.Run("explicit", 2e-3, None, error=1e9, diverged=True))
    entry = fits.fit_orders(runs)["explicit"]
    assert entry["points"] == 3 and entry["order"] == pytest.approx(1.0)
    assert entry["order_finest"] == pytest.approx(1.0)
    assert fits.cheapest(runs + [study.Run("explicit", 4e-3, None, error=1e-9, wall_s=1e-9, diverged=True)],
                          1e-2)["dt"] in (1e-3, 5e-4, 2.5e-4)


def test_runs_within_the_timing_noise_tie():
    """Issue 60: ``study cloth --integrators explicit,symplectic --rungs 2`` run twice
    flipped its "error <= 0.001" verdict (explicit 0.108 s, then symplectic 0.093 s): two
    runs within ``fits.TIE`` (30%) of each other's time are a tie, named in the verdict,
    whichever was the faster; a run 50% slower is not, nor one of the same line."""
    explicit = study.Run("explicit", 1e-4, None, error=5e-4, wall_s=0.108)
    symplectic = study.Run("symplectic", 2e-4, None, error=8e-4, wall_s=0.093)
    rk4 = study.Run("rk4", 1e-3, None, error=1e-6, wall_s=0.14)  # 51% slower than symplectic's
    finer = study.Run("symplectic", 1e-4, None, error=2e-4, wall_s=0.1)  # its own line: not a tie
    for order in ([explicit, symplectic, rk4, finer], [finer, rk4, symplectic, explicit]):
        best = fits.cheapest(order, 1e-3)
        assert best["integrator"] == "symplectic" and best["dt"] == 2e-4
        assert [(t["integrator"], t["dt"]) for t in best["ties"]] == [("explicit", 1e-4)]
    slower = dataclasses.replace(explicit, wall_s=0.093 * 1.31)
    assert fits.cheapest([slower, symplectic], 1e-3)["ties"] == []
    orders = fits.fit_orders([explicit, symplectic])
    text = report.report(study.Study("cloth", {}, 0.1, np.array([0.1]), 1.0, [explicit, symplectic],
                                     study.ReferenceCheck("exact"), orders))
    assert "cheapest symplectic dt 0.0002 s" in text and "a tie: explicit dt 0.0001 s" in text


# ---- outputs ----------------------------------------------------------------


@FULL
def test_csv_and_json_have_one_row_per_run(chain_study, tmp_path):
    written = report.write_outputs(chain_study, tmp_path / "out")
    assert {p.name for p in written} == {"runs.csv", "runs.json", "summary.json"}
    with open(tmp_path / "out" / "runs.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    records = json.loads((tmp_path / "out" / "runs.json").read_text())
    assert len(rows) == len(records) == len(chain_study.runs) == 6
    for row, record, run in zip(rows, records, chain_study.runs):
        assert set(REQUIRED) <= set(row) and set(REQUIRED) <= set(record)
        assert record["integrator"] == row["integrator"] == run.integrator
        assert record["dt"] == float(row["dt"]) == run.dt
        assert record["error"] == pytest.approx(float(row["error"]), rel=1e-12)
        assert record["diverged"] is False and row["diverged"] == "False"
        assert (record["cg_tol"] is None) == (run.integrator != "implicit") == (row["cg_tol"] == "")


def test_error_controlled_lines_follow_their_tolerance():
    """``tols``: a run per tolerance and integrator, its error against the exact spring
    (computed here from its end state) within 0.03x..30x of tol and smaller at the smaller
    tol; a line of their own, no order fitted to it, and among the cheapest runs."""
    scene = ms.load_scene("spring")
    s = study.run_study(scene, integrators=["bdf2", "implicit"], duration=END, cg_tols=[1e-10], newton_tols=[1e-8],
                        ladders={"bdf2": [8e-3, 4e-3], "implicit": [8e-3, 4e-3]}, tols=[1e-2, 1e-3], repeats=1,
                        use_cache=False)
    adaptive = [r for r in s.runs if r.tol is not None]
    assert [(r.integrator, r.tol) for r in adaptive] == [("bdf2", 1e-2), ("bdf2", 1e-3), ("implicit", 1e-2),
                                                         ("implicit", 1e-3)]
    u_ref = exact_state(END)[0]
    for run in adaptive:
        assert run.line.endswith("error-controlled") and not run.diverged and run.steps > 0
        error = abs(run.positions[-1][1, 0] - (L0 + u_ref)) / SIZE
        assert run.error == pytest.approx(error, rel=1e-9)
        assert 0.03 * run.tol <= run.error <= 30 * run.tol, (run.integrator, run.tol, run.error)
    for name in ("bdf2", "implicit"):
        loose, tight = (r for r in adaptive if r.integrator == name)
        assert tight.error < loose.error and tight.steps > loose.steps
    assert not any(line.endswith("error-controlled") for line in s.orders)
    assert "chosen" in report.report(s)  # the table's dt column of an error-controlled run


def test_cli_study(tmp_path, capsys):
    out = tmp_path / "study"
    code = main(["study", "spring", "--out", str(out), "--duration", "0.2", "--rungs", "2",
                 "--cg-tols", "1e-6", "--repeats", "1", "--cache-dir", str(tmp_path / "cache")])
    text = capsys.readouterr().out
    assert code == 0
    assert "measured order" in text and "reference: exact solution" in text
    assert len(json.loads((out / "runs.json").read_text())) == 6
    adaptive = tmp_path / "adaptive"
    assert main(["study", "spring", "--out", str(adaptive), "--duration", "0.2", "--rungs", "2",
                 "--integrators", "bdf2", "--newton-tols", "1e-6", "--tol", "1e-2", "--repeats", "1",
                 "--cache-dir", str(tmp_path / "cache")]) == 0
    assert "tol 1e-02" in capsys.readouterr().err
    assert [row["tol"] for row in json.loads((adaptive / "runs.json").read_text())] == [None, None, 0.01]
    import matplotlib  # noqa: F401  (in the [test] extra: a missing one fails here, not a skip)
    assert (out / "work_precision.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("args, key", [(["--rungs", "0"], "--rungs: expected an integer"),
                                       (["--cg-tols", "2"], "--cg-tols: must be < 1"),
                                       (["--integrators", "rk2"], "--integrators: unknown value 'rk2'"),
                                       (["--duration", "-1"], "--duration: must be a finite number > 0"),
                                       (["--repeats", "0"], "--repeats: expected an integer"),
                                       (["--preconditioners", "amg"], "--preconditioners: unknown value 'amg'"),
                                       (["--cg-tols", "x"], "--cg-tols: expected a number"),
                                       (["--tol", "0"], "--tol: "), (["--tol", "1e-3,x"], "--tol: expected a number")])
def test_cli_study_bad_input(args, key, tmp_path, capsys):
    assert main(["study", "spring", "--out", str(tmp_path / "o"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and key in err
    assert not (tmp_path / "o").exists()


@FULL
def test_implicit_runs_get_a_line_per_preconditioner(tmp_path):
    """Two preconditioners solving to 1e-8 give two lines of the same errors."""
    result = study.run_study(tiny_chain(), integrators=["implicit"], duration=0.04,
                             ladders={"implicit": [2e-3, 1e-3]}, cg_tols=[1e-8],
                             preconditioners=["block-jacobi", "multigrid"], repeats=1, cache=tmp_path)
    assert set(result.orders) == {"implicit (block-jacobi) cg_tol=1e-08", "implicit (multigrid) cg_tol=1e-08"}
    by = {(r.preconditioner, r.dt): r for r in result.runs}
    for dt in (2e-3, 1e-3):
        bj, mg = by["block-jacobi", dt], by["multigrid", dt]
        assert abs(bj.error - mg.error) <= 1e-4 * bj.error
    assert "(multigrid)" in report.report(result)
    with pytest.raises(ValueError, match="preconditioners"):
        study.run_study(tiny_chain(), preconditioners=["amg"])


@pytest.mark.full
def test_rk4_cache_tells_air_pins_and_colliders_apart(tmp_path):
    """A cached reference is only reused for the same physics: drag, moving pins or a
    collider make another entry (and a different trajectory); the exact spring solution
    does not apply to them."""
    import massspring as ms

    base = tiny_chain().model()
    dt, times = 1e-4, np.array([0.01])
    args = dict(masses=base.masses, stiffness=base.stiffness, damping=base.damping, gravity=base.gravity,
                fixed=base.fixed, rest_lengths=base.rest_lengths)
    variants = [base, ms.Model(base.positions, base.springs, drag=0.05, **args),
                ms.Model(base.positions, base.springs, pin_velocity=[[0.0, 0.0, 0.5]], **args),
                ms.Model(base.positions, base.springs, colliders=[ms.Plane((0, 0, -1e-4), (0, 0, 1))], **args)]
    finals = [reference.rk4(model, times, dt, cache=tmp_path).positions[-1] for model in variants]
    assert len(list(tmp_path.glob("rk4-*.npz"))) == len(variants)
    for other in finals[1:]:
        assert np.abs(other - finals[0]).max() > 1e-6
    spring = ms.load_scene("spring").model()
    assert reference.exact_spring(spring, [0.1]) is not None
    dragged = ms.Model(spring.positions, spring.springs, masses=spring.masses, stiffness=spring.stiffness,
                       damping=spring.damping, rest_lengths=spring.rest_lengths, gravity=spring.gravity,
                       fixed=spring.fixed, drag=0.1)
    assert reference.exact_spring(dragged, [0.1]) is None


@pytest.mark.full
def test_newton_integrators_get_a_line_per_newton_tolerance(tmp_path):
    """backward-euler and bdf2 run at each of newton_tols (not cg_tols), recorded per run and
    in the lines' names; bdf2's error falls about 4x per halving of dt, backward Euler's 2x."""
    ladders = {"backward-euler": [2e-3, 1e-3, 5e-4], "bdf2": [2e-3, 1e-3, 5e-4]}
    s = study.run_study(tiny_chain(), duration=0.04, integrators=["backward-euler", "bdf2"], ladders=ladders,
                        cg_tols=[1e-8], newton_tols=[1e-10, 1e-2], repeats=1, cache=tmp_path)
    assert len(s.runs) == 12 and all(r.cg_tol is None for r in s.runs)
    assert {r.newton_tol for r in s.runs} == {1e-10, 1e-2}
    assert "bdf2 (block-jacobi) newton_tol=1e-10" in s.orders
    assert all(row["newton_tol"] in (1e-10, 1e-2) for row in (r.row() for r in s.runs))
    assert s.orders["backward-euler (block-jacobi) newton_tol=1e-10"]["order"] == pytest.approx(1.0, abs=0.15)
    assert s.orders["bdf2 (block-jacobi) newton_tol=1e-10"]["order"] == pytest.approx(2.0, abs=0.25)
    assert "1e-10" in report.table(s) and "newton_tol=1e-10" in report.progress_line(s.runs[0])


def test_auto_is_resolved_as_each_integrator_resolves_it():
    """On a 72 x 72 cloth (5,184 free particles, past the multigrid crossover) "auto" is
    the linearised step's multigrid with its finest level in f32, but the Newton-solved
    steps' f64 multigrid (they set the hierarchy up every Newton iteration: the f32 level
    does not pay there), as their own Simulations pick; a name given twice is one line."""
    model = ms.load_scene("cloth").with_params(resolution=72).model()
    assert study.line_preconditioners(model, "implicit", ["auto", "block-jacobi"]) == ["multigrid-f32",
                                                                                       "block-jacobi"]
    for integrator in ("backward-euler", "bdf2"):
        assert study.line_preconditioners(model, integrator, ["auto", "multigrid"]) == ["multigrid"]
        sim = ms.Simulation(model, integrator, dt=1 / 60)
        assert sim.preconditioner == "multigrid"
        sim.close()
