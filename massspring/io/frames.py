"""Export of a run's frames (``run --export DIR --format FMT``): one file per frame (or
one file for the whole run), a JSON manifest, and for VTK a ParaView ``.pvd`` series.

Each format is one record in ``FORMATS`` (``FrameFormat``: extension, writer, the
optional module and extra it needs, its help); the CLI's choices and help come from it.
Each frame holds the positions (m) at one step and, where the Model has a surface,
its triangles; a model without one (a chain) gets its springs as line elements:

* ``obj`` (default; no dependency): ``v`` lines in shortest round-trip decimals (exact
  float64), ``f`` triangles or ``l`` springs, 1-based (``io.obj.write_obj``);
* ``ply``: binary PLY by meshio, float64 positions, triangles or springs as edges;
* ``vtk``: VTK XML unstructured grid (``.vtu``, binary) by meshio, float64 positions,
  triangles or springs as lines, and the ``velocity`` (m/s) as point data, plus
  ``frames.pvd``: the series with each frame's simulated time, for ParaView;
* ``npz``: a state file (``io.state``: positions, velocities, time, steps, the model's
  fingerprint, triangles), so any frame can start a ``--restart``;
* ``usd``: one USD stage, ``frames.usdc``, by pxr (``io.usd``): the body's points and
  velocities time-sampled (float32, as USD stores points), and the colliders.

Frames are named ``frame_00000.EXT``, ``frame_00001.EXT``, ... in the order written
(at least 5 digits, more for more frames); files of an earlier run in the directory
are replaced where the names repeat, and otherwise left alone. Every file is written
to a temporary name and renamed. Before each frame's file is renamed into place (an
earlier run's file of its name removed first), one line ({``file``, ``step``,
``time``}) is appended to ``frames.jsonl``, the journal: a cost per frame that does not
grow with the run. ``manifest.json`` (and the ``.pvd``) are rewritten, atomically, when
the run starts, when the frame count reaches a power of two and when the run ends,
however it ends: then its ``frames`` (and the journal) list exactly the frames of this
run on disk. While the run goes, or if the process was killed outright, the manifest
lists a prefix of them and the journal all of them, the last perhaps still being
written; ``read_frames(directory)`` returns exactly those on disk in either case. A single-file
format (usd) holds its frames in memory and writes its file when the run ends (not
if the process is killed outright); its manifest lists them from then on. The
manifest's keys: ``status`` ("running", "complete", "diverged", "interrupted",
"terminated", or "failed" when a frame could not be written), ``message`` (why it
stopped, or ""), ``format``, ``frames`` (a list of {``file``, ``step``, ``time``}),
``journal`` ("frames.jsonl"; null for a single-file format), ``last_step``/``last_time`` (the last good state
reached), ``series`` (the .pvd or the single file, else null), ``massspring``
(version) and whatever the caller describes the run with (``info``: scene,
integrator, dt, ...).
"""

from __future__ import annotations

import importlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from massspring.support.defaults import VERSION
from massspring.support.extras import install_hint
from massspring.io.files import atomic_output, atomic_path, check_writable, write_json
from massspring.io.obj import write_obj
from massspring.io.state import write_state
from massspring.support.text import brief, clipped

MANIFEST = "manifest.json"
JOURNAL = "frames.jsonl"


@dataclass(frozen=True)
class FrameFormat:
    """One format of ``run --export``: everything the export and the CLI know of it.

    ``writer`` ("module:name", imported when first used): for a format of one file per
    frame a function ``(path, sim, scene)`` writing ``sim``'s current state; for a
    ``single_file`` format a class ``(path, sim, scene)`` whose ``add(sim)`` takes each
    frame and ``save()`` writes them all to ``path``, atomically. ``module``: the
    optional module the writer needs, installed by the extra ``extra`` of
    pyproject.toml. ``index``: "module:name" of a function ``(path, frames)`` writing an
    index of the frame files named ``index_name`` (e.g. ParaView's series)."""

    name: str
    extension: str
    help: str
    writer: str
    module: str | None = None
    extra: str | None = None
    single_file: bool = False
    index: str | None = None
    index_name: str | None = None

    def load(self, what="writer"):
        """The object ``what`` ("writer" or "index") names."""
        module, _, name = getattr(self, what).partition(":")
        return getattr(importlib.import_module(module), name)

    @property
    def series(self):
        """The file that holds or lists the whole run (the manifest's ``series``), or None."""
        return f"frames{self.extension}" if self.single_file else self.index_name


