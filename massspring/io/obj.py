"""Wavefront OBJ: a reader for meshes (``read_obj``) and a writer for frames (``write_obj``).

Our own reader rather than meshio's (5.3.5) or trimesh's (5.2): both mishandle OBJ in
ways that matter for a mass-spring net: negative indices off by one (meshio) or
resolved against the end of the file (trimesh), index 0 and out-of-range indices
accepted silently, files whose vt/vn counts differ from the v count refused (meshio)
or vertices split at UV/normal seams and material changes (trimesh), and no line
numbers in errors.

Reading: ``v x y z`` (further components, e.g. w or a colour, are ignored) and ``f``
with indices in any of the forms ``v``, ``v/vt``, ``v//vn``, ``v/vt/vn``, 1-based or
negative (relative to the vertices read so far); faces of more than three vertices
are kept as polygons (``massspring.model.mesh`` fan-triangulates them). ``#`` starts a
comment anywhere on a line, a trailing ``\\`` continues a line, and every other
statement (vt, vn, o, g, s, usemtl, mtllib, l, ...) is ignored. Every problem raises
:class:`ObjError` whose message starts with ``FILE:LINE:`` (``FILE:`` for problems of
the whole file).
"""

from __future__ import annotations

import math
import os
import stat
from dataclasses import dataclass

import numpy as np

from massspring.support import memory
from massspring.model import mesh
from massspring.io.files import atomic_output
from massspring.support.text import brief

READ_BYTES_PER_FILE_BYTE = 22  # peak memory of read_obj per byte of the file (a 300 x 300 grid mesh)
MAX_LINE = 1 << 20  # characters of one logical line
MAX_INDEX = 2**31 - 1  # vertex indices (kernels count particles in int32)


class ObjError(ValueError):
    """A file that is not a usable mesh: ``path``, ``line`` (1-based, or None for the
    whole file) and ``reason``; ``str()`` is ``"FILE:LINE: reason"``."""

    def __init__(self, path, line, reason):
        self.path, self.line, self.reason = str(path), line, reason
        super().__init__(f"{self.path}:{line}: {reason}" if line is not None else f"{self.path}: {reason}")


@dataclass(frozen=True)
class ObjMesh:
    """A mesh read from an OBJ file: ``vertices`` (n, 3) float64 (file units, m by
    convention); ``faces``: 0-based vertex indices of each face (lists of >= 3);
    ``face_lines``, ``vertex_lines``: the line each face and vertex was read from."""

    path: str
    vertices: np.ndarray
    faces: list
    face_lines: np.ndarray
    vertex_lines: np.ndarray


def _logical_lines(path, fh):
    """(first physical line number, text) of each line, ``\\`` continuations joined; a
    line longer than ``MAX_LINE`` characters raises ObjError."""
    pending, start = "", None
    # at most MAX_LINE characters and a line end per read: a longer line is never held whole
    for number, raw in enumerate(iter(lambda: fh.readline(MAX_LINE + 2), ""), 1):
        text = raw.rstrip("\r\n")
        if start is None:
            start = number
        if len(pending) + len(text) > MAX_LINE:
            raise ObjError(path, start, f"a line longer than {MAX_LINE:,} characters: not an OBJ mesh")
        if text.endswith("\\"):
            pending += text[:-1] + " "
            continue
        yield start, pending + text
        pending, start = "", None
    if start is not None:
        yield start, pending


