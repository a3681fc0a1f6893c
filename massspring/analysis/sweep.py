"""Parameter sweeps: one run of a scene per combination of varied values.

``plan`` checks the varied keys and values and lists the cases (before any run);
``run_case`` runs one (a plain function of plain data, so a Dask worker can run it);
``sweep`` runs them all, here or on a cluster (``cluster.run_tasks``), appending a CSV
row as each finishes and skipping the cases a previous run of the same sweep finished.

Keys are the scene's model parameters (as ``--set``), plus ``dt``, ``integrator`` and
``preconditioner``. A row holds the varied values, ``status`` (``ok``, ``diverged``,
``failed``) and ``message``, ``steps``, ``time`` (simulated s), ``wall_s``, ``energy``
(the final total energy, J, ``Model.energy``), ``max_strain`` (the largest |l / l0 - 1|
of a spring at the end), ``cg_iterations`` (mean per step, implicit integrators) and
``setup`` (``setup_text``: the integrator, dt, length and Simulation options the case ran
with, and a digest of the scene). A resumed sweep skips a case only if its row holds
the same number, values and setup; a CSV whose rows disagree with the sweep is refused.
"""

from __future__ import annotations

import csv
import hashlib
import io
import itertools
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from massspring.support import validate
from massspring.analysis import cluster

RUN_KEYS = ("dt", "integrator", "preconditioner", "tol")
COLUMNS = ("status", "message", "steps", "time", "wall_s", "energy", "max_strain", "cg_iterations")
SETUP = "setup"  # the last column: what every case of the sweep ran with (setup_text)
NUMBERS = ("steps", "time", "wall_s", "energy", "max_strain", "cg_iterations")
METRICS = ("energy", "max_strain", "wall_s", "steps", "time", "cg_iterations")
UNITS = {"energy": "J", "wall_s": "s", "time": "s"}
MAX_CASES = 200  # more than this needs confirm=True (--yes)
MOST_CASES = 100_000  # more than this is refused even with confirm (each case is a run: days of them)


@dataclass(frozen=True)
class Case:
    """One combination: its number in the sweep (from 1) and ((key, value), ...) in the
    order the keys were varied."""

    number: int
    values: tuple

    @property
    def texts(self) -> tuple:
        return tuple(value_text(v) for _, v in self.values)

    def label(self) -> str:
        return " ".join(f"{k}={value_text(v)}" for k, v in self.values)