FORMATS = {f.name: f for f in (
    FrameFormat("obj", ".obj", "Wavefront OBJ per frame, exact float64", "massspring.io.frames:write_obj_frame"),
    FrameFormat("ply", ".ply", "binary PLY per frame", "massspring.io.frames:write_ply_frame", "meshio", "mesh"),
    FrameFormat("vtk", ".vtu", "VTK XML per frame with velocities, and a ParaView frames.pvd",
                "massspring.io.frames:write_vtu_frame", "meshio", "mesh", index="massspring.io.frames:write_series",
                index_name="frames.pvd"),
    FrameFormat("npz", ".npz", "states that --restart takes", "massspring.io.frames:write_npz_frame"),
    FrameFormat("usd", ".usdc", "one USD stage, frames.usdc, time-sampled points and velocities, colliders",
                "massspring.io.usd:StageWriter", "pxr", "usd", single_file=True),
)}
DEFAULT_FORMAT = "obj"


MAX_LIST_BYTES = 256 * 2**20  # the largest manifest or journal ``read_frames`` reads (about 3 million frames)


def read_frames(directory):
    """The frames (each {``file``, ``step``, ``time``}) of the last export into
    ``directory`` that are on disk, in order: the manifest's list once its run ended;
    while the run goes, or if its process was killed outright (SIGKILL), the journal's
    lines whose file is in place (only the last can be missing: the process was killed
    while writing it). Raises ValueError naming the file if ``directory`` holds no
    export's manifest, or one that is not a regular file of at most ``MAX_LIST_BYTES``,
    not JSON of the shape above, or that names a file outside ``directory``."""
    directory = Path(directory)
    where = directory / MANIFEST
    try:
        manifest = json.loads(_read_list_file(where))
        frames, journal = manifest["frames"], manifest["journal"]
        if manifest["status"] != "running" or journal is None:
            return [_frame(f, directory) for f in _as_list(frames)]
        where = directory / _inside(journal, directory)
        lines = _read_list_file(where).split(b"\n")[:-1]  # a line without its newline is not there yet
        return [f for f in (_frame(json.loads(line), directory) for line in lines) if (directory / f["file"]).exists()]
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
        raise ValueError(f"{str(where)!r}: not the manifest of an export ({clipped(str(exc), 300)})") from None


def _read_list_file(path):
    """The bytes of ``path``, a regular file of at most ``MAX_LIST_BYTES`` (a FIFO or a
    device would block or never end)."""
    if not path.is_file():
        raise ValueError("not a regular file")
    with open(path, "rb") as fh:
        data = fh.read(MAX_LIST_BYTES + 1)
    if len(data) > MAX_LIST_BYTES:
        raise ValueError(f"more than {MAX_LIST_BYTES // 2**20} MB")
    return data


def _as_list(value):
    if not isinstance(value, list):
        raise ValueError(f"frames: expected a list, got {type(value).__name__}")
    return value


def _inside(name, directory):
    """``name`` if it is a relative path that stays inside ``directory``, symbolic links
    followed, else ValueError."""
    if not isinstance(name, str) or not name or Path(name).is_absolute() or ".." in Path(name).parts:
        raise ValueError(f"{brief(name, 80)} is not a file name inside {str(directory)!r}")
    if not (directory / name).resolve().is_relative_to(directory.resolve()):
        raise ValueError(f"{brief(name, 80)} is a link out of {str(directory)!r}")
    return name


def _frame(entry, directory):
    """A frame entry checked: {``file`` (inside ``directory``), ``step`` (int), ``time`` (number)}."""
    if not isinstance(entry, dict) or not {"file", "step", "time"} <= set(entry):
        raise ValueError(f"a frame: expected {{file, step, time}}, got {brief(entry, 80)}")
    if not isinstance(entry["step"], int) or isinstance(entry["time"], bool) \
            or not isinstance(entry["time"], (int, float)):
        raise ValueError(f"a frame: step and time must be numbers, got {brief(entry, 80)}")
    _inside(entry["file"], directory)
    return entry