def _open(path):
    """``path`` opened as UTF-8 text (a byte-order mark skipped) once it shows a regular
    file (never a FIFO or device, which could block or never end) whose reading fits in
    the memory available (``memory.available``)."""
    try:
        info = os.stat(path)
    except (OSError, ValueError) as exc:
        raise ObjError(path, None, f"cannot be read: {getattr(exc, 'strerror', None) or exc}") from None
    if not stat.S_ISREG(info.st_mode):
        raise ObjError(path, None, "not a regular file (an OBJ mesh is a text file)")
    try:
        memory.check(memory.MARGIN * READ_BYTES_PER_FILE_BYTE * info.st_size,
                     f"reading its {info.st_size / 1e9:.3g} GB")
    except memory.MemoryNeedError as exc:
        raise ObjError(path, None, str(exc)) from None
    try:
        return open(path, encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise ObjError(path, None, f"cannot be read: {exc.strerror}") from None


def read_obj(path) -> ObjMesh:
    """Read a polygon mesh from an OBJ file, checked for what a Model needs: at least
    one vertex and one face, valid indices, no vertex twice in a face, no triangle of
    zero area (``mesh.degenerate_triangles``), no vertex outside every face."""
    fh = _open(path)
    vertices, vertex_lines, faces, face_lines = [], [], [], []
    with fh:
        for number, text in _logical_lines(path, fh):
            if text.startswith(("vt", "vn", "#")):  # the most common lines this reader ignores
                continue
            if "#" in text:
                text = text.split("#", 1)[0]
            tokens = text.split()
            if not tokens:
                continue
            keyword = tokens[0]
            if keyword == "v":
                vertices.append(_vertex(path, number, tokens[1:]))
                vertex_lines.append(number)
            elif keyword == "f":
                faces.append(_face(path, number, tokens[1:], len(vertices)))
                face_lines.append(number)
    if not vertices:
        raise ObjError(path, None, "no vertices ('v' lines)")
    if not faces:
        raise ObjError(path, None, "no faces ('f' lines)")
    x = np.array(vertices, dtype=np.float64)
    indices = np.fromiter((i for face in faces for i in face), dtype=np.int64)
    sizes = np.fromiter((len(face) for face in faces), dtype=np.int64, count=len(faces))
    beyond = np.flatnonzero(indices >= len(x))  # positive indices may point forward: checked at the end
    if beyond.size:
        k = int(np.searchsorted(np.cumsum(sizes), beyond[0], side="right"))
        raise ObjError(path, face_lines[k], f"vertex index {indices[beyond[0]] + 1} is beyond the {len(x)} "
                       "vertices of the file")
    triangles, face_of, _ = mesh.triangulate(indices, sizes)
    bad = mesh.degenerate_triangles(x, triangles)
    if bad.size:
        corners = " ".join(str(i + 1) for i in triangles[bad[0]])
        raise ObjError(path, face_lines[face_of[bad[0]]], f"degenerate face: the triangle of vertices {corners} "
                       "has zero area")
    unused = mesh.unused_vertices(len(x), triangles)
    if unused.size:
        raise ObjError(path, vertex_lines[unused[0]], f"vertex {unused[0] + 1} belongs to no face "
                       "(it would have no mass)")
    return ObjMesh(str(path), x, faces, np.array(face_lines), np.array(vertex_lines))


def _vertex(path, number, args):
    if len(args) < 3:
        raise ObjError(path, number, f"a vertex needs 3 coordinates, got {len(args)}")
    try:
        xyz = (float(args[0]), float(args[1]), float(args[2]))
    except ValueError:
        raise ObjError(path, number, f"malformed number in vertex {' '.join(args[:3])!r}") from None
    if not (math.isfinite(xyz[0]) and math.isfinite(xyz[1]) and math.isfinite(xyz[2])):
        raise ObjError(path, number, f"non-finite vertex coordinate in {' '.join(args[:3])!r}")
    return xyz


def _face(path, number, args, count):
    """0-based vertex indices of a face; ``count``: vertices read so far (for negative indices)."""
    if len(args) < 3:
        raise ObjError(path, number, f"a face needs at least 3 vertices, got {len(args)}")
    face = []
    for arg in args:
        try:
            i = int(arg if "/" not in arg else arg[:arg.index("/")])
        except ValueError:
            raise ObjError(path, number, f"malformed vertex index {arg!r}") from None
        if i > MAX_INDEX:  # positive indices may point forward, so the count is checked at the end
            raise ObjError(path, number, f"vertex index {brief(i, 40)} is beyond any mesh (at most {MAX_INDEX:,})")
        if i > 0:
            face.append(i - 1)
        elif i < 0:
            if -i > count:
                raise ObjError(path, number, f"relative vertex index {i} points before the first vertex "
                               f"({count} read so far)")
            face.append(count + i)
        else:
            raise ObjError(path, number, "vertex index 0 is invalid (OBJ indices start at 1)")
    if len(set(face)) != len(face):
        raise ObjError(path, number, f"degenerate face: a vertex repeats in {' '.join(args)!r}")
    return face


def write_obj(path, vertices, triangles=(), lines=(), comment=""):
    """Write ``vertices`` (n, 3) as ``v`` lines (shortest round-trip decimals: float64
    is read back exactly), ``triangles`` (t, 3) as ``f`` and ``lines`` (k, 2) as ``l``
    lines (0-based in, 1-based in the file), atomically. ``comment``: a first ``#`` line."""
    parts = [f"# {comment}\n"] if comment else []
    parts += [f"v {x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(vertices, dtype=np.float64).tolist()]
    parts += [f"f {a} {b} {c}\n" for a, b, c in (np.asarray(triangles, dtype=np.int64).reshape(-1, 3) + 1).tolist()]
    parts += [f"l {a} {b}\n" for a, b in (np.asarray(lines, dtype=np.int64).reshape(-1, 2) + 1).tolist()]
    with atomic_output(path) as fh:
        fh.write("".join(parts).encode())
