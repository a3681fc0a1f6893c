"""The Taichi side of a simulation: one bundle of fields, its compile-time switches, the arch.

A :class:`Bundle` holds every field one simulation needs as attributes
(``dev.mass``, ``dev.x``, ``dev.coef``, ...) and is passed whole to the kernels as
a ``ti.template()``, with a :class:`Config` of compile-time switches (precision,
force terms, pins, preconditioner). A kernel is compiled once per (bundle, config).

Fields, not ndarrays: on this project's 2-core CPU the CG operator ran faster on
fields (Taichi indexes ndarrays with 32-bit arithmetic and a sign extension per
element, fields with 64-bit addresses and vector loads), as ``benchmarks/storage.py``
measures side by side. What fields cost is compilation: a kernel
compiles again for every new field tree. Two things keep that rare:

* capacity classes: fields are allocated for ``capacity(count)`` items, the next
  of 2^k or 3 * 2^(k-1) above a floor, and kernels loop to the real counts kept in
  ``dev.size``; every small model (up to 4096 particles and 16384 springs) shares
  one class;
* a pool: a closed simulation's bundle goes back to the pool and the next one
  with the same declarations takes it, with the kernels already compiled for it.
  A sweep of same-size runs (a study, a test suite) compiles once.

Declarations (:class:`Layout`) name each field, its dtype, element shape and
which count it follows ("particle", "spring", "entry" (2 per spring), "block" or
a fixed number); values (numpy) fill it at allocation, padded with zeros.
"""

import contextlib
import ctypes
import ctypes.util
import io
import os
import re
import subprocess
import sys
import tempfile
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import taichi as ti
from taichi.lang import impl

from massspring.support import memory
from massspring.kernels.blocks import BLOCK
from massspring.kernels.fill import fill
from massspring.model.colliders import collider_arrays, collider_groups
from massspring.model.terms import active_terms

REAL = {"f32": ti.f32, "f64": ti.f64}
_NUMPY = {ti.f32: np.float32, ti.f64: np.float64, ti.i32: np.int32, ti.i64: np.int64}
ARCHS = ("cpu", "gpu", "cuda", "vulkan", "metal", "opengl", "x64", "arm64")
CPU_ARCHS = ("cpu", "x64", "arm64")
PARTICLE_FLOOR = 4096   # smallest particle capacity
SPRING_FLOOR = 16384    # smallest spring capacity
POOL_BUDGET = 1 << 30   # bytes of idle bundles kept for reuse


def ensure_taichi(arch="cpu", name="arch"):
    """Start Taichi once per process on ``arch``; later calls must name the same arch.

    An arch other than the CPU is first tried in a child process: Taichi falls back
    to the CPU when a device is missing, and crashes outright for some (OpenGL
    without a display). Either way this raises ValueError starting with ``name`` and
    saying what is missing.
    """
    if arch not in ARCHS:
        raise ValueError(f"{name}: unknown value {arch!r}, expected one of {', '.join(ARCHS)}")
    if impl.get_runtime().prog is None:
        if arch not in CPU_ARCHS:
            _probe(arch, name)
        with tempfile.TemporaryFile() as log:
            try:
                with contextlib.redirect_stdout(io.StringIO()), _stderr_to(log), _floating_point_kept():
                    ti.init(arch=getattr(ti, "cpu" if arch == "cpu" else arch), default_fp=ti.f64,
                            log_level=ti.ERROR if arch not in CPU_ARCHS else ti.WARN)
            except RuntimeError as exc:  # e.g. its memory pool under a low ulimit -v; its own log line dropped
                reason = str(exc).split("] ", 1)[-1].strip()
                raise ValueError(f"{name}: Taichi could not start on {arch!r}: {reason} (it reserves about "
                                 f"{memory.TAICHI_RESERVE / 1e9:.1f} GB of address space; see ulimit -v)") from None
            log.seek(0)
            sys.stderr.write(log.read().decode(errors="replace"))  # a start's warnings, as they were
    current = impl.current_cfg().arch
    if arch in CPU_ARCHS:
        accepted = (ti.x64, ti.arm64) if arch == "cpu" else (getattr(ti, arch),)
    else:
        accepted = tuple(ti.gpu) if arch == "gpu" else (getattr(ti, arch),)
    if current not in accepted:
        raise ValueError(f"{name}: Taichi already runs on {current.name} in this process; cannot switch to {arch!r}")