def check_format(fmt, name="format"):
    """Refuse an unknown format, or one whose writer's module is not installed:
    ValueError starting with ``name``."""
    if fmt not in FORMATS:
        raise ValueError(f"{name}: unknown format {fmt!r}, expected one of {', '.join(FORMATS)}")
    record = FORMATS[fmt]
    if record.module is not None:
        try:
            importlib.import_module(record.module)
        except ImportError:
            raise ValueError(f"{name} {fmt}: needs {record.module}, which is not installed "
                             f"({install_hint(record.extra)})") from None


def _elements(model):
    """(meshio cell type, (k, d) int32 indices) of a frame: the surface, else the springs."""
    if len(model.triangles):
        return "triangle", model.triangles.astype(np.int32)
    return "line", model.springs.astype(np.int32)


def write_obj_frame(path, sim, scene):
    x = sim.positions
    surface = sim.model.triangles
    write_obj(path, x, surface, () if len(surface) else sim.model.springs,
              comment=f"massspring {scene}: step {sim.steps}, t = {sim.time!r} s")


def write_ply_frame(path, sim, scene):
    import meshio

    kind, cells = _elements(sim.model)
    with atomic_path(path) as tmp:
        meshio.write(tmp, meshio.Mesh(sim.positions, [(kind, cells)] if len(cells) else []), file_format="ply")


def write_vtu_frame(path, sim, scene):
    import meshio

    kind, cells = _elements(sim.model)
    mesh = meshio.Mesh(sim.positions, [(kind, cells)] if len(cells) else [],
                       point_data={"velocity": sim.velocities})
    with atomic_path(path) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")


def write_npz_frame(path, sim, scene):
    write_state(sim, path, scene)


def write_series(path, frames):
    """ParaView's collection file: each frame's file (relative) at its simulated time, atomically."""
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    lines += [f'    <DataSet timestep="{float(f["time"])!r}" group="" part="0" file={quoteattr(f["file"])}/>'
              for f in frames]
    lines += ["  </Collection>", "</VTKFile>", ""]
    with atomic_output(path) as fh:
        fh.write("\n".join(lines).encode())