def value_text(value) -> str:
    """A value as the CSV writes it (and a resumed sweep compares it): TOML-like."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (float, np.floating)):
        return repr(float(value))  # a NumPy float as the number it holds, not np.float64(...)
    if isinstance(value, np.integer):
        return str(int(value))
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(value_text(v) for v in value) + "]"
    return str(value)


def split_values(text) -> list:
    """``"1e3,1e4"`` -> ["1e3", "1e4"]; commas inside brackets or quotes do not split
    (``"[0,0,-9.81],[0,0,-1.62]"`` is two values)."""
    out, depth, quote, start = [], 0, None, 0
    for i, c in enumerate(text):
        if quote:
            quote = None if c == quote else quote
        elif c in "\"'":
            quote = c
        elif c == "[":
            depth += 1
        elif c == "]":
            depth -= 1
        elif c == "," and depth == 0:
            out.append(text[start:i])
            start = i + 1
    out.append(text[start:])
    return [t.strip() for t in out]


def parse_vary(items) -> dict:
    """``--vary KEY=V1,V2,...`` strings -> {key: [value, ...]} (values parsed like ``--set``)."""
    from massspring.scene.spec import setting_items, setting_value

    vary = {}
    for key, text in setting_items(items, "--vary", "KEY=V1,V2,..."):
        texts = split_values(text)
        if any(t == "" for t in texts):
            raise ValueError(f"--vary {key}: an empty value in {text!r} (values are separated by commas)")
        vary[key] = [setting_value(t) for t in texts]
    return vary


def plan(scene, vary, integrator=None, confirm=False, limit=MAX_CASES, option="vary") -> list:
    """The cases of ``vary`` ({key: [values]}) on ``scene``, checked: every key known, every
    value valid for its key (each model parameter value builds a model, without kernels),
    no list empty or repeating a value, a varied preconditioner only with an integrator
    that solves linear systems (``integrator``, else the scene's, unless the integrator is
    varied too), at most ``limit`` cases unless ``confirm``. Raises ValueError naming
    ``option``, the key and the value."""
    from massspring.engine.adaptive import Tolerance
    from massspring.integrators import INTEGRATORS
    from massspring.solvers import CHOICES

    if not isinstance(vary, dict) or not vary:
        raise ValueError(f"{option}: nothing to vary (give KEY=V1,V2,...)")
    vary = {key: _plain(values) for key, values in vary.items()}
    known = set(scene.params) | set(scene.common)
    for key, values in vary.items():
        where = f"{option} {key}"
        if key not in known and key not in RUN_KEYS:
            raise ValueError(f"{where}: unknown key; expected one of {', '.join(sorted(known | set(RUN_KEYS)))}")
        if not isinstance(values, (list, tuple)) or not values:
            raise ValueError(f"{where}: no values")
        seen = {}
        for k, value in enumerate(values):  # 1000 and 1e3 are one value
            first = seen.setdefault(_same_value(value), k)
            if first != k:
                raise ValueError(f"{where}: a value given twice ({value_text(values[first])} and "
                                 f"{value_text(value)})")
    count = math.prod(len(v) for v in vary.values())
    if count > MOST_CASES or (count > limit and not confirm):
        more = (f"more than {MOST_CASES:,}, more than a sweep runs; split it" if count > MOST_CASES else
                f"more than {limit}; pass --yes (confirm=True) to run them all")
        raise ValueError(f"{option}: {count:,} cases, {more}")
    for key, values in vary.items():
        where = f"{option} {key}"
        for value in values:
            try:
                if key == "dt":
                    validate.positive_float("dt", value)
                elif key == "integrator":
                    validate.choice("integrator", value, tuple(INTEGRATORS))
                elif key == "preconditioner":
                    validate.choice("preconditioner", value, CHOICES)
                elif key == "tol":
                    Tolerance.of(value)
                else:
                    scene.with_params(**{key: value}).model()
            except ValueError as exc:
                raise ValueError(f"{where}: value {value_text(value)}: {exc}") from None
    fixed = integrator or scene.integrator
    if "preconditioner" in vary and "integrator" not in vary and not INTEGRATORS[fixed].traits.linear_solver:
        raise ValueError(f"{option} preconditioner: {fixed} solves no linear system; vary it with "
                         + ", ".join(k for k, cls in INTEGRATORS.items() if cls.traits.linear_solver))
    keys = list(vary)
    return [Case(n, tuple(zip(keys, combo))) for n, combo in enumerate(itertools.product(*vary.values()), start=1)]


def check_duration(scene, cases, duration, integrator=None, dt=None, option="duration"):
    """Refuse (ValueError naming ``option``) a ``duration`` (s) that is more than
    MAX_STEPS steps of some case's dt (the varied one, else ``dt``, else the scene's
    default for the case's integrator)."""
    from massspring.support.defaults import MAX_STEPS

    for case in cases:
        values = dict(case.values)
        step = values.get("dt", dt)
        if step is None:
            step = scene.default_dt(values.get("integrator", integrator) or scene.integrator)
        if not duration / step <= MAX_STEPS:
            raise ValueError(f"{option}: {duration:g} s at dt = {step:.3g} s (case {case.number}) is "
                             f"{duration / step:.3g} steps, more than {MAX_STEPS:.3g}")


def setup_text(scene, integrator=None, dt=None, duration=None, steps=None, options=None) -> str:
    """What a case's result depends on besides its varied values, as one line of text:
    ``integrator``, ``dt``, ``duration``, ``steps`` and the Simulation ``options`` that
    are set (sorted, ``key=value``), then ``scene=`` and a digest of the scene's model
    (``Model.fingerprint``: two models with one fingerprint step identically) with the
    scene's default integrator, dts, duration, [solver] table and tols, so that a changed
    scene file, ``--set`` or option makes another setup."""
    run = {"integrator": integrator, "dt": dt, "duration": duration, "steps": steps, **(options or {})}
    fields = [f"{key}={value_text(value)}" for key, value in sorted(run.items()) if value is not None]
    defaults = (scene.integrator, sorted(scene.dt.items()), scene.duration, sorted(scene.solver.items()))
    defaults += (sorted(scene.tol.items()),) if scene.tol else ()  # a scene without one keeps its digest
    digest = hashlib.sha256(f"{scene.model().fingerprint()} {defaults!r}".encode()).hexdigest()[:16]
    return " ".join([*fields, f"scene={digest}"])


