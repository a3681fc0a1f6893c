"""A simulation's state as a ``.npz`` file (``run --out``, ``--export DIR --format npz``,
read back by ``run --restart``).

Keys: ``positions``, ``velocities`` (n, 3) float64 (m, m/s); ``springs`` (m, 2) int;
``time`` (s), ``steps``, ``dt`` (s); and, to check a restart against its model:
``fingerprint`` (``Model.fingerprint()``, hex), ``scene`` (the scene's name, "" when
none was given), ``integrator``, ``triangles`` (t, 3) int (the surface, possibly empty);
``carried_<name>`` for each array of ``Simulation.carried_state()`` (the implicit
step's contact memory, a Newton run's previous state, the self-collision pass's
anchors) and, from an error-controlled run, ``control_<name>`` for each of
``Simulation.control_state()`` (its step-size controller and the accepted states its
error estimate draws on), so that a restart continues to the bit.
"""

from __future__ import annotations

import math
import os
import stat
import zipfile
import zlib
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from numpy.lib import format as npformat

from massspring.support import memory
from massspring.io.files import atomic_output

# key -> (kind, shape); "n" and "m" stand for the counts of the file's own arrays.
KEYS = {"positions": ("f", ("n", 3)), "velocities": ("f", ("n", 3)), "springs": ("i", ("m", 2)),
        "time": ("f", ()), "steps": ("i", ()), "dt": ("f", ()), "fingerprint": ("U", ()),
        "scene": ("U", ()), "integrator": ("U", ())}
CARRIED = "carried_"  # prefix of the keys of Simulation.carried_state()
CONTROL = "control_"  # prefix of the keys of Simulation.control_state() (which set_state checks)
CONTROL_NUMBERS = (64, 64)  # a state's control_ members hold at most 64 n + 64 numbers (n particles)
TRIANGLES = "triangles"  # the surface, for drawing; (t, 3) integers
HEADER_LIMIT = 10_000  # bytes of a member's .npy header
ITEM_LIMIT = 8  # bytes of a number
STRING_LIMIT = 4096  # characters of fingerprint, scene and integrator
# Bytes of the zip's central directory: its only bound on the count of carried_<name>
# members (an entry takes 46 bytes and twice its name, at most 2 x 77: about 300 members;
# what a run carries today, at most 8, takes about 1,000 bytes).
DIRECTORY_LIMIT = 64 * 1024
MEMBER_OVERHEAD = HEADER_LIMIT + 1_000  # bytes of a member besides its data: zip headers, .npy header
COMPRESSION_NAMES = {1: "Shrink", 6: "Implode", 9: "Deflate64", 12: "BZIP2", 14: "LZMA", 93: "Zstandard",
                     98: "PPMd", 99: "AES encryption"}


def write_state(sim, path, scene=""):
    """Write ``sim``'s current state to ``path`` (.npz), atomically; ``scene``: its name."""
    with atomic_output(path) as fh:
        save_state(sim, fh, scene)


def save_state(sim, fh, scene=""):
    """Write ``sim``'s current state as .npz to the binary file object ``fh``."""
    carried = {f"{CARRIED}{name}": values for name, values in sim.carried_state().items()}
    control = {f"{CONTROL}{name}": values for name, values in sim.control_state().items()}
    np.savez(fh, positions=sim.positions, velocities=sim.velocities, springs=sim.model.springs,
             time=sim.time, steps=sim.steps, dt=sim.dt, fingerprint=sim.model.fingerprint(),
             scene=str(scene), integrator=sim.integrator, triangles=sim.model.triangles, **carried, **control)


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
    control: dict | None = None  # Simulation.control_state() at the save, if it was error-controlled

    @property
    def n_particles(self) -> int:
        return len(self.positions)