class FrameExport:
    """Writes the frames of one run into ``directory`` as ``fmt`` (see the module
    docstring). ``count``: the frames planned (for the width of their numbers);
    ``scene``: the scene's name (in each file); ``info``: a JSON-able description of
    the run, copied into the manifest. Call ``prepare()`` before the run, the object
    itself as ``run``'s ``on_frame``, and ``finish`` after it.

    A frame that cannot be written (a full disk) stops the export, not the run:
    ``error`` then says why, and the manifest's status is "failed".
    """

    def __init__(self, directory, fmt, count, scene="", info=None, name="--export"):
        self.directory, self.fmt, self.scene, self.name = Path(directory), fmt, scene, name
        self.info = dict(info or {})
        self.digits = max(5, len(str(max(count - 1, 0))))
        self.frames = []   # the frames on disk
        self.pending = []  # a single-file format's frames not yet saved
        self.writer = None  # a single-file format's writer, made at the first frame
        self.error = None
        self.last = (None, None)  # (step, time) of the last state seen
        self.journal = None  # the journal's file descriptor while frames are written
        self.writing = None  # the frame whose file is being written (its journal line is written)

    def file_name(self, k):
        record = FORMATS[self.fmt]
        return record.series if record.single_file else f"frame_{k:0{self.digits}d}{record.extension}"

    def prepare(self):
        """Before the run: check the format, create the directory (and its parents) if
        missing, try the files a frame and the manifest would be written as, and write a
        manifest saying "running". Raises ValueError starting with ``name``."""
        check_format(self.fmt, "--format")
        try:
            if self.directory.exists() and not self.directory.is_dir():
                raise ValueError(f"{self.name}: {str(self.directory)!r} exists and is not a directory")
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"{self.name}: cannot create the directory {str(self.directory)!r}: "
                             f"{exc.strerror or exc}") from None
        for file in (MANIFEST, JOURNAL, self.file_name(0)):
            check_writable(self.directory / file, self.name)
        try:
            if not FORMATS[self.fmt].single_file:
                with atomic_output(self.directory / JOURNAL):
                    pass  # empty: an earlier run's journal goes
            self._write_manifest("running", "")
        except OSError as exc:
            raise ValueError(f"{self.name}: cannot write {str(self.directory / MANIFEST)!r}: "
                             f"{exc.strerror or exc}") from None

    def __call__(self, sim):
        """Write ``sim``'s current state as the next frame, then the manifest (and the
        index); a single-file format's writer takes the frame, to be saved by ``finish``."""
        self.last = (sim.steps, sim.time)
        if self.error is not None:
            return
        record = FORMATS[self.fmt]
        file = self.file_name(len(self.frames))
        try:
            if record.single_file:
                if self.writer is None:
                    self.writer = record.load()(self.directory / file, sim, self.scene)
                self.writer.add(sim)
                self.pending.append({"file": file, "step": sim.steps, "time": sim.time})
                return
            frame, path = {"file": file, "step": sim.steps, "time": sim.time}, self.directory / file
            # an earlier run's file of this name goes first, so that after the journal's line
            # the file is there only if this run wrote it (read_frames relies on that)
            path.unlink(missing_ok=True)
            self.writing = frame
            self._journal(frame)
            record.load()(path, sim, self.scene)
            self.frames.append(frame)
            self.writing = None
            if len(self.frames) & (len(self.frames) - 1) == 0:  # a power of two: amortised constant time
                self._write_manifest("running", "")
        except OSError as exc:
            self.error = f"could not write {str(self.directory / file)!r}: {exc.strerror or exc}"

    def finish(self, status, sim, message=""):
        """Save a single-file format's frames, then mark the manifest with ``status``
        ("complete", "diverged", "interrupted", "terminated"; "failed" if a frame could
        not be written) and the last good state ``sim`` reached. Returns ``error`` (None
        if every file was written)."""
        self.last = (sim.steps, sim.time)
        writing, self.writing = self.writing, None
        if writing is not None and not (self.frames and self.frames[-1] is writing):
            # a signal came while its file was written: is it in place?
            if (self.directory / writing["file"]).exists():
                self.frames.append(writing)
            else:
                self._rewrite_journal()
        if self.journal is not None:
            os.close(self.journal)
            self.journal = None
        if self.writer is not None and self.error is None:
            try:
                self.writer.save()
                self.frames = self.pending
            except OSError as exc:
                self.error = f"could not write {str(self.directory / self.file_name(0))!r}: {exc.strerror or exc}"
        if self.error is not None:
            status, message = "failed", self.error
        try:
            self._write_manifest(status, message)
        except OSError as exc:
            self.error = self.error or f"could not write {str(self.directory / MANIFEST)!r}: {exc.strerror or exc}"
        return self.error

    def _journal(self, frame):
        """Append ``frame``'s line to the journal in one write (a line is never half
        there), before its file is renamed into place; the journal stays open until
        ``finish``."""
        if self.journal is None:
            self.journal = os.open(self.directory / JOURNAL, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        os.write(self.journal, (json.dumps(frame) + "\n").encode())

    def _rewrite_journal(self):
        """The journal as ``frames`` (after a frame whose file never came), atomically."""
        try:
            if self.journal is not None:
                os.close(self.journal)
                self.journal = None
            with atomic_output(self.directory / JOURNAL) as fh:
                fh.write("".join(json.dumps(f) + "\n" for f in self.frames).encode())
        except OSError as exc:
            self.error = self.error or f"could not write {str(self.directory / JOURNAL)!r}: {exc.strerror or exc}"

    def _write_manifest(self, status, message):
        record = FORMATS[self.fmt]
        if record.index is not None and self.frames:
            record.load("index")(self.directory / record.index_name, self.frames)
        step, time = self.last
        write_json(self.directory / MANIFEST, {
            "massspring": VERSION, "status": status, "message": message, "format": self.fmt, **self.info,
            "last_step": step, "last_time": time, "series": record.series,
            "journal": None if record.single_file else JOURNAL, "frames": self.frames})

    def __len__(self):
        return len(self.frames)
