"""Shared helpers of the tests: independent numpy references (forces, the dense
Jacobians and system of Eq. 15 with prescribed velocities), random test systems, and
the driver switch.

Nothing here uses the package's kernels or its algebraic shortcuts (the dense
right-hand side keeps the -dt D v term instead of cancelling it against the
damping force).

Two tiers: ``python -m pytest`` runs the fast tier (every module and public option,
sampled matrices); ``python -m pytest --all`` runs every case (every scene x integrator,
long runs, clusters, memory probes). CI runs ``--all``.

Which cases the fast tier runs is written at each test, nowhere else (``fast_tier``): a
case runs there unless it is marked ``full`` (``@FULL`` on a test, or ``marks=FULL`` on a
``pytest.param``, as ``sampled`` writes) or the test's ``fast_sample`` mark leaves it out:
``@pytest.mark.fast_sample(integrator=["symplectic", "implicit"], path=["serial"])``
keeps the cases whose parameters take one of the values named, for each parameter it
names (the others: every value). A parametrised test with neither runs every case in the
fast tier. A mark that names a parameter the test does not have, or a value none of its
cases takes, is an error (in both tiers). A case asked for by its node id runs even where
the mark leaves it out (of a test whose collected cases it leaves all out, the first).
Integrator lists are built from ``massspring.integrators.INTEGRATORS`` (filtered by the
capability a test needs), so a new integrator joins them by itself, in the full suite
(the marks name the integrators the fast tier runs).
"""

import math
import os
import resource

# Compiling kernels is most of the suite's time. Taichi's own IR optimisation passes
# off (set before Taichi starts, inherited by the tests' child processes) halve the
# compile time of the large serial kernels and leave LLVM's optimisation on; kernels
# then run 6-36% slower (benchmarks/compile_options.py). Users and the
# benchmarks run with it on; TI_ADVANCED_OPTIMIZATION=1 python -m pytest runs the tests so.
os.environ.setdefault("TI_ADVANCED_OPTIMIZATION", "0")
# Taichi's offline cache misses within a run (its key holds the numbers of the fields a
# kernel reads, which depend on what earlier tests allocated) and, written by two
# workers at once, prints "Lock ... failed" warnings into the stderr of the command-line
# tests, whose errors must be one line: off in the tests unless set.
os.environ.setdefault("TI_OFFLINE_CACHE", "0")

import numpy as np
import pytest

import massspring as ms
from massspring.device import reset_taichi

PEAK_RSS_LIMIT = 3e9  # bytes: in pytest's process, in each xdist worker and in any one child process
RESET_ABOVE = 2e9  # bytes resident after a test module: Taichi is then reset (its kernels and fields freed)
WORKER_RESET_ABOVE = 0.8e9  # the same in each of pytest-xdist's worker processes, whose peaks add up
TEST_RESET_ABOVE = 1.5e9  # bytes resident after a test of a module that sets RESET_BETWEEN_TESTS
WORKERS_MAX = 4  # -n auto (the default, pyproject's addopts): one worker per core, at most this many
ZERO_LENGTH = 1e-12  # f64 zero-length rule: such a spring has no direction or force (stiffness only if l0 = 0)

# Each integrator has two drivers running the same algorithm: serial kernels (one
# launch for a whole step or solve; chosen for systems below
# ``massspring.engine.simulation.SERIAL_BELOW`` springs, i.e. every system here) and
# parallel kernels (one launch per phase; large systems). Tests run both on small
# systems through Simulation's ``loops`` option.
PATHS = ("serial", "parallel")


def pytest_addoption(parser):
    parser.addoption("--all", action="store_true", default=False,
                     help="run the full suite (what CI runs): also the tests marked 'full'")


def pytest_configure(config):
    config.addinivalue_line("markers", "full: in the full suite only (python -m pytest --all), not the fast tier")
    config.addinivalue_line("markers", "fast_sample(**values): the parameter values of the cases the fast tier runs")


