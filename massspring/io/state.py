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

import math
import os
import stat
import zipfile
from dataclasses import dataclass

import numpy as np
from numpy.lib import format as npformat

from massspring import memory
from massspring.io.files import atomic_output

# key -> (kind, shape); "n" and "m" stand for the counts of the file's own arrays.
KEYS = {"positions": ("f", ("n", 3)), "velocities": ("f", ("n", 3)), "springs": ("i", ("m", 2)),
        "time": ("f", ()), "steps": ("i", ()), "dt": ("f", ()), "fingerprint": ("U", ()),
        "scene": ("U", ()), "integrator": ("U", ())}
CARRIED = "carried_"  # prefix of the keys of Simulation.carried_state()
TRIANGLES = "triangles"  # the surface, for drawing; (t, 3) integers
HEADER_LIMIT = 10_000  # bytes of a member's .npy header


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


def read_state(path, model=None, model_name="this run's model") -> State:
    """Read and check a state file. Raises ValueError naming the file and the key.

    Nothing is read before it is checked, so no file can make this allocate more than
    its arrays' declared size, and that size is bounded:
    1. ``path`` is a regular file (never a FIFO or device, which could block or never end);
    2. the zip directory: every member a key of ``KEYS``, ``triangles`` or
       ``carried_<name>``, each once, stored or deflated, not encrypted;
    3. each member's .npy header: a plain dtype of the key's kind (no pickled objects),
       the key's shape (``n``, ``m`` the same across keys, and with ``model`` its particle,
       spring and triangle counts), and a data size equal to the member's stored size;
       the sum of the declared sizes within the memory available (with ``model``, it is
       the model's own arrays' size; ``model_name`` names it in messages);
    4. the data: numbers finite, ``steps`` >= 0, ``dt`` > 0.
    """
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{path}: not a regular file (a state file written by --out or --export)")
    try:
        with zipfile.ZipFile(path) as archive:
            members = _check_directory(path, archive)
            headers = {key: _check_header(path, archive, info, key) for key, info in members.items()}
            _check_sizes(path, headers, model, model_name)
            arrays = {key: _read_member(path, archive, members[key], key) for key in members}
    except (zipfile.BadZipFile, EOFError) as exc:
        raise ValueError(f"{path}: not a state file (.npz) of massspring: {exc or 'truncated'}") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    return _check_values(path, arrays)


def _allowed(key):
    return key in KEYS or key == TRIANGLES or (key.startswith(CARRIED) and len(key) > len(CARRIED))


def _check_directory(path, archive):
    """{key: ZipInfo} of the archive's members, each checked (step 2 of ``read_state``)."""
    members = {}
    for info in archive.infolist():
        key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
        if not _allowed(key) or not info.filename.endswith(".npy"):
            raise ValueError(f"{path}: {info.filename[:80]!r}: not a member of a massspring state file "
                             f"(expected {', '.join(KEYS)}, {TRIANGLES} and {CARRIED}<name>, as .npy)")
        if key in members:
            raise ValueError(f"{path}: {key}: stored twice")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise ValueError(f"{path}: {key}: compression method {info.compress_type} is not supported "
                             "(a state file is stored or deflated)")
        if info.flag_bits & 0x1:
            raise ValueError(f"{path}: {key}: encrypted")
        members[key] = info
    for key in KEYS:
        if key not in members:
            raise ValueError(f"{path}: {key}: missing (not a state file written by this version of massspring)")
    return members


