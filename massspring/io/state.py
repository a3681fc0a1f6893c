"""A simulation's state as a ``.npz`` file (``run --out``, ``--export DIR --format npz``,
read back by ``run --restart``).

Keys: ``positions``, ``velocities`` (n, 3) float64 (m, m/s); ``springs`` (m, 2) int;
``time`` (s), ``steps``, ``dt`` (s); and, to check a restart against its model:
``fingerprint`` (``Model.fingerprint()``, hex), ``scene`` (the scene's name, "" when
none was given), ``integrator``, ``triangles`` (t, 3) int (the surface, possibly empty);
``carried_<name>`` for each array of ``Simulation.carried_state()`` (the implicit
step's contact memory), so that a restart continues to the bit.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass

import numpy as np

from massspring.io.files import atomic_output

# key -> (kind, shape); "n" and "m" stand for the counts of the file's own arrays.
KEYS = {"positions": ("f", ("n", 3)), "velocities": ("f", ("n", 3)), "springs": ("i", ("m", 2)),
        "time": ("f", ()), "steps": ("i", ()), "dt": ("f", ()), "fingerprint": ("U", ()),
        "scene": ("U", ()), "integrator": ("U", ())}
CARRIED = "carried_"  # prefix of the keys of Simulation.carried_state()


def write_state(sim, path, scene=""):
    """Write ``sim``'s current state to ``path`` (.npz), atomically; ``scene``: its name."""
    with atomic_output(path) as fh:
        carried = {f"{CARRIED}{name}": values for name, values in sim.carried_state().items()}
        np.savez(fh, positions=sim.positions, velocities=sim.velocities, springs=sim.model.springs,
                 time=sim.time, steps=sim.steps, dt=sim.dt, fingerprint=sim.model.fingerprint(),
                 scene=str(scene), integrator=sim.integrator, triangles=sim.model.triangles, **carried)


@dataclass(frozen=True)
class State:
    """A state read by ``read_state``: arrays as in the file, scalars as Python values."""

    path: str
    positions: np.ndarray
    velocities: np.ndarray
    springs: np.ndarray
    time: float
    steps: int
    dt: float
    fingerprint: str
    scene: str
    integrator: str
    carried: dict | None = None  # Simulation.carried_state() at the save, if it had any

    @property
    def n_particles(self) -> int:
        return len(self.positions)


def read_state(path) -> State:
    """Read and check a state file: every key of ``KEYS`` present with its kind and shape,
    numbers finite, ``steps`` >= 0, ``dt`` > 0. Raises ValueError naming the file and key."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    except (ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise ValueError(f"{path}: not a state file (.npz) of massspring: {exc}") from None
    counts = {}
    for key, (kind, shape) in KEYS.items():
        if key not in arrays:
            raise ValueError(f"{path}: {key}: missing (not a state file written by this version of massspring)")
        arr = arrays[key]
        if arr.dtype.kind not in (("i", "u") if kind == "i" else (kind,)):
            raise ValueError(f"{path}: {key}: expected {_KINDS[kind]}, got dtype {arr.dtype}")
        if not _shape_fits(arr.shape, shape, counts):
            raise ValueError(f"{path}: {key}: expected shape {_shape(shape, counts)}, got {arr.shape}")
        if kind == "f" and not np.all(np.isfinite(arr)):
            raise ValueError(f"{path}: {key}: holds a non-finite value (NaN or Inf)")
    if arrays["positions"].shape[0] < 1:
        raise ValueError(f"{path}: positions: no particles")
    steps, dt = int(arrays["steps"]), float(arrays["dt"])
    if steps < 0:
        raise ValueError(f"{path}: steps: must be >= 0, got {steps}")
    if not dt > 0:
        raise ValueError(f"{path}: dt: must be > 0, got {dt:g}")
    carried = {key[len(CARRIED):]: arrays[key] for key in arrays if key.startswith(CARRIED)}
    for name, arr in carried.items():
        n = arrays["positions"].shape[0]
        if arr.dtype.kind not in "iuf" or arr.shape[:1] != (n,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{path}: {CARRIED}{name}: expected finite numbers, a row per particle ({n}), "
                             f"got shape {arr.shape} of {arr.dtype}")
    return State(str(path), arrays["positions"].astype(np.float64), arrays["velocities"].astype(np.float64),
                 arrays["springs"], float(arrays["time"]), steps, dt, str(arrays["fingerprint"]),
                 str(arrays["scene"]), str(arrays["integrator"]), carried or None)


_KINDS = {"f": "real numbers", "i": "integers", "U": "a string"}


def _shape_fits(actual, shape, counts):
    """Whether ``actual`` matches ``shape``; a named size takes its first value from ``counts``."""
    if len(actual) != len(shape):
        return False
    return all(size == (counts.setdefault(want, size) if isinstance(want, str) else want)
               for size, want in zip(actual, shape))


def _shape(shape, counts):
    sizes = [str(d) for d in shape]
    known = [f"{d} = {counts[d]}" for d in shape if isinstance(d, str) and d in counts]
    return "(" + ", ".join(sizes) + ("," if len(shape) == 1 else "") + ")" + (f" with {', '.join(known)}" if known else "")