def run_case(scene, case, integrator=None, dt=None, duration=None, steps=None, options=None, keep_state=False):
    """Run one case to its end and measure it; never raises for the run's own failure.

    Returns (row, state): ``row`` the case's CSV values (``status`` ``diverged`` with the
    last good state's figures, ``failed`` with the error's message), ``state`` the final
    state's .npz bytes when ``keep_state`` (else None)."""
    from massspring.support.errors import DivergenceError
    from massspring.integrators import INTEGRATORS
    from massspring.io.render import spring_strain
    from massspring.io.state import save_state

    values = dict(case.values)
    params = {k: v for k, v in values.items() if k not in RUN_KEYS}
    integrator = values.get("integrator", integrator)
    dt = values.get("dt", dt)
    options = dict(options or {})
    for key in ("preconditioner", "tol"):
        if key in values:
            options[key] = values[key]
    if steps is not None:
        options.setdefault("tol", None)  # a step count asks for fixed steps: the scene's tol gives way
    if duration is not None:
        options.setdefault("horizon", duration)  # an error-controlled case's (the scene's tol, or one given)
    row = {"status": "ok", "message": "", **{k: "" for k in NUMBERS}}
    start = time.perf_counter()
    sim = None
    try:
        solves = INTEGRATORS[integrator or scene.integrator].traits.linear_solver
        if "preconditioner" in values and not solves:
            raise ValueError(f"preconditioner: {integrator} solves no linear system")
        case_scene = scene.with_params(**params)
        sim = case_scene.simulation(integrator, dt=dt, **options)
        try:
            if sim.tol is not None:  # error-controlled: measured in time
                sim.advance(duration or case_scene.duration)
            else:
                sim.step(steps if steps is not None else max(1, round((duration or case_scene.duration) / sim.dt)))
        except DivergenceError as exc:
            row.update(status="diverged", message=str(exc))
        model = sim.model
        strain = spring_strain(sim.positions, model.springs, model.rest_lengths)
        row.update(steps=sim.steps, time=sim.time, energy=sim.energy()["total"],
                   max_strain=float(np.abs(strain).max()) if len(strain) else 0.0,
                   cg_iterations=float(np.mean(sim.cg_iterations)) if sim.cg_iterations else "")
        state = None
        if keep_state:
            buffer = io.BytesIO()
            save_state(sim, buffer, scene.name)
            state = buffer.getvalue()
    except Exception as exc:  # a case that cannot run is a row, not the end of the sweep
        row.update(status="failed", message=f"{type(exc).__name__}: {exc}")
        state = None
    finally:
        if sim is not None:
            sim.close()
    row["wall_s"] = time.perf_counter() - start
    return row, state


