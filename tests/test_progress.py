"""Progress off a terminal: plain lines (no colour codes, no carriage returns) every
``progress.INTERVAL`` seconds of long work, nothing for short work or with --quiet."""

import io
import time

import pytest

from massspring.support import progress
from massspring.cli import main


def test_step_line():
    line = progress.step_line("run chain (implicit, dt 1/100 s)", 250, 1000, 0.01, 12.4, rate=25.0)
    assert line == "run chain (implicit, dt 1/100 s): step 250/1,000 (25%), 2.5 s simulated, 12 s elapsed, ~30 s left"
    assert "left" not in progress.step_line("x", 0, 10, 0.1, 3.0)
    assert "compiling kernels" in progress.step_line("x", 0, 10, 0.1, 3.0)  # issue 42: a first run sat silent
    assert "compiling" not in progress.step_line("x", 1, 10, 0.1, 3.0)
    assert "left" not in progress.step_line("x", 10, 10, 0.1, 3.0, rate=2.0)


def plain_lines(err):
    lines = [line for line in err.splitlines() if "elapsed" in line]
    for line in lines:
        assert "\x1b[" not in line and "\r" not in line
    return lines


def test_a_long_run_off_a_terminal_prints_plain_lines(monkeypatch, capsys):
    monkeypatch.setattr(progress, "INTERVAL", 0.01)
    monkeypatch.setattr(progress, "interactive", lambda stream: False)
    assert main(["run", "chain", "--set", "count=5", "--steps", "300"]) == 0
    lines = plain_lines(capsys.readouterr().err)
    steps = [line for line in lines if ": step " in line]
    assert steps and all(line.startswith("run chain (implicit, dt 1/100 s): step ") and "/300 (" in line
                         for line in steps)
    assert main(["run", "chain", "--set", "count=5", "--steps", "300", "--quiet"]) == 0
    assert plain_lines(capsys.readouterr().err) == []


def test_short_work_prints_nothing(capsys):
    assert main(["run", "chain", "--set", "count=5", "--steps", "2"]) == 0  # INTERVAL is 5 s
    assert plain_lines(capsys.readouterr().err) == []


def test_phase_reports_while_the_block_runs(monkeypatch):
    monkeypatch.setattr(progress, "INTERVAL", 0.02)
    stream = io.StringIO()
    with progress.phase("info cloth: building", stream=stream):
        time.sleep(0.15)
    lines = stream.getvalue().splitlines()
    assert lines and all(line.startswith("info cloth: building: ") and line.endswith(" s elapsed") for line in lines)
    stream = io.StringIO()
    with progress.phase("quiet", show=False, stream=stream):
        time.sleep(0.05)
    assert stream.getvalue() == ""


def test_steps_estimates_the_time_left_from_the_pace(monkeypatch):
    now = [0.0]
    tracker = progress.steps("run x", 100, 0.01, stream=io.StringIO(), clock=lambda: now[0])
    monkeypatch.setattr(progress, "interactive", lambda stream: False)
    with tracker as update:
        now[0] = 20.0                 # the first step, with compilation
        update(1, 100)
        now[0] = 29.0
        update(10, 100)               # 9 steps in 9 s after it
        assert tracker.line(29.0).endswith("step 10/100 (10%), 0.1 s simulated, 29 s elapsed, ~90 s left")


@pytest.mark.parametrize("tty", [True, False])
def test_interactive(tty):
    class Stream(io.StringIO):
        def isatty(self):
            return tty

    assert progress.interactive(Stream()) is tty
    assert progress.interactive(object()) is False


def test_stability_reports_its_settling_run(monkeypatch, capsys):
    """``stability --at`` runs the implicit integrator first (10^6 steps and more are
    accepted): it reports progress as ``run`` does."""
    monkeypatch.setattr(progress, "INTERVAL", 0.01)
    monkeypatch.setattr(progress, "interactive", lambda stream: False)
    assert main(["stability", "chain", "--set", "count=5", "--at", "3", "--predict-only"]) == 0
    steps = [line for line in plain_lines(capsys.readouterr().err) if ": step " in line]
    assert steps and all(line.startswith("stability chain: settling for --at 3 s (implicit, dt 1/100 s): step ")
                         and "/300 (" in line for line in steps)
