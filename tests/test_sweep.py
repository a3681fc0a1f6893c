"""Sweeps (massspring/analysis/sweep.py, cluster.py, `massspring sweep`): the cases and
their checks, rows equal to direct runs of the same case, resume, divergence and
failure as rows, final states, the plot, and the same rows from a Dask cluster of
worker processes, also when a worker is killed mid-case."""

import csv
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import massspring as ms
from massspring.analysis import sweep
from massspring.cli import main
from massspring.io.state import read_state

from conftest import FULL, one_line_error


def chain(count=5):
    return ms.load_scene("chain").with_params(count=count)


def direct(scene, steps, integrator=None, dt=None, **params):
    """The case run by hand: (final total energy, largest |strain|, steps)."""
    sim = scene.with_params(**params).simulation(integrator, dt=dt)
    try:
        sim.step(steps)
    except ms.DivergenceError:
        pass
    x = sim.positions
    springs, rest = sim.model.springs, sim.model.rest_lengths
    strain = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1) / rest - 1
    out = sim.energy()["total"], float(np.abs(strain).max()), sim.steps
    sim.close()
    return out


def read_rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_split_values_keeps_lists_and_quotes_whole():
    assert sweep.split_values("1e3, 1e4") == ["1e3", "1e4"]
    assert sweep.split_values("[0,0,-9.81],[0,0,-1.62]") == ["[0,0,-9.81]", "[0,0,-1.62]"]
    assert sweep.split_values('"a,b",c') == ['"a,b"', "c"]
    assert sweep.parse_vary(["gravity=[0,0,-9.81],[0,0,-1.62]", "pin=end,none"]) == {
        "gravity": [[0, 0, -9.81], [0, 0, -1.62]], "pin": ["end", "none"]}


def test_one_case_per_combination_in_order():
    cases = sweep.plan(chain(), {"stiffness": [1e2, 1e3], "dt": [0.01, 0.02, 0.03]})
    assert [c.number for c in cases] == [1, 2, 3, 4, 5, 6]
    assert [c.label() for c in cases[:2]] == ["stiffness=100.0 dt=0.01", "stiffness=100.0 dt=0.02"]


@pytest.mark.parametrize("vary, message", [
    ({"bogus": [1]}, "vary bogus: unknown key"),
    ({"stiffness": []}, "vary stiffness: no values"),
    ({"count": [5, 1]}, "vary count: value 1: .*must be >= 2"),
    ({"stiffness": [1e3, 1000.0]}, "vary stiffness: a value given twice"),
    ({"dt": [0.01, -1.0]}, "vary dt: value -1.0"),
    ({"integrator": ["implicit", "leapfrog"]}, "vary integrator: value leapfrog"),
    ({"preconditioner": ["multigrid"]}, "vary preconditioner: explicit solves no linear system"),
    ({"count": list(range(2, 17)), "stiffness": list(range(1, 15))}, "vary: 210 cases, more than 200"),
])
def test_bad_vary_is_refused_before_any_case(vary, message):
    scene = chain()
    with pytest.raises(ValueError, match=message):
        sweep.plan(scene, vary, integrator="explicit" if "preconditioner" in vary else None)


@FULL
def test_rows_are_the_direct_runs_and_resume_skips_finished_cases(tmp_path):
    out = tmp_path / "rows.csv"
    vary = {"stiffness": [1e2, 1e3], "integrator": ["implicit", "symplectic"]}
    rows = ms.sweep(chain(), vary, steps=20, out=out)
    assert [(r["stiffness"], r["integrator"]) for r in rows] == [
        (1e2, "implicit"), (1e2, "symplectic"), (1e3, "implicit"), (1e3, "symplectic")]
    for row in rows:
        energy, strain, steps = direct(chain(), 20, row["integrator"], stiffness=row["stiffness"])
        assert (row["status"], row["energy"], row["max_strain"], row["steps"]) == ("ok", energy, strain, steps)
        assert (row["cg_iterations"] != "") == (row["integrator"] == "implicit")
    written = read_rows(out)
    assert [float(r["energy"]) for r in written] == [r["energy"] for r in rows]  # repr: the same bits
    # a crash cut the last line short: that case is run again, the others are skipped
    text = out.read_text()
    out.write_text(text[: text.rstrip("\n").rfind("\n") + 12])
    seen = []
    again = sweep.sweep(chain(), vary, steps=20, out=out, progress=lambda case, row: seen.append(case.number))
    assert seen == [4]
    assert [r["energy"] for r in again] == [r["energy"] for r in rows]
    assert len(read_rows(out)) == 4