def fast_tier(items):
    """The items of the fast tier: none marked ``full``, and of a test with a ``fast_sample``
    mark (``@pytest.mark.fast_sample(integrator=["implicit"])``) only the cases whose
    parameters take the values it names, or, where it leaves out every case collected (a
    case chosen by its node id), the first. Raises ``pytest.UsageError`` for a mark naming
    a parameter its test does not have or a value none of its cases takes."""
    by_function = {}
    for item in items:
        by_function.setdefault(getattr(item, "function", item), []).append(item)
    keep = set()
    for cases in by_function.values():
        mark = cases[0].get_closest_marker("fast_sample")
        sample = check_fast_sample(mark, cases) if mark else {}
        open_cases = [item for item in cases if not item.get_closest_marker("full")]
        chosen = [item for item in open_cases
                  if all(params(item)[name] in values for name, values in sample.items())]
        keep.update(id(item) for item in chosen or open_cases[:1])
    return [item for item in items if id(item) in keep]


def params(item):
    return getattr(getattr(item, "callspec", None), "params", {})


def check_fast_sample(mark, cases):
    """The mark's {parameter: values}, each parameter one of the test's and each value one
    of its cases takes (of all its cases, whichever ``-k`` or node ids select)."""
    where = cases[0].nodeid.split("[")[0]
    if mark.args or not mark.kwargs:
        raise pytest.UsageError(f"{where}: fast_sample takes parameter=[values] only")
    for name, values in mark.kwargs.items():
        taken = parametrised_values(cases[0], name)
        if taken is None:  # not by a parametrize mark: the values of the cases collected
            taken = [params(item)[name] for item in cases if name in params(item)]
        if not taken:
            raise pytest.UsageError(f"{where}: fast_sample names {name!r}, which is not one of its parameters")
        if isinstance(values, str) or any(value not in taken for value in values):
            raise pytest.UsageError(f"{where}: fast_sample's {name}={values!r} is not a list of values its cases "
                                    f"take ({taken!r})")
    return mark.kwargs


def parametrised_values(item, name):
    """The values of the parameter ``name`` in ``item``'s function's parametrize marks, None if none has it."""
    for mark in item.iter_markers("parametrize"):
        names = mark.args[0] if mark.args else mark.kwargs["argnames"]
        names = [part.strip() for part in names.split(",")] if isinstance(names, str) else list(names)
        if name in names:
            cases = mark.args[1] if len(mark.args) > 1 else mark.kwargs["argvalues"]
            rows = [case.values if hasattr(case, "marks") else (case,) if len(names) == 1 else case for case in cases]
            return [row[names.index(name)] for row in rows]
    return None


# The test files of most CPU time in the full suite, most first (seconds summed from
# ``--durations=0`` on this 2-core machine); the two workers take them first (pyproject's
# ``--no-loadscope-reorder`` keeps this order), so that no heavy file starts last and
# leaves one worker running alone: xdist otherwise orders files by their number of tests.
HEAVY_FIRST = ("test_gradient.py", "test_gradient_contact.py", "test_self_collision.py", "test_scene_energy.py",
               "test_cli.py", "test_adaptive.py", "test_multigrid.py", "test_contact.py", "test_uniform_terms.py",
               "test_exact.py", "test_stability.py", "test_device.py", "test_render.py", "test_sweep.py",
               "test_newton.py", "test_multigrid_f32.py")