class Results:
    """The sweep's CSV: its header, the rows already there by case number (a resumed
    sweep checks them against its cases and skips them), and appending a row as a case
    finishes (one write of a whole line)."""

    def __init__(self, path, keys):
        self.path = Path(path)
        self.keys = list(keys)
        self.header = ["case", *keys, *COLUMNS, SETUP]
        self.done = {}  # case number -> the row as read (text)
        self.lock = _lock(self.path)
        try:
            if self.path.exists() and self.path.stat().st_size > 0:
                self._read()
            else:  # a new CSV, or an empty one (a disk that was full as the header was written)
                self._write([self.header])
        except BaseException:
            self.close()
            raise

    def _read(self):
        with open(self.path, newline="") as fh:
            text = fh.read()
        try:
            lines = list(csv.reader(io.StringIO(text)))
        except csv.Error as exc:  # e.g. a cell longer than the csv module's field limit
            raise ValueError(f"--out: {str(self.path)!r} is not a sweep's CSV ({exc}); give another --out") from None
        if not lines or lines[0] != self.header:
            found = ",".join(lines[0]) if lines else "nothing"
            raise ValueError(f"--out: {str(self.path)!r} holds another table (columns {found}; this sweep "
                             f"writes {','.join(self.header)}); give another --out")
        if not text.endswith("\n"):
            lines = lines[:1] + lines[1:-1]  # the last line was cut (a crash inside its write): not finished
        kept = [lines[0]]
        for line in lines[1:]:
            if len(line) == len(self.header) and line[0].isdigit():  # a line cut short by a crash is dropped
                kept.append(line)
                self.done[int(line[0])] = dict(zip(self.header, line))
        if len(kept) != len(lines) or not text.endswith("\n"):
            self._write(kept)

    def _write(self, lines):
        from massspring.io.files import atomic_output

        out = io.StringIO()
        csv.writer(out).writerows(lines)
        try:
            with atomic_output(self.path) as fh:
                fh.write(out.getvalue().encode())
        except OSError as exc:
            raise ValueError(f"--out: cannot write {str(self.path)!r}: {exc.strerror or exc}") from None

    def check(self, cases, setup):
        """Refuse (ValueError) a CSV holding a case this sweep does not have, or has with
        other values or another ``setup``: resuming it would mix two sweeps' rows (and
        overwrite their ``--states`` files). Returns the finished cases' rows."""
        numbers = {case.number: case for case in cases}
        for number, line in self.done.items():
            case = numbers.get(number)
            values = tuple(line[key] for key in self.keys)
            if case is not None and case.texts == values and line[SETUP] == setup:
                continue
            written = " ".join(f"{k}={v}" for k, v in zip(self.keys, values))
            if case is None:
                now = f"this sweep has {len(cases)} case(s)"
            elif case.texts != values:
                now = f"this sweep's case {number} is {case.label()}"
            else:
                now = f"this sweep runs it with {setup}"
            ran = f" with {line[SETUP]}" if case is not None and case.texts == values else ""
            raise ValueError(f"--out: {str(self.path)!r} holds case {number} ({written}){ran}, but {now}; give "
                             "another --out, or the --vary values and options of the sweep that wrote it")
        return {number: line for number, line in self.done.items()}

    def close(self):
        """Let another sweep write the CSV: its lock file removed (while still held, so
        that a sweep waiting on it finds it gone and makes its own: ``_lock``), then
        released."""
        if self.lock is not None:
            try:
                os.unlink(_lock_path(self.path))
            except OSError:
                pass
            os.close(self.lock)
            self.lock = None

    def append(self, case, row, setup):
        out = io.StringIO()
        csv.writer(out).writerow([case.number, *case.texts, *(_cell(row[k]) for k in COLUMNS), setup])
        try:
            with open(self.path, "a", newline="") as fh:
                fh.write(out.getvalue())
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            raise ValueError(f"--out: cannot append case {case.number} to {str(self.path)!r}: "
                             f"{exc.strerror or exc}") from None


def resumable(out, keys, cases, setup) -> int:
    """How many of ``cases`` the CSV ``out`` already holds (0 when there is none); raises
    ValueError as ``Results`` and ``Results.check`` do when this sweep cannot resume it."""
    if not Path(out).exists():
        return 0
    results = Results(out, keys)
    try:
        return len(results.check(cases, setup))
    finally:
        results.close()


def _lock(path):
    """An exclusive lock (``fcntl.flock``) on ``path``'s hidden sidecar ``.NAME.lock``,
    held until ``Results.close``: a second sweep on the same CSV is refused at once
    instead of writing every case twice. Returns the lock's file descriptor."""
    import fcntl

    lock = _lock_path(path)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise ValueError(f"--out: {str(path)!r} is being written by another sweep (it holds {lock.name}); "
                             "wait for it to end or give another --out") from None
        try:  # the file locked is still the one at that name (a closing sweep removes it before releasing it)
            if os.stat(lock).st_ino == os.fstat(fd).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


def _lock_path(path):
    return Path(path).with_name(f".{Path(path).name}.lock")