def test_an_out_file_of_another_sweep_is_refused(tmp_path):
    out = tmp_path / "rows.csv"
    sweep.sweep(chain(), {"stiffness": [1e2]}, steps=2, out=out)
    with pytest.raises(ValueError, match="holds another table"):
        sweep.sweep(chain(), {"damping": [0.1]}, steps=2, out=out)


def test_diverged_and_failed_cases_are_rows_and_the_sweep_goes_on(tmp_path):
    rows = sweep.sweep(chain(), {"integrator": ["explicit", "implicit"], "preconditioner": ["block-jacobi"]},
                       dt=0.05, steps=30)
    failed, ok = rows
    assert failed["status"] == "failed" and "explicit solves no linear system" in failed["message"]
    assert ok["status"] == "ok"
    rows = sweep.sweep(chain(), {"dt": [1e-3, 0.05]}, integrator="explicit", steps=30, states=tmp_path)
    assert [r["status"] for r in rows] == ["ok", "diverged"]
    energy, _, steps = direct(chain(), 30, "explicit", dt=0.05)
    assert rows[1]["steps"] == steps < 30 and rows[1]["energy"] == energy  # the last good state
    assert "diverged at step" in rows[1]["message"]
    state = read_state(tmp_path / "case0002.npz", chain().model())
    assert state.steps == steps and state.dt == 0.05


def test_a_ladder_of_tolerances_runs_each_case_to_its_duration():
    """``tol`` varied: each case is an error-controlled run that ends on the duration
    exactly, the tighter tol taking more steps and coming closer to a reference run (BDF2
    at a tenth of the tightest tol); its row is the direct run's."""
    scene = chain()
    rows = sweep.sweep(scene, {"tol": [1e-2, 1e-3]}, integrator="bdf2", duration=0.2)
    assert [r["status"] for r in rows] == ["ok", "ok"] and all(r["time"] == 0.2 for r in rows)
    assert rows[0]["steps"] < rows[1]["steps"]
    finals = []
    for tol in (1e-2, 1e-3, 1e-4):
        sim = scene.simulation("bdf2", tol=tol, horizon=0.2)
        sim.advance(0.2)
        finals.append((sim.positions, sim.energy()["total"], sim.steps))
        sim.close()
    assert [r["energy"] for r in rows] == [finals[0][1], finals[1][1]]
    assert [r["steps"] for r in rows] == [finals[0][2], finals[1][2]]
    errors = [np.abs(x - finals[2][0]).max() for x, _, _ in finals[:2]]
    assert errors[1] < errors[0]


def test_cli_sweep_writes_csv_and_table(tmp_path, capsys):
    out = tmp_path / "s.csv"
    code = main(["sweep", "chain", "--set", "count=5", "--vary", "stiffness=1e2,1e3", "--vary", "damping=0,0.1",
                 "--steps", "10", "--out", str(out)])
    assert code == 0
    text = capsys.readouterr()
    assert "case 4 of 4 (stiffness=1000.0 damping=0.1): ok" in text.err
    assert len(read_rows(out)) == 4
    assert text.out.splitlines()[0].split() == ["case", "stiffness", "damping", "status", "steps", "time", "wall_s",
                                                "energy", "max_strain", "cg_iterations"]


