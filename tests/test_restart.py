"""Restart: a run continued from a saved state equals the unbroken run to the bit (f64, every
integrator); states of another model, count or dt, and broken state files, are refused."""

import numpy as np
import pytest

import massspring as ms
from massspring.cli import main
from massspring.engine import adaptive
from massspring.integrators import INTEGRATORS
from massspring.io.state import read_state
from conftest import FULL, PATHS, one_line_error, random_system

CLOTH = ["cloth", "--set", "resolution=5", "--quiet"]  # pins, gravity, damping, a surface


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
def test_ten_plus_ten_steps_through_a_file_equal_twenty(integrator, tmp_path, capsys):
    first, second, whole = (tmp_path / f"{name}.npz" for name in ("first", "second", "whole"))
    args = ["run", *CLOTH, "--integrator", integrator]
    assert main([*args, "--steps", "10", "--out", str(first)]) == 0
    assert main([*args, "--steps", "10", "--restart", str(first), "--out", str(second)]) == 0
    assert "from the restart at step 10 to step 20" in capsys.readouterr().out
    assert main([*args, "--steps", "20", "--out", str(whole)]) == 0
    a, b = np.load(second), np.load(whole)
    assert np.array_equal(a["positions"], b["positions"]) and np.array_equal(a["velocities"], b["velocities"])
    assert int(a["steps"]) == 20 and float(a["time"]) == float(b["time"])
    assert not np.array_equal(a["positions"], np.load(first)["positions"])  # it did move


@FULL
def test_restart_of_a_contact_scene_through_a_file_continues_to_the_bit(tmp_path, capsys):
    """The implicit step's contact memory (sticking, released contacts, friction) goes
    into the state file with the positions."""
    first, second, whole = (tmp_path / f"{name}.npz" for name in ("first", "second", "whole"))
    args = ["run", "drape", "--set", "resolution=8", "--quiet"]
    assert main([*args, "--steps", "30", "--out", str(first)]) == 0
    assert "carried_stick" in np.load(first).files
    assert main([*args, "--steps", "10", "--restart", str(first), "--out", str(second)]) == 0
    assert main([*args, "--steps", "40", "--out", str(whole)]) == 0
    a, b = np.load(second), np.load(whole)
    assert np.array_equal(a["positions"], b["positions"]) and np.array_equal(a["velocities"], b["velocities"])


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
def test_set_state_continues_bitwise(integrator, path):
    """With what the run carries (``carried_state``: BDF2's previous state; nothing for the
    others on this model without colliders or self-collision)."""
    model = random_system(3)
    whole = ms.Simulation(model, integrator=integrator, dt=2e-3, loops=path).step(12)
    part = ms.Simulation(model, integrator=integrator, dt=2e-3, loops=path).step(5)
    x, v, carried = part.positions, part.velocities, part.carried_state()
    part.close()
    rest = ms.Simulation(model, integrator=integrator, dt=2e-3, loops=path).set_state(x, v, steps=5,
                                                                                      carried=carried).step(7)
    assert rest.steps == 12 and rest.time == whole.time
    assert np.array_equal(rest.positions, whole.positions) and np.array_equal(rest.velocities, whole.velocities)
    whole.close()
    rest.close()


@FULL
@pytest.mark.parametrize("integrator", ["symplectic", "implicit"])
def test_set_state_continues_moving_pins_and_colliders_bitwise(integrator):
    """Moving pins and a moving collider are where they are at steps x dt after a restart:
    the continued run equals the unbroken one to the bit."""
    base = ms.load_scene("cloth").with_params(resolution=6).model()
    floor = ms.Plane((0.0, 0.0, -0.3), (0.0, 0.0, 1.0), friction=0.5, velocity=(0.0, 0.0, 0.2))
    model = ms.Model(base.positions, base.springs, masses=base.masses, stiffness=base.stiffness,
                     damping=base.damping, rest_lengths=base.rest_lengths, gravity=base.gravity, fixed=base.fixed,
                     pin_velocity=[[0.0, 0.0, -0.4]] * base.fixed.size, colliders=[floor])
    dt = 1 / 60 if integrator == "implicit" else 1e-3
    whole = ms.Simulation(model, integrator=integrator, dt=dt).step(40)
    part = ms.Simulation(model, integrator=integrator, dt=dt).step(25)
    x, v, carried = part.positions, part.velocities, part.carried_state()
    part.close()
    assert set(carried) == ({"released", "stick", "fric"} if integrator == "implicit" else set())
    rest = ms.Simulation(model, integrator=integrator, dt=dt).set_state(x, v, steps=25, carried=carried).step(15)
    assert np.array_equal(rest.positions, whole.positions) and np.array_equal(rest.velocities, whole.velocities)
    free = model.free_mask()  # pins are kinematic: they go through the floor
    assert np.all(rest.positions[free, 2] >= -0.3 + 0.2 * rest.time - 1e-9)  # the floor moved up to meet them
    with pytest.raises(ValueError, match="pin velocity"):
        rest.set_state(x, np.zeros_like(v))
    with pytest.raises(ValueError, match="carried"):
        rest.set_state(x, v, carried={"stick": np.zeros(model.n_particles)})
    whole.close()
    rest.close()


