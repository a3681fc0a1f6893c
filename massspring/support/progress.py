"""Progress of long work on stderr: a rich bar on a terminal, plain lines elsewhere.

Where stderr is not a terminal (CI logs, ``| tee``, ``nohup``) a bar would be lost or
garbled, so work that takes longer than ``INTERVAL`` seconds prints one plain line
(no colour, no carriage return) every ``INTERVAL`` seconds instead; work that ends
sooner prints nothing.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time


INTERVAL = 5.0  # seconds between plain progress lines


def interactive(stream) -> bool:
    """Whether ``stream`` is a terminal (a rich bar can be drawn on it)."""
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def step_line(label, done, total, dt, elapsed, rate=None, unit="step") -> str:
    """One plain progress line of a run: ``done`` of ``total`` steps of ``dt`` s after
    ``elapsed`` s of wall time; with ``rate`` (steps per second), the time left."""
    line = (f"{label}: {unit} {done:,}/{total:,} ({100 * done / total:.0f}%), "
            f"{done * dt:.4g} s simulated, {elapsed:.0f} s elapsed")
    if rate and done < total:
        line += f", ~{(total - done) / rate:.0f} s left"
    if done == 0:
        line += "; compiling kernels (a configuration's first steps compile them, once per process)"
    return line


class steps:
    """Progress of ``total`` steps of ``dt`` s as ``simulation.run``'s callback: a
    context manager giving the callback (None when ``show`` is false). Off a terminal,
    a thread prints ``step_line`` every ``INTERVAL`` s, so the first step's compilation
    is reported too (until a step is done, a line and the bar say it compiles kernels); the time left is estimated from the pace after the first report
    of steps done (which includes compiling)."""

    def __init__(self, label, total, dt, show=True, stream=None, clock=time.monotonic, unit="step"):
        self.label, self.total, self.dt, self.show, self.unit = label, total, dt, show, unit
        self.stream = sys.stderr if stream is None else stream
        self.clock = clock
        self.bar = self.ticker = None
        self.done, self.first = 0, None

    def __enter__(self):
        if not self.show:
            return None
        if interactive(self.stream):
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("[progress.description]{task.description}"), BarColumn(),
                                TextColumn("{task.completed}/{task.total} " + ("steps" if self.unit == "step" else self.unit)), TimeElapsedColumn(),
                                TimeRemainingColumn(), transient=True, console=Console(file=self.stream))
            self.bar.__enter__()
            task = self.bar.add_task(f"{self.label}: compiling kernels", total=self.total)
            return lambda done, total: self.bar.update(task, completed=done, description=self.label)
        self.ticker = phase(self.label, stream=self.stream, clock=self.clock, line=self.line)
        self.ticker.__enter__()
        return self.update

    def update(self, done, total):
        self.done = done
        if self.first is None:
            self.first = (self.clock(), done)

    def line(self, elapsed):
        """The current ``step_line``."""
        rate = None
        if self.first is not None and self.done > self.first[1]:
            rate = (self.done - self.first[1]) / max(self.clock() - self.first[0], 1e-9)
        return step_line(self.label, self.done, self.total, self.dt, elapsed, rate, self.unit)

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)
        if self.ticker is not None:
            self.ticker.__exit__(*exc)
        return False


@contextlib.contextmanager
def phase(label, show=True, stream=None, clock=time.monotonic, line=None):
    """While the block runs, print ``label: N s elapsed`` (or ``line(elapsed)``) every
    ``INTERVAL`` seconds, from a thread (nothing if it ends sooner, or if ``show`` is
    false): for work with no steps to count (building a large model, compiling
    kernels, setting up multigrid)."""
    if not show:
        yield
        return
    stream = sys.stderr if stream is None else stream
    line = line or (lambda elapsed: f"{label}: {elapsed:.0f} s elapsed")
    done = threading.Event()
    start = clock()

    def report():
        while not done.wait(INTERVAL):
            print(line(clock() - start), file=stream, flush=True)

    thread = threading.Thread(target=report, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