def test_an_axis_spanning_decades_is_logarithmic():
    """Issue 42: a metric over decades (wall times, strains) was drawn on a linear axis."""
    assert sweep.spans_decades([1e-3, 0.5, 2.0]) and sweep.spans_decades([10, 100])
    assert not sweep.spans_decades([1.0, 9.0]) and not sweep.spans_decades([0.0, 100.0])
    assert not sweep.spans_decades([-1.0, 100.0]) and not sweep.spans_decades([5.0])


def test_plot_marks_diverged_cases(tmp_path):
    import matplotlib  # noqa: F401  (in the [test] extra: a missing one fails here, not a skip)
    from PIL import Image

    rows = sweep.sweep(chain(), {"dt": [1e-3, 2e-3, 0.05], "damping": [0.0, 0.1]}, integrator="explicit", steps=30)
    assert sorted({r["status"] for r in rows}) == ["diverged", "ok"]
    path = sweep.plot(rows, ["dt", "damping"], "max_strain", tmp_path / "p.png", "chain")
    pixels = np.asarray(Image.open(path).convert("RGB")).reshape(-1, 3).astype(int)
    red = (pixels[:, 0] > 200) & (pixels[:, 1] < 60) & (pixels[:, 2] < 60)
    assert red.sum() > 20  # the crosses of the diverged cases


@pytest.mark.parametrize("argv, words", [
    (["--vary", "bogus=1"], ["--vary bogus", "unknown key"]),
    (["--vary", "count="], ["--vary count", "empty value"]),
    (["--vary", "count=2,3", "--plot", "x.gif"], ["--plot", ".png"]),
    (["--vary", "count=2", "--vary", "stiffness=1", "--vary", "damping=0", "--plot", "p.png"], ["--plot", "two"]),
    (["--vary", "count=2", "--workers", "0"], ["--workers", "1..1024"]),
    (["--vary", "count=2", "--steps", "0"], ["--steps"]),
    (["--vary", "tol=1e-3,0"], ["--vary tol", "tol"]),
    (["--vary", "tol=1e-3", "--steps", "10"], ["--steps", "measured in time"]),
    (["--vary", "count=2", "--tol", "1e-3", "--steps", "10"], ["--steps", "measured in time"]),
    (["--vary", "count=2", "--tol", "1e-3", "--cg-tol", "1e-6"], ["--cg-tol", "derives it from --tol"]),
])
def test_cli_bad_input_exits_2_naming_it(argv, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["sweep", "chain", "--out", "s.csv", *argv]) == 2
    one_line_error(capsys, *words)
    assert not (tmp_path / "s.csv").exists()