@contextlib.contextmanager
def _floating_point_kept():
    """The calling thread's floating-point environment as it was before the block.
    ``ti.init`` turns on flush-to-zero and denormals-are-zero in it, after which Python
    itself reads ``float("1e-320")`` as 0.0: input would parse and validate one way
    before the first simulation and another after it. Taichi's kernels do not set the
    mode again (they compute as before on its worker threads; measured: the mode stays
    restored through later launches). Through C99's ``fegetenv``/``fesetenv`` where the
    C library has them; elsewhere the mode is left as Taichi sets it."""
    env, libm = None, _libm()
    if libm is not None:
        env = ctypes.create_string_buffer(1024)  # larger than any platform's fenv_t
        if libm.fegetenv(env) != 0:
            env = None
    try:
        yield
    finally:
        if env is not None:
            libm.fesetenv(env)


def _libm():
    """The C math library (``ctypes.CDLL``) if it has ``fegetenv`` and ``fesetenv``, else None."""
    name = ctypes.util.find_library("m") or ctypes.util.find_library("c")
    try:
        lib = ctypes.CDLL(name)
        lib.fegetenv, lib.fesetenv  # noqa: B018 (looked up: AttributeError where missing)
    except (OSError, AttributeError, TypeError):
        return None
    return lib


@contextlib.contextmanager
def _stderr_to(file):
    """File descriptor 2 (where Taichi's C++ logs) into ``file`` for the block."""
    sys.stderr.flush()
    saved = os.dup(2)
    os.dup2(file.fileno(), 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _probe(arch, name):
    script = ("import taichi as ti\nfrom taichi.lang import impl\n"
              f"ti.init(arch=ti.{arch})\nprint('STARTED', impl.current_cfg().arch.name)\n")
    try:
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        raise ValueError(f"{name}: {arch!r} did not start within 120 s") from None
    started = re.search(r"STARTED (\w+)", proc.stdout)
    # Taichi's warnings, less its own "Arch=[...] is not supported, falling back to CPU"
    warnings = [line.split("] ", 2)[-1].strip().rstrip(".") for line in proc.stderr.splitlines()
                if line.startswith("[W") and "falling back" not in line]
    reason = "; ".join(warnings)
    if proc.returncode < 0 or not started:
        raise ValueError(f"{name}: {arch!r} is not available here: Taichi crashed while starting it (exit "
                         f"{proc.returncode}); {reason or 'no usable driver or display'}")
    if started.group(1) in ("x64", "arm64"):
        raise ValueError(f"{name}: {arch!r} is not available here ({reason or 'no such device'}); "
                         f"use {name} cpu")


def capacity(count, floor):
    """The capacity class of ``count`` items: the smallest 2^k or 3 * 2^(k-1) >= max(count, floor)."""
    need = max(int(count), int(floor), 1)
    k = max(need - 1, 1).bit_length()  # 2^k >= need
    return 3 << (k - 2) if k >= 2 and 3 << (k - 2) >= need else 1 << k


@dataclass(frozen=True)
class Config:
    """Compile-time switches of a simulation's kernels (hashed by value: equal
    configs share compiled kernels).

    real: ti.f32 or ti.f64; spring_terms, particle_terms: the kernel classes
    (``kernels.terms``) of the active force terms (``terms.active_terms``); fixed:
    whether any particle is pinned; fix: the definiteness fix (implicit); precond: a
    pointwise preconditioner class of ``kernels.preconditioners`` or None; colliders: (kind, count, first) of each
    collider kind present (``colliders.collider_groups``); moving_pins: whether
    some pin has a velocity; contact_filter: whether contacts are constraints of the
    implicit solve (``kernels/constraints.py``); self_pairs: whether self-collision
    pairs are penalties of the implicit solve (``kernels/pair_penalty.py``); lagged:
    whether the rate-dependent spring terms (damping) act along each spring's direction
    at the step's prediction, a second direction in the operator's blocks (the
    Newton-solved steps, ``kernels/newton.py``).
    """

    real: object
    spring_terms: tuple
    particle_terms: tuple
    fixed: bool
    fix: bool = True
    precond: object = None
    colliders: tuple = ()
    moving_pins: bool = False
    contact_filter: bool = False
    self_pairs: bool = False
    lagged: bool = False

    @property
    def has_springs(self):
        """Whether the model has springs (and so the adjacency fields)."""
        return len(self.spring_terms) > 0

    @property
    def rate_stiffness(self):
        """Whether a spring term's force turns with its spring through the rates (damping:
        an x-derivative the operator leaves out, ``rate_stiffness_adjoint``; the
        Newton-solved steps hold it along a predicted direction, ``lagged``)."""
        return any(term.rate_dependent for term in self.spring_terms)

    @property
    def pointwise(self):
        """Whether the CG kernels apply a pointwise preconditioner themselves."""
        return self.precond is not None

    @property
    def needs_diagonal(self):
        """Whether the operator's refresh must form the diagonal blocks for the preconditioner."""
        return self.precond is not None and self.precond.needs_diagonal

    @property
    def uniform_terms(self):
        """The particle terms that are uniform accelerations (``kernels.terms.uniform_acceleration``)."""
        return tuple(term for term in self.particle_terms if term.uniform)

    @property
    def has_uniform(self):
        """Whether a uniform acceleration acts (gravity, or any other ``uniform`` term)."""
        return len(self.uniform_terms) > 0

    @property
    def has_colliders(self):
        return len(self.colliders) > 0

    @property
    def collider_count(self):
        """The number of colliders, all kinds."""
        return sum(count for _, count, _ in self.colliders)

    @property
    def collider_order(self):
        """(kind, k, index) of every collider in the order the contact response meets them
        (``index`` among all kinds); ``collider_order_back``: the same backwards."""
        return tuple((kind, k, first + k) for kind, count, first in self.colliders for k in range(count))

    @property
    def collider_order_back(self):
        return self.collider_order[::-1]

    @classmethod
    def of(cls, model, precision, **switches):
        terms = active_terms(model)
        return cls(REAL[precision], tuple(t.kernel for t in terms if t.kind == "spring"),
                   tuple(t.kernel for t in terms if t.kind == "particle"), model.has_fixed,
                   colliders=collider_groups(model), moving_pins=model.has_moving_pins, **switches)


@ti.data_oriented
class State:
    """Positions ``x`` (m) and velocities ``v`` (m/s): (capacity,) vec3 fields."""

    def __init__(self, x, v):
        self.x = x
        self.v = v


@ti.data_oriented
class Bundle:
    """The fields of one simulation, as attributes named by their declarations.

    ``state`` is the (x, v) pair; ``states`` maps each declared pair's name to its
    :class:`State`. ``n``, ``m``: particle and spring counts (the fields hold
    ``capacity`` items; ``dev.size`` = (n, m) tells the kernels). ``compiled``: keys
    of optional kernels a run has compiled for this bundle (it stays with the bundle in
    the pool, so the next run of the same kind may launch them at no compile cost).
    """

    def __init__(self, fields, pairs):
        self.compiled = set()
        for name, field in fields.items():
            setattr(self, name, field)
        self.states = {name: State(fields[x], fields[v]) for name, (x, v) in pairs.items()}
        self.state = self.states.get("state")
        self.n = self.m = 0

    def read(self, name, count=None):
        """A numpy copy of field ``name`` cut to its real length (particles by default)."""
        return getattr(self, name).to_numpy()[: self.n if count is None else count]


class Layout:
    """Declarations of a bundle's fields; ``allocate`` makes (or reuses) and fills them."""

    def __init__(self, n, m, real):
        self.n, self.m, self.real = int(n), int(m), real
        self.counts = {"particle": capacity(n, PARTICLE_FLOOR), "spring": capacity(m, SPRING_FLOOR)}
        self.counts["entry"] = 2 * self.counts["spring"]
        self.counts["block"] = -(-self.counts["particle"] // BLOCK)  # kernels/blocks.py's sums
        self.decls = OrderedDict()
        self.pairs = {}

    def add(self, name, dtype, per, element=(), values=None):
        """Declare field ``name``: ``per`` items ("particle", "spring", "entry", "block",
        or an int; () for one item) of ``element``-shaped ``dtype`` values."""
        if name in self.decls:
            raise ValueError(f"field {name!r} declared twice")
        shape = () if per == () else (self.counts[per] if isinstance(per, str) else int(per),)
        self.decls[name] = (dtype, shape, tuple(element), values)

    def vectors(self, name, dtype, per="particle", values=None, k=3):
        self.add(name, dtype, per, (k,), values)

    def state(self, name, dtype, positions=None, velocities=None):
        """Declare a state pair: fields ``x``/``v`` for "state", else ``x_<name>``/``v_<name>``."""
        x, v = ("x", "v") if name == "state" else (f"x_{name}", f"v_{name}")
        self.vectors(x, dtype, values=positions)
        self.vectors(v, dtype, values=velocities)
        self.pairs[name] = (x, v)

    def signature(self):
        return tuple((name, dtype, shape, element) for name, (dtype, shape, element, _) in self.decls.items()) + \
            tuple(sorted(self.pairs.items()))

    def nbytes(self):
        return sum(int(np.prod(shape + element)) * np.dtype(_NUMPY[dtype]).itemsize
                   for dtype, shape, element, _ in self.decls.values())

    def allocate(self, what=None) -> "Bundle":
        """The bundle: taken from the pool if one has these declarations, else new; filled.
        A new one that would not fit in the memory available is refused (ValueError
        starting with ``what``, by default the model's counts)."""
        signature = self.signature()
        bundle = POOL.take(signature)
        reused = bundle is not None
        if not reused:
            what = what or f"model: {self.n:,} particles and {self.m:,} springs; the fields of this run"
            memory.check(self.nbytes(), what)
            builder = ti.FieldsBuilder()
            fields = {name: _place(builder, dtype, shape, element)
                      for name, (dtype, shape, element, _) in self.decls.items()}
            tree = builder.finalize()
            bundle = Bundle(fields, self.pairs)
            bundle._tree, bundle._signature, bundle._nbytes = tree, signature, self.nbytes()
            bundle._program = impl.get_runtime().prog
        plan, reals, ints, where = self._fill_plan()
        fill(bundle, plan, reals, ints, where)
        bundle.n, bundle.m = self.n, self.m
        return bundle


    def _fill_plan(self):
        """What ``kernels.fill`` takes for this layout: a plan and three buffers (float64
        and int32 values, int64 counts and offsets; numpy arrays passed as they are). The
        plan groups the fields with values by how many items they get (one loop each; 0-D
        fields apart) and says where in the last buffer each group's offsets start; per field: name, whether it is an integer field, its element shape
        and size. The counts and where each field's values start are in the last buffer,
        not the plan, so the kernel compiled for a bundle serves every model that reuses it.
        Items past the values (the capacity padding) are never read by a kernel, so they
        are left as they are."""
        groups, chunks, sizes = {}, ([], []), [0, 0]
        for name, (dtype, shape, element, values) in self.decls.items():
            if values is None:
                continue
            is_int = dtype == ti.i32
            values = np.asarray(values, dtype=np.int32 if is_int else np.float64)
            values = values.reshape((-1,) + element) if shape else values.reshape(element)
            entry = (name, is_int, element, int(np.prod(element, dtype=np.int64)))
            groups.setdefault(len(values) if shape else None, []).append((entry, sizes[is_int]))
            chunks[is_int].append(values.reshape(-1))
            sizes[is_int] += values.size
        buffers = [np.ascontiguousarray(np.concatenate(parts) if parts else np.zeros(1), dtype=dtype)
                   for parts, dtype in zip(chunks, (np.float64, np.int32))]
        starts = np.cumsum([len(groups)] + [len(entries) for entries in groups.values()]).tolist()
        plan = tuple((count is None, start, tuple(entry for entry, _ in entries))
                     for (count, entries), start in zip(groups.items(), starts))
        where = [count or 0 for count in groups] + [offset for entries in groups.values() for _, offset in entries]
        return plan, buffers[0], buffers[1], np.array(where, dtype=np.int64)


def _place(builder, dtype, shape, element):
    if not element:
        field = ti.field(dtype)
    elif len(element) == 1:
        field = ti.Vector.field(element[0], dtype)
    else:
        field = ti.Matrix.field(element[0], element[1], dtype)
    if shape:
        builder.dense(ti.i, shape).place(field)
    else:
        builder.place(field)
    return field


class Pool:
    """Idle bundles by declaration signature, at most ``budget`` bytes in all.

    It holds fields of the process's one Taichi runtime, so there is one pool per
    process (``POOL``); a bundle made before a ``reset_taichi`` (a Simulation closed or
    collected after it) is not taken back. Destroying a field tree makes Taichi recompile the kernels in
    use, so idle bundles are kept until the budget is exceeded, oldest out first.
    """

    def __init__(self, budget=POOL_BUDGET):
        self.budget = budget
        self._idle = OrderedDict()  # id -> bundle
        self.created = 0

    def take(self, signature):
        for key, bundle in self._idle.items():
            if bundle._signature == signature:
                del self._idle[key]
                return bundle
        self.created += 1
        return None

    def give(self, bundle):
        if bundle._program is not impl.get_runtime().prog:
            return  # made before a reset_taichi: its fields died with that runtime
        self._idle[id(bundle)] = bundle
        while sum(b._nbytes for b in self._idle.values()) > self.budget:
            _, old = self._idle.popitem(last=False)
            old._tree.destroy()

    def idle(self):
        return len(self._idle)

    def forget(self):
        """Drop every idle bundle without destroying its fields (for ``reset_taichi``)."""
        self._idle.clear()


POOL = Pool()


def read_verdict(result) -> tuple:
    """(code, kinetic J, bound J) as Python numbers from a kernel's ``divergence.verdict`` vector."""
    return int(result[0]), float(result[1]), float(result[2])


def reset_taichi():
    """Stop Taichi in this process (``ti.reset``), freeing every field and compiled kernel,
    and empty ``POOL``; the next Simulation starts it again (``ensure_taichi``). A
    Simulation still open becomes unusable. For long-lived processes that run unrelated
    batches (the test suite resets between test modules to bound its memory)."""
    POOL.forget()
    if impl.get_runtime().prog is not None:
        ti.reset()


def model_layout(model, precision) -> "Layout":
    """Declarations of a Model's fields: the state, masses, pins (and their velocities),
    colliders, adjacency, the force terms' arrays, the divergence check and block
    partial sums."""
    real = REAL[precision]
    n, m = model.n_particles, model.n_springs
    layout = Layout(n, m, real)
    layout.add("size", ti.i32, 2, values=np.array([n, m]))
    layout.state("state", real, model.positions, model.velocities)
    layout.add("mass", real, "particle", values=model.masses)
    if model.has_fixed:
        layout.add("free", ti.i32, "particle", values=model.free_mask())
    if model.has_moving_pins:
        pins = np.zeros((n, 3))
        pins[model.fixed] = model.pin_velocity
        layout.vectors("pin_velocity", real, values=pins)
    for name, (count, element, values) in collider_arrays(model).items():
        layout.add(name, real, count, element, values)
    if m:
        offsets, other, entry = adjacency(model)
        layout.vectors("ends", ti.i32, "spring", values=model.springs, k=2)
        layout.add("offsets", ti.i32, layout.counts["particle"] + 1, values=offsets)
        layout.add("other", ti.i32, "entry", values=other)
        layout.add("entry", ti.i32, "entry", values=entry)
        layout.vectors("fs", real, "spring")
    for term in active_terms(model):
        for name, (per, values) in term.arrays(model).items():
            if per == "vector":
                layout.vectors(name, real, (), values)
            else:
                layout.add(name, real, () if per == "scalar" else per, values=values)
    layout.vectors("check", ti.f64, ())
    layout.vectors("partial", ti.f64, "block")
    return layout


def adjacency(model):
    """Per-particle spring lists in CSR form, for gather kernels.

    Returns ``(offsets, other, entry)``: for particle ``i`` the entries
    ``offsets[i]:offsets[i+1]`` name the particle ``other[e]`` at the other end of
    each spring touching ``i``, and the spring as ``entry[e]`` = s if ``i`` is its
    first end, -1 - s if its second. Entries of a particle are in spring order.
    Shapes (n+1,), (2m,), (2m,), int32.
    """
    n, m = model.n_particles, model.n_springs
    ends = model.springs
    owner = np.concatenate([ends[:, 0], ends[:, 1]])
    other = np.concatenate([ends[:, 1], ends[:, 0]])
    entry = np.concatenate([np.arange(m), -1 - np.arange(m)])
    order = np.argsort(owner, kind="stable")
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(owner, minlength=n), out=offsets[1:])
    return offsets.astype(np.int32), other[order].astype(np.int32), entry[order].astype(np.int32)