def test_set_state_checks_its_arguments():
    model = random_system(4, n=8, n_fixed=1)
    sim = ms.Simulation(model, integrator="symplectic", dt=1e-3)
    pinned = int(model.fixed[0])
    x, v = model.positions.copy(), np.zeros((8, 3))
    for kwargs, word in ((dict(positions=x[:7], velocities=v), "positions: expected shape (8, 3)"),
                         (dict(positions=x, velocities=v.ravel()), "velocities: expected shape"),
                         (dict(positions=np.where(x == x[0, 0], np.nan, x), velocities=v), "positions: contains"),
                         (dict(positions=x, velocities=v, steps=-1), "steps"),
                         (dict(positions=x, velocities=np.where(np.arange(8)[:, None] == pinned, 1.0, v)),
                          f"velocities: particle {pinned} is pinned")):
        with pytest.raises(ValueError, match=word.replace("(", r"\(").replace(")", r"\)")):
            sim.set_state(**kwargs)
    assert sim.steps == 0 and np.array_equal(sim.positions, model.positions)  # nothing was changed
    sim.close()


def test_state_file_records_what_a_restart_checks(tmp_path):
    out = tmp_path / "state.npz"
    assert main(["run", *CLOTH, "--steps", "3", "--out", str(out)]) == 0
    state = read_state(out)
    model = ms.load_scene("cloth").with_params(resolution=5).model()
    assert state.fingerprint == model.fingerprint() and state.scene == "cloth" and state.integrator == "implicit"
    assert state.steps == 3 and state.n_particles == 25 and state.dt == pytest.approx(1 / 60)
    with np.load(out) as data:  # the keys of earlier versions are unchanged
        assert {"positions", "velocities", "springs", "time", "steps", "dt"} <= set(data.files)