@FULL
def test_sigterm_keeps_every_finished_row_and_a_rerun_finishes(tmp_path):
    out = tmp_path / "s.csv"
    args = [sys.executable, "-m", "massspring", "sweep", "cloth", "--set", "resolution=16", "--integrator",
            "implicit", "--vary", "stiffness=1e3,2e3,3e3,4e3,5e3,6e3", "--steps", "1000", "--out", str(out)]
    proc = subprocess.Popen(args, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    for line in proc.stderr:  # wait for the first finished case
        if "case 1 of 6" in line:
            break
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "terminated" in err and "Traceback" not in err
    done = read_rows(out)
    assert 1 <= len(done) < 6 and all(r["status"] == "ok" for r in done)
    rerun = subprocess.run(args, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stderr
    assert f"case {len(done) + 1} of 6" in rerun.stderr and "case 1 of 6" not in rerun.stderr
    assert sorted(int(r["case"]) for r in read_rows(out)) == [1, 2, 3, 4, 5, 6]


# ---------------------------------------------------------------- on a Dask cluster

def free_port():
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def client():
    """A real cluster on 127.0.0.1: `dask scheduler` and two `dask worker` processes (one
    thread each, under a nanny that restarts a killed worker), torn down after."""
    pytest.importorskip("distributed", reason="the [cluster] extra (Dask distributed) is not installed")
    from massspring.analysis import cluster

    address = f"tcp://127.0.0.1:{free_port()}"
    dask = [sys.executable, "-m", "dask"]
    quiet = dict(stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    processes = [subprocess.Popen([*dask, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                                   "--no-dashboard"], **quiet)]
    try:
        processes += [subprocess.Popen([*dask, "worker", address, "--nthreads", "1", "--no-dashboard",
                                        "--death-timeout", "60"], **quiet) for _ in range(2)]
        with cluster.cluster(address=address, timeout=60) as c:
            c.wait_for_workers(2, timeout=120)
            yield c
    finally:
        for proc in processes[::-1]:
            proc.terminate()
        for proc in processes[::-1]:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@FULL
def test_a_cluster_gives_the_serial_rows_to_the_bit_and_resumes(client, tmp_path):
    vary = {"stiffness": [1e2, 1e3], "integrator": ["implicit", "bdf2", "symplectic"]}
    here = sweep.sweep(chain(), vary, steps=20)
    out = tmp_path / "s.csv"
    there = sweep.sweep(chain(), vary, steps=20, client=client, out=out, states=tmp_path)
    keys = ("stiffness", "integrator", "status", "steps", "energy", "max_strain", "cg_iterations")
    assert [[r[k] for k in keys] for r in there] == [[r[k] for k in keys] for r in here]
    assert len(read_rows(out)) == 6 and len(list(tmp_path.glob("case*.npz"))) == 6
    lines = out.read_text().splitlines(keepends=True)
    out.write_text("".join(lines[:4]))  # the header and three cases
    seen = []
    again = sweep.sweep(chain(), vary, steps=20, client=client, out=out, progress=lambda c, r: seen.append(c.number))
    assert len(seen) == 3 and sorted(int(r["case"]) for r in read_rows(out)) == [1, 2, 3, 4, 5, 6]
    assert [r["energy"] for r in again] == [r["energy"] for r in here]


@FULL
def test_a_case_whose_worker_is_killed_is_run_again(client):
    pids = list(client.run(os.getpid).values())
    killed = []

    def kill_one(case, row):
        if not killed:  # both workers are busy with the next cases: kill one mid-case
            time.sleep(0.3)
            os.kill(pids[0], signal.SIGKILL)
            killed.append(case.number)

    vary = {"stiffness": [1e3 * (k + 1) for k in range(6)]}
    cloth = ms.load_scene("cloth").with_params(resolution=16)
    rows = sweep.sweep(cloth, vary, integrator="implicit", steps=1000, client=client, progress=kill_one)
    assert killed and [r["status"] for r in rows] == ["ok"] * 6
    assert all(r["steps"] == 1000 for r in rows)
    client.wait_for_workers(2, timeout=60)  # the nanny restarted the killed one


def test_cli_runs_on_local_workers(tmp_path, capsys):
    pytest.importorskip("distributed", reason="the [cluster] extra (Dask distributed) is not installed")
    out = tmp_path / "s.csv"
    assert main(["sweep", "chain", "--set", "count=5", "--vary", "stiffness=1e2,1e3", "--steps", "10",
                 "--out", str(out), "--workers", "2", "--quiet"]) == 0
    assert [r["status"] for r in read_rows(out)] == ["ok", "ok"]


@FULL
def test_stability_ladder_and_study_on_a_cluster_equal_the_serial_ones(client):
    from massspring.analysis import stability, study

    scene = chain()
    prediction = stability.predict(scene.model())
    here = stability.ladder(scene, prediction, duration=0.05, max_steps=50)
    there = stability.ladder(scene, prediction, duration=0.05, max_steps=50, client=client)
    assert repr(there) == repr(here) and len(here) > 10  # repr: nan equals nan
    options = dict(integrators=["explicit", "bdf2"], rungs=2, repeats=1, duration=0.05, use_cache=False)
    a, b = study.run_study(scene, **options), study.run_study(scene, client=client, **options)
    assert [(r.integrator, r.dt, r.error, r.steps) for r in b.runs] == [(r.integrator, r.dt, r.error, r.steps)
                                                                        for r in a.runs]
    assert all(r.error is not None for r in a.runs)


def test_equal_values_written_differently_are_one_value():
    """Issue 42: ``--vary stiffness=1000,1e3`` ran the same case twice."""
    scene = ms.load_scene("spring")
    with pytest.raises(ValueError, match=r"vary stiffness: a value given twice \(1000 and 1000.0\)"):
        sweep.plan(scene, {"stiffness": [1000, 1e3]})


def test_equal_vectors_written_differently_are_one_value():
    """Issue 60: ``--vary "gravity=[0,0,-1],[0,0,-1.0]"`` ran two identical cases."""
    scene = ms.load_scene("spring")
    with pytest.raises(ValueError, match=r"vary gravity: a value given twice"):
        sweep.plan(scene, sweep.parse_vary(["gravity=[0,0,-1],[0,0,-1.0]"]))
    assert len(sweep.plan(scene, {"gravity": [[0, 0, -1], [0, 0, -2]]})) == 2


def test_numpy_arrays_and_scalars_are_values():
    """Issue 60: ``ms.sweep`` with a numpy array of values said "no values", and with
    ``np.int64(100)`` "expected a number, got int64"; a 2-d array is a list of vectors."""
    scene = chain()
    cases = sweep.plan(scene, {"stiffness": np.array([1e2, 1e3]), "count": [np.int64(4)]})
    assert [dict(case.values) for case in cases] == [{"stiffness": 100.0, "count": 4}, {"stiffness": 1000.0, "count": 4}]
    assert all(type(case.values[1][1]) is int for case in cases)
    cases = sweep.plan(scene, {"gravity": np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -2.0]])})
    assert [case.values[0][1] for case in cases] == [[0.0, 0.0, -1.0], [0.0, 0.0, -2.0]]


