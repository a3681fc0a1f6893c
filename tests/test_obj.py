"""OBJ in and out: every index form, polygons and statements read as written; every bad file
refused with FILE:LINE; float64 vertices written and read back exactly."""

import numpy as np
import pytest

import massspring as ms
from massspring.io.obj import ObjError, read_obj, write_obj

TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
SQUARE = TRIANGLE + "v 1 1 0\n"

# name -> (file text, expected faces, 0-based)
GOOD = {
    "triangle": (TRIANGLE + "f 1 2 3\n", [[0, 1, 2]]),
    "quad": ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n", [[0, 1, 2, 3]]),
    "pentagon": ("v 0 0 0\nv 2 0 0\nv 3 1 0\nv 1 2 0\nv -1 1 0\nf 1 2 3 4 5\n", [[0, 1, 2, 3, 4]]),
    "v/vt": (TRIANGLE + "vt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n", [[0, 1, 2]]),
    "v//vn": (TRIANGLE + "vn 0 0 1\nf 1//1 2//1 3//1\n", [[0, 1, 2]]),
    "v/vt/vn": (TRIANGLE + "vt 0 0\nvn 0 0 1\nf 1/1/1 2/1/1 3/1/1\n", [[0, 1, 2]]),
    "negative": (TRIANGLE + "f -3 -2 -1\n", [[0, 1, 2]]),
    "negative, interleaved with vertices": (
        TRIANGLE + "f -3 -2 -1\nv 5 0 0\nv 6 0 0\nv 5 1 0\nf -3/-3/-1 -2/-2/-1 -1/-1/-1\nvt 0 0\nvn 0 0 1\n",
        [[0, 1, 2], [3, 4, 5]]),
    "statements and comments": ("# a comment\nmtllib a.mtl\no thing\ng one\ns 1\nusemtl red\n" + SQUARE +
                                "vn 0 0 1\nvt 0 0\nl 1 2\ns off\nf 1 2 3\ng two\nusemtl blue\nf 2 4 3\n",
                                [[0, 1, 2], [1, 3, 2]]),
    "CRLF line ends": (TRIANGLE.replace("\n", "\r\n") + "f 1 2 3\r\n", [[0, 1, 2]]),
    "comment after data": ("v 0 0 0 # origin\nv 1 0 0\nv 0 1 0\nf 1 2 3 # the face\n", [[0, 1, 2]]),
    "w and colour components": ("v 0 0 0 1.0\nv 1 0 0 1 0 0\nv 0 1 0\nf 1 2 3\n", [[0, 1, 2]]),
    "unknown statement": (TRIANGLE + "foo bar\nf 1 2 3\n", [[0, 1, 2]]),
    "forward reference": ("v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n", [[0, 1, 2]]),
    "continuation line": (SQUARE + "f 1 2 \\\n 4 3\n", [[0, 1, 3, 2]]),
}

# name -> (file text, line or None, words of the message)
BAD = {
    "empty": ("", None, "no vertices"),
    "comments only": ("# nothing\n\n# here\n", None, "no vertices"),
    "no faces": (TRIANGLE, None, "no faces"),
    "faces, no vertices": ("f 1 2 3\n", None, "no vertices"),
    "index 0": (TRIANGLE + "f 0 1 2\n", 4, "index 0 is invalid"),
    "index too large": (TRIANGLE + "f 1 2 9\n", 4, "index 9 is beyond the 3 vertices"),
    "negative index too far back": (TRIANGLE + "f -1 -2 -9\n", 4, "relative vertex index -9"),
    "index not a number": (TRIANGLE + "f 1 2 x\n", 4, "malformed vertex index 'x'"),
    "index with a fraction": (TRIANGLE + "f 1 2 3.0\n", 4, "malformed vertex index '3.0'"),
    "malformed coordinate": ("v 0 0 0\nv 1 0 0\nv 0 1.0.0 0\nf 1 2 3\n", 3, "malformed number"),
    "NaN coordinate": ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", 3, "non-finite"),
    "two coordinates": ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", 2, "needs 3 coordinates"),
    "face of two vertices": (TRIANGLE + "f 1 2\n", 4, "at least 3 vertices"),
    "repeated vertex": (TRIANGLE + "f 1 1 2\n", 4, "a vertex repeats"),
    "zero-area triangle": ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", 4, "zero area"),
    "zero-area triangle of a quad": (SQUARE + "v 2 2 0\nf 1 2 3\nf 1 4 5 3\n", 7, "zero area"),
    "vertex in no face": (SQUARE + "f 1 2 3\n", 4, "vertex 4 belongs to no face"),
    "error after a continuation": (SQUARE + "f 1 2 \\\n 4 3\nf 1 2 x\n", 7, "malformed vertex index"),
}


@pytest.mark.parametrize("name", sorted(GOOD))
def test_good_files_read_as_written(name, tmp_path):
    text, faces = GOOD[name]
    path = tmp_path / "mesh.obj"
    path.write_bytes(text.encode())
    mesh = read_obj(path)
    assert mesh.faces == faces
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.shape[1] == 3


