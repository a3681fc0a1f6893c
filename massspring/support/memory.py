"""How much memory a run needs, and how much this process may still take.

A run too large for the machine is refused before its model is built: the estimate
works from the particle and spring counts alone (a scene knows them before it
builds anything), and it is compared with the least of three limits:

* the memory the system has available (Linux ``MemAvailable``),
* the room left under the process's control group (cgroup v2 ``memory.max`` less
  ``memory.current``; v1 ``memory.limit_in_bytes`` less ``memory.usage_in_bytes``),
* the address space left under ``ulimit -v`` (``RLIMIT_AS`` less ``VmSize``; a
  Taichi runtime not yet started is counted for the address space it reserves).

The estimate is the peak resident memory a run adds to the process, model building
included, per particle and per spring, for each kind of linear solver; the table
is fitted to peaks measured by ``benchmarks/memory.py`` (cloth, chain and cube
scenes; its JSON holds the figures) and applied with ``MARGIN``.
"""

from __future__ import annotations

import math
import resource
from pathlib import Path

# Peak bytes a run adds (model, fields, solver setup), per particle and per spring,
# by what its integrator solves with: None (no linear solve), or the preconditioner.
RUN_BYTES = {None: (270, 310), "none": (575, 465), "block-jacobi": (575, 465), "multigrid": (4720, 1040),
             "multigrid-f32": (4720, 1080)}  # multigrid's, with its f32 copy of the coefficients (40 B a spring)
# Peak bytes of building a Model alone (generator arrays, springs, triangles).
BUILD_BYTES = (150, 130)
MARGIN = 1.5
FIXED = 200e6           # the runtime and compiled kernels of a first run
TAICHI_RESERVE = 1.6e9  # address space that starting Taichi's CPU runtime reserves


class MemoryNeedError(ValueError):
    """A run would not fit in the memory this process may use."""


def run_bytes(particles, springs, solver=None, model_built=False, extra=0, spring_extra=0) -> float:
    """Bytes a run of ``particles`` and ``springs`` may add at its peak, margin included.

    ``solver``: None for an integrator without a linear solve, else the preconditioner
    it resolves to ("none", "block-jacobi", "multigrid"). ``model_built``: the Model's
    own arrays exist already (then building them is not counted again). ``extra``:
    bytes per particle the integrator adds to the linearised step's (its
    ``extra_bytes``: the Newton-solved ones' work vectors); ``spring_extra``: bytes per
    spring beyond (a strain limit's corrections)."""
    per_particle, per_spring = RUN_BYTES[solver]
    per_particle += extra
    per_spring += spring_extra
    if model_built:
        per_particle, per_spring = per_particle - BUILD_BYTES[0], per_spring - BUILD_BYTES[1]
    return _total(per_particle, particles, per_spring, springs) + FIXED


def build_bytes(particles, springs) -> float:
    """Bytes that building a Model of ``particles`` and ``springs`` may take at its peak."""
    return _total(BUILD_BYTES[0], particles, BUILD_BYTES[1], springs)


def _total(per_particle, particles, per_spring, springs) -> float:
    """MARGIN x the bytes of ``particles`` and ``springs``; inf for counts beyond a float
    (a size key of hundreds of digits)."""
    try:
        return MARGIN * (per_particle * float(particles) + per_spring * float(springs))
    except OverflowError:
        return math.inf


def available() -> tuple[float | None, str]:
    """(bytes this process may still allocate, which limit sets it); (None, "") where
    no limit can be read."""
    limits = [(value, name) for value, name in ((_mem_available(), "of memory available"),
                                                (_cgroup_room(), "left under the cgroup's memory limit"),
                                                (_address_space_room(), "of address space left under ulimit -v"))
              if value is not None]
    return min(limits) if limits else (None, "")


def check(need, what):
    """Raise MemoryNeedError "``what`` ... needs N GB; M GB <limit>" if ``need`` bytes do
    not fit in ``available()``."""
    room, name = available()
    if room is not None and need > room:
        amount = f"about {need / 1e9:.3g} GB" if math.isfinite(need) else "more bytes than a float can count"
        raise MemoryNeedError(f"{what} needs {amount}; {max(room, 0) / 1e9:.3g} GB {name}")


def _read(path):
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def _mem_available():
    text = _read("/proc/meminfo")
    for line in (text or "").splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) * 1024
    return None


def _cgroup_room():
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        limit, usage = _read(limit_file), _read(usage_file)
        if limit and usage and limit.isdigit() and usage.isdigit() and int(limit) < 1 << 60:
            return int(limit) - int(usage)
    return None


def _address_space_room():
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    size = None
    for line in (_read("/proc/self/status") or "").splitlines():
        if line.startswith("VmSize:"):
            size = int(line.split()[1]) * 1024
    if size is None:
        return None
    from taichi.lang import impl

    reserve = 0 if impl.get_runtime().prog is not None else TAICHI_RESERVE
    return soft - size - reserve