@pytest.mark.parametrize("options, words", [
    (["cloth", "--set", "resolution=6"], ["holds 25 particles", "scene 'cloth' has 36"]),
    (["spring"], ["holds 25 particles", "scene 'spring' has 2"]),
    ([*CLOTH, "--set", "stiffness=2e4"], ["another model", "scene 'cloth'", "--set"]),
    ([*CLOTH, "--set", "bend=0.2"], ["another model"]),
    ([*CLOTH, "--dt", "0.01"], ["dt = 0.016666666666666666 s", "--dt 0.016666666666666666"]),
])
def test_restart_of_another_model_or_dt_is_refused(options, words, tmp_path, capsys):
    out = tmp_path / "state.npz"
    assert main(["run", *CLOTH, "--steps", "2", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["run", *options, "--steps", "2", "--restart", str(out)]) == 2
    one_line_error(capsys, "--restart", *words)


def test_broken_state_files_are_refused(tmp_path, capsys):
    good = tmp_path / "good.npz"
    assert main(["run", *CLOTH, "--steps", "2", "--out", str(good)]) == 0
    capsys.readouterr()
    data = dict(np.load(good))
    cases = {"text.npz": b"not a zip file", "old.npz": {k: v for k, v in data.items() if k != "fingerprint"},
             "nan.npz": {**data, "positions": np.where(data["positions"] > 0.5, np.nan, data["positions"])},
             "shape.npz": {**data, "velocities": data["velocities"][:3]},
             "steps.npz": {**data, "steps": np.array(-4)},
             "kind.npz": {**data, "dt": np.array("0.1")}}
    words = {"text.npz": "not a state file", "old.npz": "fingerprint: missing", "nan.npz": "positions: holds a "
             "non-finite", "shape.npz": "velocities: expected shape (n, 3) with n = 25", "steps.npz": "steps: must be",
             "kind.npz": "dt: expected real numbers"}
    for name, content in cases.items():
        path = tmp_path / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            np.savez(path, **content)
        assert main(["run", *CLOTH, "--steps", "2", "--restart", str(path)]) == 2, name
        one_line_error(capsys, "--restart", str(path), words[name])
    assert main(["run", *CLOTH, "--steps", "2", "--restart", str(tmp_path / "none.npz")]) == 2
    one_line_error(capsys, "--restart", "cannot be read")


def test_an_error_controlled_state_file_carries_its_controller(tmp_path, capsys):
    """A state saved by an error-controlled run holds its control_<name> members (its
    controller and the states its estimate draws on), a fixed run's none; a file with
    only some of them, another, a name that is none, more numbers than a run of its size
    keeps, or shapes that do not fit the run is refused (exit 2, one line naming the
    file and key)."""
    controlled, fixed = tmp_path / "tol.npz", tmp_path / "fixed.npz"
    assert main(["run", "spring", "--tol", "1e-2", "--duration", "0.5", "--out", str(controlled), "--quiet"]) == 0
    assert main(["run", "spring", "--steps", "5", "--out", str(fixed), "--quiet"]) == 0
    capsys.readouterr()
    assert sorted(read_state(controlled).control) == sorted(adaptive.CONTROL_KEYS)
    assert read_state(fixed).control is None
    data = dict(np.load(controlled))
    cases = {"part.npz": ({k: v for k, v in data.items() if k != "control_est_y"}, "control: expected the keys"),
             "other.npz": ({**data, "control_extra": np.zeros(3)}, "control: expected the keys"),
             "deep.npz": ({**data, "control_extra": np.zeros((1, 1, 1, 1))}, "control_extra: expected at most 3"),
             "name.npz": ({**data, "control_not-a-name": np.zeros(3)}, "'control_not-a-name.npy': not a key"),
             "big.npz": ({**data, "control_est_y": np.zeros((3, 200, 6))}, "control_<name> members hold"),
             "shape.npz": ({**data, "control_est_y": data["control_est_y"][:, :, :3]},
                           "control['est_y']: expected shape")}
    for name, (content, words) in cases.items():
        path = tmp_path / name
        np.savez(path, **content)
        assert main(["run", "spring", "--tol", "1e-2", "--restart", str(path), "--quiet"]) == 2, name
        one_line_error(capsys, "--restart", str(path), words)


@FULL
def test_an_error_controlled_run_with_impacts_restarts_to_the_bit(tmp_path, capsys):
    """The rope landing on its ball (midpoint, tol 1e-2): 0.3 s, saved, then 0.3 s more
    from the file equal the unbroken run of two 0.3 s parts to the bit, its estimate's
    distances to the colliders and contacts carried in the file."""
    first, second = tmp_path / "first.npz", tmp_path / "second.npz"
    args = ["run", "rope-drop", "--integrator", "midpoint", "--tol", "1e-2", "--duration", "0.3", "--quiet"]
    assert main([*args, "--out", str(first)]) == 0
    assert main([*args, "--restart", str(first), "--out", str(second)]) == 0
    assert np.load(first)["control_est_has"][:, 0].all()  # each point with its distances
    unbroken = ms.load_scene("rope-drop").simulation("midpoint", tol=1e-2).advance(0.3).advance(0.3)
    end = np.load(second)
    assert int(end["steps"]) == unbroken.steps and float(end["time"]) == unbroken.time
    assert np.array_equal(end["positions"], unbroken.positions)
    assert np.array_equal(end["velocities"], unbroken.velocities)
    assert unbroken.control_stats()["rejected"]["error"] > 0  # it did control its steps


def test_restart_without_a_length_finishes_the_scene(tmp_path, capsys):
    # spring: 5 s at dt = 1/100 s, 500 steps; a restart at step 120 adds the 380 left
    first, second, whole = (tmp_path / f"{name}.npz" for name in ("first", "second", "whole"))
    assert main(["run", "spring", "--quiet", "--steps", "120", "--out", str(first)]) == 0
    assert main(["run", "spring", "--quiet", "--restart", str(first), "--out", str(second)]) == 0
    assert "380 from the restart at step 120 to step 500" in capsys.readouterr().out
    assert main(["run", "spring", "--quiet", "--out", str(whole)]) == 0
    a, b = np.load(second), np.load(whole)
    assert int(a["steps"]) == int(b["steps"]) == 500
    assert np.array_equal(a["positions"], b["positions"]) and np.array_equal(a["velocities"], b["velocities"])
    # a state already at (or past) the scene's end: nothing is left to run
    assert main(["run", "spring", "--quiet", "--restart", str(whole), "--out", str(first)]) == 0
    assert int(np.load(first)["steps"]) == 500