def _cell(value):
    return repr(float(value)) if isinstance(value, (float, np.floating)) else str(value)


def sweep(scene, vary, *, integrator=None, dt=None, duration=None, steps=None, out=None, states=None,
          client=None, options=None, confirm=False, progress=None):
    """Run every combination of ``vary`` ({key: [values]}) on ``scene`` (a Scene or a
    built-in scene's name) and return the rows in case order.

    ``integrator``, ``dt``, ``options`` (Simulation arguments such as cg_tol, or tol for
    error-controlled runs): for every case, unless varied (``tol`` may be varied: a
    ladder of tolerances). ``duration`` (s) or ``steps``: each run's length (default: the
    scene's duration; an error-controlled case runs for a duration, ending on it
    exactly, its ``steps`` column the steps it chose; a scene's own tol gives way to
    ``steps``, ``dt``, cg_tol and newton_tol, as in ``Scene.simulation``). ``out``: the CSV (a row appended as each case finishes; cases
    already in it are skipped and their rows returned as read; one holding a case with
    another number, values or setup is refused, ``Results.check``). ``states``: a directory
    for each case's final state (``case0001.npz``...). ``client``: a
    ``dask.distributed.Client`` (None: in this process). ``progress(case, row)`` is
    called as each case finishes."""
    from massspring.io.files import atomic_output, check_writable
    from massspring.scene import load_scene

    if isinstance(scene, str):
        scene = load_scene(scene)
    cases = plan(scene, vary, integrator=integrator, confirm=confirm)
    if steps is not None:
        steps = validate.count("steps", steps)
    if duration is not None:
        duration = validate.positive_float("duration", duration)
    if dt is not None:
        dt = validate.positive_float("dt", dt)
    adaptive = (options or {}).get("tol") is not None or "tol" in vary
    if adaptive and steps is not None:
        raise ValueError("steps: an error-controlled sweep (tol) is measured in time; give duration")
    for name in ("newton_tol", "cg_tol"):
        if "tol" in vary and (options or {}).get(name) is not None:
            raise ValueError(f"{name}: an error-controlled run (tol) derives it from tol; give one or the other")
    if duration is not None and not adaptive:
        check_duration(scene, cases, duration, integrator, dt)
    if states is not None:
        states = Path(states)
        if not states.is_dir():
            raise ValueError(f"--states: {str(states)!r} is not a directory")
        check_writable(states / "case0001.npz", "--states")
    setup = setup_text(scene, integrator, dt, duration, steps, options)
    results = None
    if out is not None:
        check_writable(out, "--out", (".csv",))
        results = Results(out, list(vary))
    try:
        previous = results.check(cases, setup) if results else {}
    except BaseException:
        results.close()
        raise
    todo = [case for case in cases if case.number not in previous]
    rows = {number: _typed(line) for number, line in previous.items()}
    keep = states is not None

    def finished(index, result):
        case = todo[index]
        if isinstance(result, Exception):  # a worker that kept dying
            row, state = {"status": "failed", "message": f"{type(result).__name__}: {result}",
                          **{k: "" for k in NUMBERS}}, None
        else:
            row, state = result
        if results:
            results.append(case, row, setup)  # the row first: a state that cannot be written loses nothing
        rows[case.number] = {"case": case.number, **dict(case.values), **row}
        if state is not None:
            name = states / f"case{case.number:04d}.npz"
            try:
                with atomic_output(name) as fh:
                    fh.write(state)
            except OSError as exc:
                raise ValueError(f"--states: cannot write {str(name)!r}: {exc.strerror or exc}; the CSV holds "
                                 f"case {case.number}'s row") from None
        if progress:
            progress(case, row)

    tasks = [(scene, case, integrator, dt, duration, steps, options, keep) for case in todo]
    try:
        cluster.run_tasks(run_case, tasks, client=client, on_result=finished, keep_lost=True)
    finally:
        if results:
            results.close()
    return [rows[case.number] for case in cases]