def read_state(path, model=None, model_name="this run's model") -> State:
    """Read and check a state file. Raises ValueError naming the file, the key where
    there is one, and what is wrong.

    Each step is checked before the next reads anything, so no file can block, show a
    traceback, or make this allocate more than the arrays it declares, a size bounded
    by ``model`` when given (``model_name`` names it in messages) and else by the
    memory available:

    1. ``path`` is a regular file (never opened if it is a FIFO or device, which could
       block or never end);
    2. the zip's end record: a central directory of at most ``DIRECTORY_LIMIT`` bytes
       (which bounds the count of members; the format itself puts none on the
       ``carried_<name>`` ones);
    3. the zip directory: with ``model``, the file no larger than a state of ``model``
       with as many carried and control members as the directory lists, stored
       uncompressed (``_file_limit``); every member ``<key>.npy`` with a key of
       ``KEYS``, ``triangles``, ``carried_<name>`` or ``control_<name>`` (any count),
       each once, stored or deflated, not encrypted; every key of ``KEYS`` present;
    4. each member's .npy header (format 1.0 or 2.0): a plain dtype of the key's kind
       (numbers of at most 8 bytes, strings of at most ``STRING_LIMIT`` characters; no
       Python objects, so no pickles), a data size equal to the member's uncompressed
       size less its header;
    5. the shapes: each key's (``n``, ``m`` the same across keys; ``carried_<name>``
       a row per particle, one number or 3 each; the ``control_<name>`` ones at most 3
       dimensions and ``CONTROL_NUMBERS`` numbers together, which
       ``Simulation.set_state`` checks further); with ``model``, its particle, spring
       and triangle counts; the sum of the declared sizes, twice over, within the
       memory available;
    6. the data, each member read by itself as its header declared: numbers finite,
       ``steps`` >= 0, ``dt`` > 0.
    """
    try:
        with _open_regular_file(path) as fh:
            _check_end_record(path, fh)
            with zipfile.ZipFile(fh) as archive:
                carried = sum(info.filename.startswith(CARRIED) for info in archive.infolist())
                control = sum(info.filename.startswith(CONTROL) for info in archive.infolist())
                _check_size(path, fh, model, model_name, carried, control)
                members = _check_directory(path, archive)
                headers = {key: _check_header(path, archive, info, key) for key, info in members.items()}
                _check_shapes(path, headers, model, model_name)
                arrays = {key: _read_member(path, archive, members[key], key, headers[key]) for key in members}
    except (zipfile.BadZipFile, EOFError, zlib.error, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a state file (.npz) of massspring: {_brief(exc) or 'truncated'}") from None
    except NotImplementedError as exc:
        raise ValueError(f"{path}: not a state file (.npz) of massspring: it uses a zip feature that state "
                         f"files never do ({_brief(exc)})") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    return _check_values(path, arrays)


def _open_regular_file(path):
    """``path`` opened for reading once ``os.stat`` shows a regular file (step 1); the
    opened file is checked to be that same file."""
    try:
        before = os.stat(path)
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(before.st_mode):
        raise ValueError(f"{path}: not a regular file but {_file_kind(before.st_mode)}; a state file is "
                         "one written by --out or --export")
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    after = os.fstat(fd)
    if (after.st_dev, after.st_ino) != (before.st_dev, before.st_ino) or after.st_size != before.st_size:
        os.close(fd)
        raise ValueError(f"{path}: changed while being opened")
    return os.fdopen(fd, "rb")


def _check_end_record(path, fh):
    """The central directory's size from the zip's end record, which ``zipfile.ZipFile``
    reads whole before anything else (step 2)."""
    end = zipfile._EndRecData(fh)
    if end is None:
        raise zipfile.BadZipFile("no zip directory at its end")
    if end[zipfile._ECD_SIZE] > DIRECTORY_LIMIT:
        raise ValueError(f"{path}: its zip directory takes {end[zipfile._ECD_SIZE]:,} bytes; a state file's "
                         f"members at most take {DIRECTORY_LIMIT:,}")


def _check_directory(path, archive):
    """{key: ZipInfo} of the archive's members, each checked (step 3)."""
    members = {}
    for info in archive.infolist():
        key = info.filename[:-4] if info.filename.endswith(".npy") else None
        if key is None or not _allowed(key):
            raise ValueError(f"{path}: {info.filename[:80]!r}: not a key of a massspring state file (keys: "
                             f"{', '.join(KEYS)}, {TRIANGLES}, {CARRIED}<name> and {CONTROL}<name>, each a .npy "
                             "member)")
        if key in members:
            raise ValueError(f"{path}: {key}: stored twice")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            name = COMPRESSION_NAMES.get(info.compress_type, "unknown")
            raise ValueError(f"{path}: {key}: compression method {info.compress_type} ({name}) is not supported; "
                             "a state file's members are stored or deflated")
        if info.flag_bits & 0x61:
            raise ValueError(f"{path}: {key}: encrypted or patched, which a state file never is")
        members[key] = info
    for key in KEYS:
        if key not in members:
            raise ValueError(f"{path}: {key}: missing (not a state file written by this version of massspring)")
    return members


def _allowed(key):
    prefix = next((p for p in (CARRIED, CONTROL) if key.startswith(p)), None)
    name = key[len(prefix or ""):]
    return key in KEYS or key == TRIANGLES or (prefix is not None and name.isidentifier() and len(name) <= 64)


@contextmanager
def _reading(path, key):
    """Errors of zipfile and numpy while reading member ``key`` as ValueError naming it."""
    try:
        yield
    except (zipfile.BadZipFile, EOFError, zlib.error, NotImplementedError, OSError) as exc:
        raise ValueError(f"{path}: {key}: cannot be read ({_brief(exc) or 'truncated'})") from None
    except (ValueError, TypeError, SyntaxError) as exc:
        raise ValueError(f"{path}: {key}: not a valid .npy array ({_brief(exc)})") from None


def _check_header(path, archive, info, key):
    """(dtype, shape, bytes) of member ``key`` from its .npy header, checked against its
    key's kind and its uncompressed size (step 4), without reading its data."""
    with _reading(path, key), archive.open(info) as fh:
        version = npformat.read_magic(fh)
        read_header = {(1, 0): npformat.read_array_header_1_0, (2, 0): npformat.read_array_header_2_0}.get(version)
        if read_header is not None:
            shape, _, dtype = read_header(fh, max_header_size=HEADER_LIMIT)
            data_size = info.file_size - fh.tell()
    if read_header is None:
        raise ValueError(f"{path}: {key}: .npy format version {version[0]}.{version[1]}; a state file's are 1.0 or 2.0")
    if dtype.hasobject:
        raise ValueError(f"{path}: {key}: holds Python objects (dtype {dtype}), which a state file never does")
    kind = KEYS[key][0] if key in KEYS else ("i" if key == TRIANGLES else "n")
    if dtype.kind not in {"f": "f", "i": "iu", "U": "U", "n": "iuf"}[kind]:
        raise ValueError(f"{path}: {key}: expected {_KINDS[kind]}, got dtype {dtype}")
    if dtype.itemsize > (4 * STRING_LIMIT if kind == "U" else ITEM_LIMIT):
        raise ValueError(f"{path}: {key}: dtype {dtype} is wider than a state file's")
    if any(d < 0 for d in shape):
        raise ValueError(f"{path}: {key}: header declares shape {shape}")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes != data_size:
        raise ValueError(f"{path}: {key}: header declares shape {shape} of {dtype} ({nbytes:,} bytes) but the "
                         f"member holds {max(data_size, 0):,} bytes")
    return dtype, shape, nbytes


def _check_shapes(path, headers, model, model_name):
    """Shapes consistent across keys and with ``model``; the total size within the memory
    available (step 5)."""
    counts = {} if model is None else {"n": model.n_particles, "m": model.n_springs}
    if model is not None and headers["positions"][1][:1] != (model.n_particles,):
        rows = headers["positions"][1][:1]
        raise ValueError(f"{path}: positions: holds {rows[0] if rows else 0} particles; {model_name} has "
                         f"{model.n_particles}")
    for key, (kind, shape) in KEYS.items():
        if not _shape_fits(headers[key][1], shape, counts):
            raise ValueError(f"{path}: {key}: expected shape {_shape(shape, counts)}, got {headers[key][1]}")
    n = headers["positions"][1][0]
    for key, (dtype, shape, _) in headers.items():
        if key.startswith(CARRIED) and (len(shape) not in (1, 2) or shape[0] != n or shape[1:] not in ((), (3,))):
            raise ValueError(f"{path}: {key}: expected a row per particle ({n}), one number or 3 each; "
                             f"got shape {shape}")
        if key.startswith(CONTROL) and len(shape) > 3:
            raise ValueError(f"{path}: {key}: expected at most 3 dimensions, got shape {shape}")
    numbers = sum(math.prod(shape) for key, (_, shape, _) in headers.items() if key.startswith(CONTROL))
    if numbers > CONTROL_NUMBERS[0] * n + CONTROL_NUMBERS[1]:
        raise ValueError(f"{path}: its {CONTROL}<name> members hold {numbers:,} numbers; an error-controlled "
                         f"run of {n} particles keeps at most {CONTROL_NUMBERS[0] * n + CONTROL_NUMBERS[1]:,}")
    if TRIANGLES in headers:
        rows = headers[TRIANGLES][1]
        if len(rows) != 2 or rows[1] != 3 or (model is not None and rows[0] != len(model.triangles)):
            want = f"({len(model.triangles)}, 3)" if model is not None else "(t, 3)"
            raise ValueError(f"{path}: {TRIANGLES}: expected shape {want}, got {rows}")
    total = sum(nbytes for _, _, nbytes in headers.values())
    room, name = memory.available()
    if room is not None and 2 * total > room:
        raise ValueError(f"{path}: its arrays declare {total / 1e9:.3g} GB; {max(room, 0) / 1e9:.3g} GB {name}")


def _read_member(path, archive, info, key, header):
    """Member ``key``'s array, read as its checked header declares (step 6)."""
    dtype, shape, _ = header
    with _reading(path, key), archive.open(info) as fh:
        arr = npformat.read_array(fh, allow_pickle=False, max_header_size=HEADER_LIMIT)
    if arr.dtype != dtype or arr.shape != shape:
        raise ValueError(f"{path}: {key}: changed while being read")
    return arr


def _check_values(path, arrays) -> State:
    """The State of checked arrays: numbers finite, ``steps`` >= 0, ``dt`` > 0 (step 6)."""
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
    control = {key[len(CONTROL):]: arr for key, arr in arrays.items() if key.startswith(CONTROL)}
    return State(str(path), arrays["positions"].astype(np.float64, copy=False),
                 arrays["velocities"].astype(np.float64, copy=False), arrays["springs"], float(arrays["time"]),
                 steps, dt, str(arrays["fingerprint"]), str(arrays["scene"]), str(arrays["integrator"]),
                 carried or None, control or None)


def _check_size(path, fh, model, model_name, carried, control=0):
    """With ``model``, the file no larger than a state of ``model`` with ``carried``
    carried_<name> and ``control`` control_<name> members (``_file_limit``; step 3)."""
    size = os.fstat(fh.fileno()).st_size
    if model is not None and size > _file_limit(model, carried, control):
        raise ValueError(f"{path}: {size:,} bytes, more than a state file of {model_name} takes "
                         f"(at most {_file_limit(model, carried, control):,} bytes)")


def _file_limit(model, carried, control=0):
    """Bytes of the largest state file of ``model`` with ``carried`` carried_<name> and
    ``control`` control_<name> members: every array at its largest (a carried one 3
    numbers per particle, the control ones ``CONTROL_NUMBERS`` together), stored."""
    n, m, t = model.n_particles, model.n_springs, len(model.triangles)
    kept = CONTROL_NUMBERS[0] * n + CONTROL_NUMBERS[1] if control else 0
    data = ITEM_LIMIT * (2 * 3 * n + 2 * m + 3 * t + carried * 3 * n + kept + 3) + 3 * 4 * STRING_LIMIT
    return int(1.01 * data) + (len(KEYS) + 1 + carried + control) * MEMBER_OVERHEAD + DIRECTORY_LIMIT


def _file_kind(mode):
    kinds = [(stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a device"),
             (stat.S_ISBLK, "a device"), (stat.S_ISSOCK, "a socket")]
    return next((name for test, name in kinds if test(mode)), "another kind of file")


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