def heavy_first(items):
    """``items`` with the files of ``HEAVY_FIRST`` first, in its order (the rest after, as
    collected; each file's tests in their own order)."""
    rank = {name: k for k, name in enumerate(HEAVY_FIRST)}
    return sorted(items, key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_collection_modifyitems(config, items):
    """Without ``--all``, the fast tier (``fast_tier``); the rest deselected. The
    ``fast_sample`` marks are checked in both tiers. The heavy files first
    (``heavy_first``)."""
    keep = fast_tier(items)
    if config.getoption("--all"):
        items[:] = heavy_first(items)
        return
    if len(keep) < len(items):
        kept = set(map(id, keep))
        config.hook.pytest_deselected(items=[item for item in items if id(item) not in kept])
    items[:] = heavy_first(keep)


FULL = pytest.mark.full


@pytest.fixture(autouse=True)
def _no_progress_lines(monkeypatch):
    """No progress line in a test's own process: one comes every ``progress.INTERVAL``
    (5 s) of a run, and a run that compiles for that long on a loaded machine added one
    to the stderr a test checks for a one-line error. tests/test_progress.py sets its
    own interval."""
    from massspring.support import progress

    monkeypatch.setattr(progress, "INTERVAL", 3600.0)


def sampled(cases, fast):
    """``cases`` (tuples or values) as pytest params, those not in ``fast`` marked ``full``:
    the fast tier runs a sample of a matrix, the full suite all of it."""
    fast = set(fast)
    out = []
    for case in cases:
        values = case.values if hasattr(case, "values") else case if isinstance(case, tuple) else (case,)
        marks = list(case.marks) if hasattr(case, "marks") else []
        key = values if len(values) > 1 else values[0]
        out.append(pytest.param(*values, marks=marks if key in fast else [*marks, FULL], id=getattr(case, "id", None)))
    return out


def one_line_error(capsys, *words):
    """The CLI's stderr after an error: one line, no traceback, holding each of ``words``."""
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, (word, err)
    return err


def simulation(model, path, **kw):
    """A Simulation whose integrator uses the ``path`` driver."""
    sim = ms.Simulation(model, loops=path, **kw)
    assert sim.loops == path
    return sim


def random_system(seed, n=None, rest=(0.6, 1.4), n_fixed=None, gravity=(0.0, 0.0, -9.81), **extra):
    """A random 3D system: n in 6..12 particles, about 2n random distinct springs with
    rest lengths ``rest`` x their current length (< 1 stretched, > 1 compressed),
    random ks, kd > 0, masses and velocities, 1-2 fixed particles; ``extra`` Model
    arguments are passed on."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(6, 13)) if n is None else n
    x = rng.uniform(-1.0, 1.0, size=(n, 3))
    pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)])
    springs = pairs[rng.choice(len(pairs), size=min(2 * n, len(pairs)), replace=False)]
    springs = np.where(rng.random((len(springs), 1)) < 0.5, springs, springs[:, ::-1])  # both orders
    length = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1)
    k = len(springs)
    n_fixed = int(rng.integers(1, 3)) if n_fixed is None else n_fixed
    return ms.Model(
        x, springs,
        masses=rng.uniform(0.5, 2.0, n),
        stiffness=rng.uniform(50.0, 500.0, k),
        damping=rng.uniform(0.5, 5.0, k),
        rest_lengths=length * rng.uniform(rest[0], rest[1], k),
        velocities=rng.normal(size=(n, 3)),
        gravity=gravity,
        fixed=rng.choice(n, size=n_fixed, replace=False),
        **extra,
    )


def spring_geometry(x, i, j):
    d = x[j] - x[i]
    length = np.linalg.norm(d)
    if length <= ZERO_LENGTH:
        return None, length
    return d / length, length


def numpy_forces(model, x, v, magnitude=False, damping_at=None):
    """Total force (n, 3) of Eq. 1-3: spring + damping + gravity, plus air drag
    -drag (v - wind). With ``magnitude``, also the per-particle sum of the terms'
    absolute values (n,) (the scale of the round-off in summing them). With
    ``damping_at`` (positions (n, 3)), spring damping acts along the springs'
    directions there (the Newton-solved steps' lagged damping: ``predicted``)."""
    air = -model.drag * (v - model.wind[None, :])
    f = model.masses[:, None] * model.gravity[None, :] + air
    mag = model.masses * np.linalg.norm(model.gravity) + np.linalg.norm(air, axis=1)
    for s, (i, j) in enumerate(model.springs):
        nvec, length = spring_geometry(x, i, j)
        mvec = nvec if damping_at is None else spring_geometry(damping_at, i, j)[0]
        fs = np.zeros(3) if nvec is None else model.stiffness[s] * (length - model.rest_lengths[s]) * nvec
        fd = np.zeros(3) if mvec is None else model.damping[s] * np.dot(v[j] - v[i], mvec) * mvec
        f[i] += fs + fd
        f[j] -= fs + fd
        size = np.linalg.norm(fs) + np.linalg.norm(fd)
        mag[i] += size
        mag[j] += size
    return (f, mag) if magnitude else f


def predicted(model, x, v, ahead):
    """x + ahead v, pins moving with their pin velocity: where the Newton-solved steps take
    spring damping's directions (``kernels/newton.py``, ``lagged_directions``)."""
    out = x + ahead * v
    out[model.fixed] = x[model.fixed] + ahead * model.pin_velocity
    return out


def dense_jacobians(model, x, definiteness_fix):
    """K = df/dx (Eq. 13, damping's x-derivative ignored) and D = df/dv (Eq. 14, plus
    -drag I from air drag), 3n x 3n.

    K_ii = ks ((l0/l - 1) I - (l0/l) n n^T) = ks (c I - (1 + c) n n^T), c = l0/l - 1
    (-ks I for l0 = 0, also at l = 0); the definiteness fix uses min(c, 0) for c, i.e. drops the transverse part
    c (I - n n^T) of compressed springs and keeps the axial part -ks n n^T.
    """
    n = model.n_particles
    K = np.zeros((3 * n, 3 * n))
    D = -model.drag * np.eye(3 * n)
    eye = np.eye(3)
    for s, (i, j) in enumerate(model.springs):
        nvec, length = spring_geometry(x, i, j)
        l0, ks, kd = model.rest_lengths[s], model.stiffness[s], model.damping[s]
        if nvec is None and l0 > 0:
            continue
        nn = np.zeros((3, 3)) if nvec is None else np.outer(nvec, nvec)
        if l0 == 0:  # f_i = ks (x_j - x_i): K_ii = -ks I, with a direction or without
            kb = -ks * eye
        elif definiteness_fix:
            c = min(l0 / length - 1.0, 0.0)
            kb = ks * (c * eye - (1.0 + c) * nn)
        else:
            kb = ks * ((l0 / length - 1.0) * eye - (l0 / length) * nn)  # Eq. 13 as written
        db = -kd * nn
        for blocks, sign in (((i, i), 1), ((j, j), 1), ((i, j), -1), ((j, i), -1)):
            a, b = blocks
            K[3 * a:3 * a + 3, 3 * b:3 * b + 3] += sign * kb
            D[3 * a:3 * a + 3, 3 * b:3 * b + 3] += sign * db
    return K, D


def free_dofs(model):
    return np.repeat(model.free_mask(), 3)


def prescribed_dofs(model, prescribed=None):
    """(mask (3n,) of the degrees of freedom whose velocity is prescribed, those velocities
    (3n,), 0 elsewhere): the pinned particles' (their pin velocities), and the entries
    of ``prescribed`` ({degree of freedom 3 i + axis: velocity in m/s})."""
    mask = ~free_dofs(model)
    values = np.zeros(3 * model.n_particles)
    values.reshape(-1, 3)[model.fixed] = model.pin_velocity
    for dof, value in (prescribed or {}).items():
        mask[dof] = True
        values[dof] = value
    return mask, values


def dense_matrices(model, dt, definiteness_fix, x=None, v=None):
    """The whole (A, b) of Eq. 15, 3n x 3n and 3n, at the state (x, v) (default: the model's)."""
    x = model.positions if x is None else x
    v = model.velocities if v is None else v
    K, D = dense_jacobians(model, x, definiteness_fix)
    M = np.diag(np.repeat(model.masses, 3))
    vf = v.reshape(-1)
    return M - dt * D - dt * dt * K, M @ vf + dt * numpy_forces(model, x, v).reshape(-1) - dt * D @ vf


def dense_system(model, dt, definiteness_fix, x=None, v=None, prescribed=None):
    """(A, b) of Eq. 15 restricted to the degrees of freedom whose velocity is not
    prescribed (``prescribed_dofs``), the prescribed velocities times their columns of
    A moved to the right-hand side: (A_uu, b_u - A_uc v_c)."""
    A, b = dense_matrices(model, dt, definiteness_fix, x, v)
    fixed, values = prescribed_dofs(model, prescribed)
    keep = ~fixed
    return A[np.ix_(keep, keep)], b[keep] - A[np.ix_(keep, fixed)] @ values[fixed]


def dense_step(model, dt, definiteness_fix, x=None, v=None, prescribed=None):
    """v' (n, 3) of Eq. 15 by a direct solve of ``dense_system``, the prescribed velocities
    in their degrees of freedom."""
    A, b = dense_system(model, dt, definiteness_fix, x, v, prescribed)
    fixed, values = prescribed_dofs(model, prescribed)
    out = values.copy()
    out[~fixed] = np.linalg.solve(A, b)
    return out.reshape(-1, 3)


def peak_rss():
    """(peak resident bytes of this process, of its largest child process so far)."""
    return tuple(resource.getrusage(who).ru_maxrss * 1024 for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))


def resident_bytes():
    """This process's resident memory now (bytes; its peak where /proc is missing)."""
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return peak_rss()[0]


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
    """After a module's last test (and its fixtures' teardown), Taichi is reset if this
    process holds more than ``RESET_ABOVE``: the kernels compiled for every configuration
    so far would otherwise stay in memory to the end. Below it, the next modules reuse them.
    A module whose tests share no Taichi objects and compile a configuration each (it sets
    ``RESET_BETWEEN_TESTS = True``) is also reset after any test that leaves more than
    ``TEST_RESET_ABOVE`` (or the bytes it sets instead of True): test_cli.py's scene x
    integrator runs grew a worker by 13 MB a test, to 1.9 GB; test_gradient.py's adjoint
    kernels of every integrator, contact and friction configuration to 1.54 GB."""
    yield
    limit = WORKER_RESET_ABOVE if os.environ.get("PYTEST_XDIST_WORKER") else RESET_ABOVE
    if nextitem is not None and nextitem.module is item.module:  # within a module
        between = getattr(item.module, "RESET_BETWEEN_TESTS", False)
        if between is True:
            limit = max(limit, TEST_RESET_ABOVE)
        elif between:  # a module's own threshold (bytes)
            limit = max(limit, between)
        else:
            limit = math.inf
    if resident_bytes() > limit:
        reset_taichi()


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker process per core, at most ``WORKERS_MAX`` (each compiles
    its own kernels and holds its own Taichi memory)."""
    return max(1, min(os.cpu_count() or 1, WORKERS_MAX))


WORKER_PEAKS = []  # (own, largest child) peak bytes of each finished xdist worker


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    WORKER_PEAKS.append(getattr(node, "workeroutput", {}).get("peak_rss", (0, 0)))


def suite_peaks():
    """(peak bytes of pytest and its workers added up: a bound on the suite's peak, of the
    largest single process: pytest's, a worker's or any child's)."""
    own, child = peak_rss()
    largest = max([own, child, *(peak for pair in WORKER_PEAKS for peak in pair)])
    return own + sum(peak[0] for peak in WORKER_PEAKS), largest


def pytest_sessionfinish(session, exitstatus):
    """A suite one of whose processes passed ``PEAK_RSS_LIMIT`` fails, whatever its tests
    said (an xdist worker hands its peaks to the controller)."""
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:
        workeroutput["peak_rss"] = peak_rss()
    elif suite_peaks()[1] > PEAK_RSS_LIMIT and session.exitstatus == 0:
        session.exitstatus = 1


def pytest_terminal_summary(terminalreporter, config):
    left = len(terminalreporter.stats.get("deselected", []))
    if not config.getoption("--all") and left:
        terminalreporter.write_line(f"fast tier: {left} tests of the full suite not run (python -m pytest --all runs "
                                    f"everything)")
    total, largest = suite_peaks()
    over = largest > PEAK_RSS_LIMIT
    workers = f" and its {len(WORKER_PEAKS)} workers added up" if WORKER_PEAKS else ""
    terminalreporter.write_line(f"peak RSS: {total / 1e9:.2f} GB in pytest{workers}, {largest / 1e9:.2f} GB in the "
                                f"largest single process (limit {PEAK_RSS_LIMIT / 1e9:g} GB per process)"
                                f"{': OVER THE LIMIT' if over else ''}", red=over)