def test_vertices_and_lines_are_those_of_the_file(tmp_path):
    path = tmp_path / "mesh.obj"
    path.write_text(GOOD["negative, interleaved with vertices"][0])
    mesh = read_obj(path)
    assert mesh.vertices[mesh.faces[1]].tolist() == [[5, 0, 0], [6, 0, 0], [5, 1, 0]]
    assert mesh.vertex_lines.tolist() == [1, 2, 3, 5, 6, 7] and mesh.face_lines.tolist() == [4, 8]


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_files_name_the_file_and_line(name, tmp_path):
    text, line, words = BAD[name]
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(ObjError) as info:
        read_obj(path)
    assert info.value.line == line
    assert str(info.value).startswith(f"{path}:{line}: " if line else f"{path}: "), str(info.value)
    assert words in str(info.value)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ObjError, match=f"^{tmp_path / 'none.obj'}: cannot be read: No such file"):
        read_obj(tmp_path / "none.obj")


def test_blender_cube_keeps_its_8_shared_vertices(tmp_path):
    corners = [(x, y, z) for x in (1, -1) for y in (1, -1) for z in (-1, 1)]
    text = "mtllib cube.mtl\no Cube\n" + "".join(f"v {x}.000000 {y}.000000 {z}.000000\n" for x, y, z in corners)
    text += "vt 0.625 0.5\nvt 0.875 0.5\nvt 0.875 0.75\nvt 0.625 0.75\n" + "vn 0 1 0\nvn 0 0 1\n"
    text += "usemtl Material\ns off\n"
    for face in ((1, 5, 7, 3), (4, 3, 7, 8), (8, 7, 5, 6), (6, 2, 4, 8), (2, 1, 3, 4), (6, 5, 1, 2)):
        text += "f " + " ".join(f"{v}/{1 + k}/{1 + k % 2}" for k, v in enumerate(face)) + "\n"
    path = tmp_path / "cube.obj"
    path.write_text(text)
    mesh = read_obj(path)
    model = ms.Model.from_mesh(mesh.vertices, mesh.faces)
    assert model.n_particles == 8 and len(model.triangles) == 12
    edges = np.sort(np.concatenate([model.triangles[:, [0, 1]], model.triangles[:, [1, 2]],
                                    model.triangles[:, [2, 0]]]), axis=1)
    assert (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()  # closed: each edge in two triangles


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(5)
    x = rng.normal(size=(40, 3))  # full 53-bit mantissas
    x[0] = [0.1, 1 / 3, -0.0]
    x[1] = [1e-17, 2 / 3, np.nextafter(1.0, 2.0)]
    triangles = np.array([[i, i + 1, i + 2] for i in range(38)])
    path = tmp_path / "frame.obj"
    write_obj(path, x, triangles, comment="t = 0.1 s")
    mesh = read_obj(path)
    assert np.array_equal(mesh.vertices, x) and np.signbit(mesh.vertices[0, 2])
    assert mesh.faces == triangles.tolist()


def test_writer_writes_springs_as_lines(tmp_path):
    path = tmp_path / "chain.obj"
    write_obj(path, [[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]], lines=[[0, 1], [1, 2]])
    assert path.read_text().splitlines() == ["v 0.0 0.0 0.0", "v 1.0 0.0 0.0", "v 2.0 0.0 0.0", "l 1 2", "l 2 3"]


def test_byte_order_mark_is_skipped(tmp_path):
    path = tmp_path / "bom.obj"
    path.write_bytes(b"\xef\xbb\xbf" + (TRIANGLE + "f 1 2 3\n").encode())
    mesh = read_obj(path)
    assert len(mesh.vertices) == 3 and mesh.faces == [[0, 1, 2]]


def test_special_files_are_refused_without_reading(tmp_path):
    import os
    import subprocess
    import sys

    for path in (tmp_path, "/dev/zero"):
        with pytest.raises(ObjError, match="not a regular file"):
            read_obj(path)
    fifo = tmp_path / "fifo.obj"
    os.mkfifo(fifo)
    script = f"from massspring.io.obj import read_obj\nread_obj({str(fifo)!r})\n"
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and "not a regular file" in proc.stderr  # at once: no writer awaited


def test_a_line_without_end_is_refused(tmp_path, monkeypatch):
    from massspring.io import obj

    monkeypatch.setattr(obj, "MAX_LINE", 1000)
    path = tmp_path / "long.obj"
    path.write_text(TRIANGLE + "f 1 2 3\n# " + "0" * 5000)
    with pytest.raises(ObjError, match=r"long.obj:5: a line longer than 1,000 characters"):
        read_obj(path)


def test_a_long_line_is_refused_without_being_read_whole(monkeypatch):
    """The reader never asks for more than MAX_LINE characters and a line end at once: a
    200 MB line costs what its first MAX_LINE characters do."""
    import io

    from massspring.io import obj

    class Recording(io.StringIO):
        longest = 0

        def readline(self, size=-1):
            line = super().readline(size)
            Recording.longest = max(Recording.longest, len(line)) if size >= 0 else 10 ** 9
            return line

    monkeypatch.setattr(obj, "MAX_LINE", 1000)
    with pytest.raises(ObjError, match=r"m.obj:5: a line longer than 1,000 characters"):
        list(obj._logical_lines("m.obj", Recording(TRIANGLE + "f 1 2 3\nv " + "1" * 100_000 + "\n")))
    assert Recording.longest <= 1002


def test_a_file_too_large_to_read_is_refused(tmp_path, monkeypatch):
    from massspring.support import memory

    monkeypatch.setattr(memory, "available", lambda: (1000.0, "of memory available"))
    path = tmp_path / "mesh.obj"
    path.write_text(TRIANGLE + "f 1 2 3\n")
    with pytest.raises(ObjError, match=r"mesh.obj: reading its .* GB needs about .* GB; 1e-06 GB of memory available"):
        read_obj(path)