def format_table(rows, keys) -> str:
    """The rows as an aligned text table: the varied keys, status and figures."""
    columns = ["case", *keys, "status", "steps", "time", "wall_s", "energy", "max_strain", "cg_iterations"]
    cells = [columns] + [[value_text(row[c]) if c in keys or isinstance(row[c], str) else f"{row[c]:.4g}"
                          for c in columns] for row in rows]
    widths = [max(len(line[i]) for line in cells) for i in range(len(columns))]
    lines = ["  ".join(cell.rjust(w) for cell, w in zip(line, widths)) for line in cells]
    notes = [f"case {row['case']}: {row['message']}" for row in rows if row["message"]]
    return "\n".join(lines + notes)


def _typed(line):
    """A row read back from the CSV with its figures as numbers (varied values as text)."""
    row = dict(line)
    row["case"] = int(row["case"])
    for key in NUMBERS:
        if row.get(key, "") != "":
            row[key] = float(row[key])
    return row


def plot(rows, keys, metric, path, title=""):
    """Draw ``metric`` against the first varied key (a line per value of the second, if
    any) to ``path``; diverged and failed cases are red crosses at the foot of the axes.
    An axis whose values span a decade or more (``spans_decades``) is logarithmic."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from massspring.io.files import atomic_path

    first, second = keys[0], (keys[1] if len(keys) > 1 else None)
    xs = list(dict.fromkeys(value_text(r[first]) for r in rows))
    numeric = all(_is_number(r[first]) for r in rows)
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    groups = list(dict.fromkeys(value_text(r[second]) for r in rows)) if second else [None]
    for group in groups:
        chosen = [r for r in rows if second is None or value_text(r[second]) == group]
        ok = [r for r in chosen if r["status"] == "ok" and r[metric] != ""]
        x = [float(r[first]) if numeric else xs.index(value_text(r[first])) for r in ok]
        order = np.argsort(x)
        label = f"{second} = {group}" if second else None
        ax.plot(np.array(x)[order], np.array([float(r[metric]) for r in ok])[order], "o-", label=label)
        bad = [r for r in chosen if r["status"] != "ok"]
        ax.plot([float(r[first]) if numeric else xs.index(value_text(r[first])) for r in bad], [0.02] * len(bad),
                "x", color="red", markersize=9, transform=ax.get_xaxis_transform(), clip_on=False)
    if numeric and spans_decades([float(r[first]) for r in rows]):
        ax.set_xscale("log")
    if spans_decades([float(r[metric]) for r in rows if r["status"] == "ok" and r[metric] != ""]):
        ax.set_yscale("log")
    if not numeric:
        ax.set_xticks(range(len(xs)), xs)
    ax.set_xlabel(first)
    ax.set_ylabel(f"{metric} ({UNITS[metric]})" if metric in UNITS else metric)
    ax.set_title(title + ("  (x: diverged or failed)" if any(r["status"] != "ok" for r in rows) else ""))
    if second:
        ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path


def spans_decades(values) -> bool:
    """Whether ``values`` (numbers) are all > 0 and the largest is at least 10 times the
    smallest: a plot's axis for them is then logarithmic."""
    values = [float(v) for v in values]
    return len(values) > 1 and min(values) > 0 and max(values) / min(values) >= 10


def _plain(values):
    """A sweep's values for one key as Python objects: a numpy array becomes its list, a
    numpy scalar its Python number, a numpy vector its list (anything else is left for
    ``plan`` to check)."""
    if isinstance(values, np.ndarray):
        values = values.tolist()
    if not isinstance(values, (list, tuple)):
        return values
    return [value.tolist() if isinstance(value, (np.ndarray, np.generic)) else value for value in values]


def _same_value(value):
    """What makes two varied values the same: numbers by value (1000 and 1e3), vectors of
    numbers by their components' values ([0, 0, -1] and [0, 0, -1.0]), the rest by their
    CSV text."""
    if _is_number(value) and not isinstance(value, (bool, str)):
        return ("number", float(value))
    if isinstance(value, (list, tuple)) and value and all(_is_number(v) and not isinstance(v, (bool, str))
                                                          for v in value):
        return ("vector", tuple(float(v) for v in value))
    return ("text", value_text(value))


def _is_number(value):
    """A number, or text that reads as one (values resumed from the CSV)."""
    try:
        float(value)
        return True
    except (TypeError, ValueError):
        return False