def _check_header(path, archive, info, key):
    """(dtype, shape) of a member from its .npy header, checked against its key and its
    stored size (step 3 of ``read_state``), without reading its data."""
    try:
        with archive.open(info) as fh:
            version = npformat.read_magic(fh)
            read_header = npformat.read_array_header_1_0 if version == (1, 0) else npformat.read_array_header_2_0
            shape, fortran, dtype = read_header(fh, max_header_size=HEADER_LIMIT)
            data_offset = fh.tell()
    except (ValueError, TypeError, SyntaxError) as exc:
        raise ValueError(f"{path}: {key}: not a valid array ({_brief(exc)})") from None
    if dtype.hasobject or dtype.kind not in "iuf" + "U":
        raise ValueError(f"{path}: {key}: dtype {dtype} is not one a state file holds")
    kind = KEYS[key][0] if key in KEYS else ("i" if key == TRIANGLES else "n")
    allowed = {"f": "f", "i": "iu", "U": "U", "n": "iuf"}[kind]
    if dtype.kind not in allowed:
        raise ValueError(f"{path}: {key}: expected {_KINDS[kind]}, got dtype {dtype}")
    if any(d < 0 for d in shape):
        raise ValueError(f"{path}: {key}: header declares shape {shape}")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes != info.file_size - data_offset:
        raise ValueError(f"{path}: {key}: header declares shape {shape} of {dtype} ({nbytes:,} bytes) but the "
                         f"member holds {max(info.file_size - data_offset, 0):,} bytes")
    return dtype, shape, nbytes


def _check_sizes(path, headers, model, model_name):
    """Shapes consistent across keys and with ``model``; the total size bounded (step 3)."""
    counts = {} if model is None else {"n": model.n_particles, "m": model.n_springs}
    rows = headers["positions"][1][:1]
    if model is not None and rows != (model.n_particles,):
        raise ValueError(f"{path} holds {rows[0] if rows else 0} particles; {model_name} has {model.n_particles}")
    for key, (kind, shape) in KEYS.items():
        if not _shape_fits(headers[key][1], shape, counts):
            raise ValueError(f"{path}: {key}: expected shape {_shape(shape, counts)}, got {headers[key][1]}")
    n = headers["positions"][1][0]
    for key, (dtype, shape, _) in headers.items():
        if key.startswith(CARRIED) and (len(shape) not in (1, 2) or shape[0] != n or shape[1:] not in ((), (3,))):
            raise ValueError(f"{path}: {key}: expected a row per particle ({n}), one number or 3 each; "
                             f"got shape {shape}")
    if TRIANGLES in headers:
        rows = headers[TRIANGLES][1]
        if len(rows) != 2 or rows[1] != 3 or (model is not None and rows[0] != len(model.triangles)):
            want = f"({len(model.triangles)}, 3)" if model is not None else "(t, 3)"
            raise ValueError(f"{path}: {TRIANGLES}: expected shape {want}, got {rows}")
    total = sum(nbytes for _, _, nbytes in headers.values())
    room, name = memory.available()
    if room is not None and 2 * total > room:
        raise ValueError(f"{path}: its arrays declare {total / 1e9:.3g} GB; {room / 1e9:.3g} GB {name}")


def _read_member(path, archive, info, key):
    try:
        with archive.open(info) as fh:
            return npformat.read_array(fh, allow_pickle=False, max_header_size=HEADER_LIMIT)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: {key}: not a valid array ({_brief(exc)})") from None


def _check_values(path, arrays) -> State:
    """The State of checked arrays: numbers finite, ``steps`` >= 0, ``dt`` > 0 (step 4)."""
    for key, arr in arrays.items():
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise ValueError(f"{path}: {key}: holds a non-finite value (NaN or Inf)")
    if arrays["positions"].shape[0] < 1:
        raise ValueError(f"{path}: positions: no particles")
    steps, dt = int(arrays["steps"]), float(arrays["dt"])
    if steps < 0:
        raise ValueError(f"{path}: steps: must be >= 0, got {steps}")
    if not dt > 0:
        raise ValueError(f"{path}: dt: must be > 0, got {dt:g}")
    carried = {key[len(CARRIED):]: arr for key, arr in arrays.items() if key.startswith(CARRIED)}
    return State(str(path), arrays["positions"].astype(np.float64), arrays["velocities"].astype(np.float64),
                 arrays["springs"], float(arrays["time"]), steps, dt, str(arrays["fingerprint"]),
                 str(arrays["scene"]), str(arrays["integrator"]), carried or None)


def _brief(exc):
    """An exception's message, without numpy's advice to load pickles unsafely."""
    text = str(exc).split("\n")[0]
    return "pickled data is refused" if "pickle" in text.lower() else text[:200]


_KINDS = {"f": "real numbers", "i": "integers", "U": "a string", "n": "numbers"}


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