def test_the_lock_file_is_removed_when_the_sweep_ends(tmp_path):
    """Issue 60: ``.sweep.csv.lock`` was left behind; removed on every exit (a failed
    sweep's too), and a sweep that follows takes a lock of its own."""
    out = tmp_path / "sweep.csv"
    sweep.sweep(chain(), {"stiffness": [1e2]}, steps=2, out=out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sweep.csv"]
    with pytest.raises(ValueError, match="holds another table"):
        sweep.sweep(chain(), {"damping": [0.1]}, steps=2, out=out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sweep.csv"]
    results = sweep.Results(out, ["stiffness"])
    try:
        with pytest.raises(ValueError, match="being written by another sweep"):
            sweep.Results(out, ["stiffness"])
    finally:
        results.close()
    assert not (tmp_path / ".sweep.csv.lock").exists()


def test_the_case_count_is_bounded_before_any_model_is_built_even_when_confirmed(monkeypatch):
    """Issue 42: ``--yes`` with 10^7 cases took 15 GB before the first case."""
    scene = ms.load_scene("spring")
    built = []
    monkeypatch.setattr(type(scene), "model", lambda self: built.append(1))
    vary = {"stiffness": list(range(1, 1001)), "damping": list(range(1, 1001))}
    with pytest.raises(ValueError, match=r"vary: 1,000,000 cases, more than 100,000"):
        sweep.plan(scene, vary, confirm=True)
    assert built == []


def test_numpy_values_are_written_as_numbers():
    """Issue 42: ``ms.sweep`` wrote ``np.float64(100.0)`` into the CSV."""
    assert sweep.value_text(np.float64(100.0)) == "100.0" and sweep.value_text(np.int64(3)) == "3"
    assert sweep._cell(np.float64(0.5)) == "0.5"


def test_a_row_cut_inside_its_last_field_is_not_finished(tmp_path):
    """Issue 42: a line cut inside its last field (24.5 written as 24) was kept as a
    finished case, so a resumed sweep never ran it again."""
    out = tmp_path / "s.csv"
    header = ",".join(["case", "stiffness", *sweep.COLUMNS, sweep.SETUP])
    out.write_text(header + "\r\n1,10,ok,,5,0.05,0.1,1.5,0.01,24.5,steps=5 scene=ab\r\n"
                   "2,20,ok,,5,0.05,0.1,1.5,0.01,24.5,steps=5 sc")
    results = sweep.Results(out, ["stiffness"])
    results.close()
    assert list(results.done) == [1]
    assert out.read_bytes().endswith(b"scene=ab\r\n")  # the cut line dropped from the file too


def test_the_csv_records_each_case_setup_and_a_resume_with_other_options_or_scene_is_refused(tmp_path):
    """Issue 42: a resume ignored every option (rows of a ``--steps 5`` sweep were returned
    for a ``--steps 500`` one). Each row records the setup it ran with; a resume with
    another length, option or scene is refused, naming the case and both setups."""
    out = tmp_path / "s.csv"
    ms.sweep(chain(), {"stiffness": [1e2]}, steps=2, out=out, options={"cg_tol": 1e-9})
    setup = read_rows(out)[0]["setup"]
    assert setup.startswith("cg_tol=1e-09 steps=2 scene=")
    assert setup == sweep.setup_text(chain(), steps=2, options={"cg_tol": 1e-9})
    for other in ({"steps": 3, "options": {"cg_tol": 1e-9}}, {"steps": 2, "options": {"cg_tol": 1e-8}},
                  {"steps": 2, "integrator": "rk4", "options": {"cg_tol": 1e-9}}):
        with pytest.raises(ValueError, match=r"--out: .* holds case 1 \(stiffness=100.0\) with cg_tol=1e-09 steps=2 "
                                             r"scene=\w+, but this sweep runs it with "):
            ms.sweep(chain(), {"stiffness": [1e2]}, out=out, **other)
    with pytest.raises(ValueError, match="but this sweep runs it with cg_tol=1e-09 steps=2 scene="):
        ms.sweep(chain(count=6), {"stiffness": [1e2]}, steps=2, out=out, options={"cg_tol": 1e-9})
    assert sweep.setup_text(chain(count=6)) != sweep.setup_text(chain()) == sweep.setup_text(chain())
    again = ms.sweep(chain(), {"stiffness": [1e2]}, steps=2, out=out, options={"cg_tol": 1e-9},
                     progress=lambda case, row: pytest.fail("a finished case ran again"))
    assert again[0]["status"] == "ok" and len(read_rows(out)) == 1


def test_cli_resume_with_other_options_is_one_line_before_any_case(tmp_path, capsys):
    out = tmp_path / "s.csv"
    argv = ["sweep", "chain", "--set", "count=5", "--vary", "stiffness=1e2,1e3", "--out", str(out)]
    assert main([*argv, "--steps", "2", "--quiet"]) == 0
    capsys.readouterr()
    assert main([*argv, "--steps", "3"]) == 2
    err = one_line_error(capsys, "--out:", "holds case 1 (stiffness=100.0) with ", "but this sweep runs it with ")
    assert " steps=2 " in err.split("but")[0] and " steps=3 " in err.split("but")[1]
    assert main([*argv, "--steps", "2"]) == 0
    assert "resuming" in capsys.readouterr().err and len(read_rows(out)) == 2


def test_a_resume_whose_case_numbers_changed_is_refused_and_values_added_at_the_end_run(tmp_path):
    """Issue 42: a changed --vary list reused case numbers (and overwrote --states files)."""
    out = tmp_path / "s.csv"
    ms.sweep(chain(), {"stiffness": [1e2, 1e3]}, steps=2, out=out, states=tmp_path)
    with pytest.raises(ValueError, match=r"holds case 2 \(stiffness=1000.0\), but this sweep's case 2 is "
                                         r"stiffness=500.0; give another --out"):
        ms.sweep(chain(), {"stiffness": [1e2, 5e2, 1e3]}, steps=2, out=out, states=tmp_path)
    with pytest.raises(ValueError, match=r"holds case 2 \(stiffness=1000.0\), but this sweep has 1 case"):
        ms.sweep(chain(), {"stiffness": [1e2]}, steps=2, out=out)
    seen = []
    ms.sweep(chain(), {"stiffness": [1e2, 1e3, 1e4]}, steps=2, out=out, states=tmp_path,
             progress=lambda case, row: seen.append(case.number))
    assert seen == [3] and [r["stiffness"] for r in read_rows(out)] == ["100.0", "1000.0", "10000.0"]


def test_an_empty_csv_is_a_new_one_and_an_unreadable_one_is_refused(tmp_path):
    """Issue 42: a disk full as the header was written left a 0-byte CSV that every resume
    refused; a cell longer than the csv module reads was a traceback."""
    out = tmp_path / "s.csv"
    out.write_text("")
    sweep.Results(out, ["stiffness"]).close()
    assert out.read_text().splitlines()[0] == ",".join(["case", "stiffness", *sweep.COLUMNS, sweep.SETUP])
    out.write_text("case," + "x" * 200_000 + "\n")
    with pytest.raises(ValueError, match=r"--out: .* is not a sweep's CSV \(field larger than field limit"):
        sweep.Results(out, ["stiffness"])


def test_a_state_that_cannot_be_written_stops_the_sweep_keeping_its_row(tmp_path, monkeypatch, capsys):
    """Issue 42: a full or read-only --states lost the finished row with a traceback."""
    import errno

    from massspring.io import files

    out, states = tmp_path / "s.csv", tmp_path / "states"
    states.mkdir()
    real = files.atomic_output

    def full(path):
        if str(path).endswith(".npz"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(path)

    monkeypatch.setattr(files, "atomic_output", full)
    assert main(["sweep", "chain", "--set", "count=5", "--vary", "stiffness=1e2,1e3", "--steps", "2",
                 "--out", str(out), "--states", str(states), "--quiet"]) == 2
    one_line_error(capsys, "--states:", "case0001.npz", "No space left on device", "the CSV holds case 1's row")
    assert [r["case"] for r in read_rows(out)] == ["1"]
    monkeypatch.setattr(files, "atomic_output", real)
    states.chmod(0o500)
    try:
        if os.access(states, os.W_OK):  # root writes anywhere
            return
        assert main(["sweep", "chain", "--vary", "stiffness=1e2", "--out", str(tmp_path / "t.csv"),
                     "--states", str(states)]) == 2
        one_line_error(capsys, "--states:", "Permission denied")
    finally:
        states.chmod(0o700)


def test_a_fifo_out_is_refused_at_once(tmp_path, capsys):
    """Issue 42: ``--out`` on a FIFO hung."""
    fifo = tmp_path / "s.csv"
    os.mkfifo(fifo)
    assert main(["sweep", "chain", "--vary", "stiffness=1e2", "--out", str(fifo)]) == 2
    one_line_error(capsys, "--out:", "is not a regular file")


def test_a_case_lost_with_its_worker_is_a_failed_row_and_the_sweep_goes_on(tmp_path, monkeypatch, capsys):
    """Issue 42: a case whose worker kept dying aborted the sweep with "Unknown format
    code 'f' for object of type 'str'" (exit 2)."""
    def lost(function, tasks, client=None, on_result=None, keep_lost=False):
        for index, _ in enumerate(tasks):
            on_result(index, RuntimeError("worker lost") if index == 0 else function(*tasks[index]))

    monkeypatch.setattr(sweep.cluster, "run_tasks", lost)
    out = tmp_path / "s.csv"
    assert main(["sweep", "chain", "--set", "count=5", "--vary", "stiffness=1e2,1e3", "--steps", "2",
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "case 1 of 2 (stiffness=100.0): failed: RuntimeError: worker lost" in err
    assert "case 2 of 2 (stiffness=1000.0): ok in " in err
    assert [r["status"] for r in read_rows(out)] == ["failed", "ok"]


@pytest.mark.parametrize("address", ["tls://127.0.0.1:8786", "ucx://127.0.0.1:8786"])
def test_addresses_needing_settings_are_refused_by_name(address, capsys):
    """Issue 42: tls:// and ucx:// addresses ended in tracebacks."""
    pytest.importorskip("distributed", reason="the [cluster] extra (Dask distributed) is not installed")
    assert main(["sweep", "chain", "--vary", "stiffness=1e2", "--out", "s.csv", "--address", address]) == 2
    one_line_error(capsys, "--address:", f"{address.split(':')[0]}:// is not supported", "tcp://HOST:PORT")


def test_a_scheduler_without_workers_is_an_error_not_a_hang(monkeypatch):
    """Issue 42: a scheduler with no workers (or all of them killed) hung with no message."""
    distributed = pytest.importorskip("distributed", reason="the [cluster] extra is not installed")
    from massspring.analysis import cluster

    monkeypatch.setattr(cluster, "NO_WORKER_S", 1.0)
    monkeypatch.setattr(cluster, "POLL_S", 0.2)
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as local, \
            distributed.Client(local) as client:
        start = time.monotonic()
        with pytest.raises(cluster.ClusterError, match=r"no worker for 1 s \(2 task\(s\) unfinished\): start workers"):
            cluster.run_tasks(max, [(1, 2), (3, 4)], client=client)
        assert time.monotonic() - start < 30


def _pause(dask_worker):
    from distributed.core import Status

    dask_worker.status = Status.paused  # what Dask's memory monitor does past the pause fraction


def test_a_cluster_whose_workers_are_all_paused_is_an_error_not_a_hang(monkeypatch):
    """Issue 42: a worker that Dask pauses (its memory past the pause fraction) still
    counted as a worker, so a sweep waited for it without end."""
    distributed = pytest.importorskip("distributed", reason="the [cluster] extra is not installed")
    from massspring.analysis import cluster

    monkeypatch.setattr(cluster, "NO_WORKER_S", 1.0)
    monkeypatch.setattr(cluster, "POLL_S", 0.2)
    with distributed.LocalCluster(n_workers=1, processes=False, dashboard_address=":0", memory_limit=0) as local, \
            distributed.Client(local) as client:
        client.run(_pause)  # no memory monitor (memory_limit=0) resumes it
        start = time.monotonic()
        with pytest.raises(cluster.ClusterError, match=r"every worker of the Dask scheduler \(1\) has been paused "
                                                       r"for 1 s \(2 task\(s\) unfinished\).*--memory-limit"):
            cluster.run_tasks(max, [(1, 2), (3, 4)], client=client)
        assert time.monotonic() - start < 30


def test_a_scheduler_that_goes_away_is_an_error_not_a_traceback(monkeypatch):
    """Issue 42: the scheduler's end cancels the futures; ``distributed.wait`` raised
    FuturesCancelledError past the sweep (found by this test)."""
    distributed = pytest.importorskip("distributed", reason="the [cluster] extra is not installed")
    import threading

    from massspring.analysis import cluster

    monkeypatch.setattr(cluster, "POLL_S", 0.2)
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0", memory_limit=0) as local, \
            distributed.Client(local) as client:
        killer = threading.Timer(1.0, local.close)  # the scheduler (and the cluster) shut down
        killer.start()
        start = time.monotonic()
        with pytest.raises(cluster.ClusterError, match=r"the Dask scheduler (went away with 2 task\(s\) unfinished|"
                                                       r"does not answer)"):
            cluster.run_tasks(max, [(1, 2), (3, 4)], client=client)
        killer.join()
        assert time.monotonic() - start < 30


def test_two_sweeps_cannot_write_one_csv(tmp_path):
    """Issue 42: two sweeps on one CSV wrote every case twice; the second is now refused
    while the first holds it, and runs once it is done."""
    out = tmp_path / "s.csv"
    first = sweep.Results(out, ["stiffness"])
    with pytest.raises(ValueError, match="is being written by another sweep"):
        sweep.Results(out, ["stiffness"])
    first.close()
    sweep.Results(out, ["stiffness"]).close()
