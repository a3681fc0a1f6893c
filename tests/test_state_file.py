"""State files (``--out``, ``--restart``) are checked before their data is read: no file
can make ``read_state`` allocate more than its model's arrays, block, or end in a
traceback, and no message suggests loading pickles."""

import io
import os
import struct
import subprocess
import sys
import time
import zipfile

import numpy as np
import pytest
from numpy.lib import format as npformat

from conftest import FULL
import massspring as ms
from massspring.cli import main
from massspring.io.state import DIRECTORY_LIMIT, read_state, write_state

CHAIN = ["chain", "--set", "count=5", "--quiet"]
BOMB_ELEMENTS = 400_000_000  # float64 zeros: 3.2 GB uncompressed, about 14 MB deflated

# read_state(argv[1]) in a child, with the chain's model if argv[2] is "model"; prints the
# message, the seconds read_state took and the bytes its peak RSS (VmHWM) grew by.
CHILD = """
import sys, time
import massspring as ms
from massspring.io.state import read_state

def peak():
    return [int(line.split()[1]) * 1024 for line in open("/proc/self/status") if line.startswith("VmHWM:")][0]

model = ms.load_scene("chain").with_params(count=5).model() if sys.argv[2] == "model" else None
base, start = peak(), time.perf_counter()
try:
    read_state(sys.argv[1], model) if model is not None else read_state(sys.argv[1])
    message = "accepted"
except ValueError as exc:
    message = str(exc)
print(message, time.perf_counter() - start, peak() - base, sep="\\n")
"""


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A real state file of the 5-particle chain after 3 implicit steps, and its Simulation."""
    path = tmp_path_factory.mktemp("state") / "good.npz"
    sim = ms.load_scene("chain").with_params(count=5).simulation("implicit")
    sim.step(3)
    write_state(sim, path, scene="chain")
    return path, sim


@pytest.fixture(scope="module")
def bombs(good, tmp_path_factory):
    """{name: path}: the good file with an extra member of 400M float64 zeros ("extra"),
    and with its positions replaced by 16.7M rows of zeros, 400 MB ("positions")."""
    folder = tmp_path_factory.mktemp("bombs")
    base = members(good[0])
    return {"extra": zero_bomb(folder / "extra.npz", "extra", (BOMB_ELEMENTS,), base),
            "positions": zero_bomb(folder / "positions.npz", "positions", (16_666_667, 3), base)}


def members(path):
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


def npy(arr):
    buffer = io.BytesIO()
    npformat.write_array(buffer, np.asanyarray(arr), allow_pickle=True)
    return buffer.getvalue()


def write_members(path, arrays, compression=zipfile.ZIP_DEFLATED, extra=()):
    """An npz of ``arrays`` (name -> array) plus ``extra`` raw (name, bytes) members."""
    with zipfile.ZipFile(path, "w", compression) as archive:
        for name, arr in arrays.items():
            archive.writestr(f"{name}.npy", npy(arr))
        for name, data in extra:
            archive.writestr(name, data)
    return path


def zero_bomb(path, name, shape, base):
    """``base``'s members with member ``name`` replaced by float64 zeros of ``shape``,
    streamed into a deflated member (never whole in this process)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for key, arr in base.items():
            if key != name:
                archive.writestr(f"{key}.npy", npy(arr))
        with archive.open(f"{name}.npy", "w", force_zip64=True) as fh:
            npformat.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": shape})
            chunk, left = memoryview(bytes(1 << 24)), int(np.prod(shape)) * 8
            while left:
                fh.write(chunk[:min(left, len(chunk))])
                left -= min(left, len(chunk))
    return path


def patch_directory(path, member, offset, value):
    """Set the 2-byte field at ``offset`` of ``member``'s central directory entry."""
    data = bytearray(path.read_bytes())
    at = data.find(b"PK\x01\x02")
    while data[at + 46:at + 46 + struct.unpack_from("<H", data, at + 28)[0]] != member.encode():
        at = data.find(b"PK\x01\x02", at + 1)
    struct.pack_into("<H", data, at + offset, value)
    path.write_bytes(bytes(data))
    return path


def refused(path, *words, model=None):
    """read_state's message for ``path``, checked to name the file and each of ``words``
    and not to mention loading pickles."""
    with pytest.raises(ValueError) as info:
        read_state(path, model) if model is not None else read_state(path)
    message = str(info.value)
    assert str(path) in message and "allow_pickle" not in message and "unsafe" not in message, message
    for word in words:
        assert word in message, (word, message)
    return message


@pytest.mark.fast_sample(scene=["chain"])
@pytest.mark.parametrize("scene, params", [("chain", {"count": 5}), ("drape", {"resolution": 4})])
def test_round_trip_is_bitwise(scene, params, tmp_path):
    sim = ms.load_scene(scene).with_params(**params).simulation("implicit")
    sim.step(3)
    path = tmp_path / "state.npz"
    write_state(sim, path, scene=scene)
    state = read_state(path, sim.model)
    for got, want in ((state.positions, sim.positions), (state.velocities, sim.velocities),
                      (state.springs, sim.model.springs)):
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    assert (state.time, state.steps, state.dt) == (sim.time, 3, sim.dt)
    assert (state.fingerprint, state.scene, state.integrator) == (sim.model.fingerprint(), scene, "implicit")
    carried = sim.carried_state()
    assert sorted(state.carried or {}) == sorted(carried) and (scene == "chain") == (not carried)
    for name, values in carried.items():
        assert state.carried[name].dtype == values.dtype and state.carried[name].tobytes() == values.tobytes()


@FULL
@pytest.mark.parametrize("name, model, words", [("extra", "-", ("'extra.npy'", "not a key")),
                                                ("positions", "-", ("velocities", "expected shape")),
                                                ("positions", "model", ("bytes, more than a state file",))])
def test_a_deflated_bomb_is_refused_without_reading_it(bombs, name, model, words):
    path = bombs[name]
    assert os.path.getsize(path) < 20e6
    proc = subprocess.run([sys.executable, "-c", CHILD, str(path), model], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    message, seconds, grown = proc.stdout.splitlines()[-3:]
    assert str(path) in message and all(word in message for word in words), message
    assert float(seconds) < 5 and int(grown) < 50e6, (seconds, grown)


@pytest.mark.parametrize("shape", [(10 ** 18,), (10 ** 18, 3)])
def test_a_header_declaring_more_than_the_member_holds(good, tmp_path, shape):
    data = members(good[0])
    header = io.BytesIO()
    npformat.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": shape})
    path = write_members(tmp_path / "huge.npz", {k: v for k, v in data.items() if k != "velocities"},
                         extra=[("velocities.npy", header.getvalue() + bytes(120))])
    refused(path, "velocities: header declares shape", "but the member holds 120 bytes")


def test_any_count_of_carried_arrays_is_read_back(good, tmp_path):
    """More carried arrays than any integrator carries today (8), each a row per particle,
    with the model's size check: the format puts no count on them."""
    path, sim = good
    data = members(path)
    n = sim.model.n_particles
    extra = {f"carried_a{i}": np.arange(n * 3, dtype=float).reshape(n, 3) + i for i in range(10)}
    extra.update({f"carried_b{i}": np.full(n, i, np.int32) for i in range(10)})
    state = read_state(write_members(tmp_path / "many.npz", {**data, **extra}), sim.model)
    assert sorted(state.carried) == sorted(key[len("carried_"):] for key in extra)
    for key, values in extra.items():
        assert np.array_equal(state.carried[key[len("carried_"):]], values)


@pytest.mark.parametrize("change, words", [
    (lambda d: d.update(extra=np.zeros(3)), ("'extra.npy'", "not a key of a massspring state file")),
    (lambda d: d.update(positions=np.array([object()] * 15).reshape(5, 3)), ("positions", "Python objects")),
    (lambda d: d.update(dt=np.array(0.01, dtype=np.longdouble)), ("dt", "wider than a state file's")),
    (lambda d: d.update(scene=np.array("x" * 5000)), ("scene", "wider than a state file's")),
    (lambda d: d.update({f"carried_{'k' * 60}{i}": np.zeros(5) for i in range(DIRECTORY_LIMIT // 100)}),
     ("zip directory takes", f"at most take {DIRECTORY_LIMIT:,}")),
    (lambda d: d.update({"carried_../x": np.zeros(5)}), ("'carried_../x.npy'", "not a key")),
])
def test_members_that_do_not_belong(good, tmp_path, change, words):
    data = members(good[0])
    change(data)
    refused(write_members(tmp_path / "bad.npz", data), *words)


def test_a_member_that_is_not_an_array_or_is_stored_twice(good, tmp_path):
    data = members(good[0])
    path = write_members(tmp_path / "text.npz", data, extra=[("notes.txt", b"hello")])
    refused(path, "'notes.txt'", "not a key")
    with pytest.warns(UserWarning, match="Duplicate name"):
        path = write_members(tmp_path / "twice.npz", data, extra=[("steps.npy", npy(np.int64(10 ** 9)))])
    refused(path, "steps: stored twice")


def test_a_zip_directory_larger_than_a_state_file_has(good, tmp_path):
    path = write_members(tmp_path / "many.npz", members(good[0]), compression=zipfile.ZIP_STORED,
                         extra=[(f"m{i}.npy", b"") for i in range(5000)])
    refused(path, "zip directory takes", "bytes")


@pytest.mark.parametrize("method, name", [(zipfile.ZIP_BZIP2, "BZIP2"), (zipfile.ZIP_LZMA, "LZMA")])
def test_compression_methods_other_than_deflate_are_refused(good, tmp_path, method, name):
    path = write_members(tmp_path / "bad.npz", members(good[0]), compression=method)
    refused(path, f"compression method {method} ({name}) is not supported")


@pytest.mark.parametrize("offset, value, words", [
    (10, 99, ("positions: compression method 99", "not supported")),  # the method field
    (8, 1, ("positions: encrypted",)),  # the flag bits: encrypted
    (6, 99, ("zip feature", "version 9.9")),  # the version needed to extract: 9.9
])
def test_zip_features_that_state_files_never_use(good, tmp_path, offset, value, words):
    path = write_members(tmp_path / "bad.npz", members(good[0]), compression=zipfile.ZIP_STORED)
    refused(patch_directory(path, "positions.npy", offset, value), *words)


def test_junk_and_truncated_files(good, tmp_path):
    content = good[0].read_bytes()
    cases = {"junk.npz": b"junk, not a zip", "pickle.npz": b"\x80\x04K\x07.", "empty.npz": b"",
             "three.npz": content[:3], "half.npz": content[:len(content) // 2], "end.npz": content[:-200]}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        refused(tmp_path / name, "not a state file")
    data = bytearray(content)
    at = content.find(b"\x93NUMPY", content.find(b"positions.npy"))
    data[at + 200:at + 208] = b"\xff" * 8  # inside the positions data: its CRC no longer holds
    (tmp_path / "crc.npz").write_bytes(bytes(data))
    refused(tmp_path / "crc.npz", "positions: cannot be read", "CRC")


def test_special_files_are_never_opened(tmp_path):
    refused(tmp_path, "not a regular file but a directory")
    refused("/dev/zero", "not a regular file but a device")
    refused(tmp_path / "missing.npz", "cannot be read")
    fifo = tmp_path / "fifo.npz"
    os.mkfifo(fifo)
    try:
        proc = subprocess.run([sys.executable, "-c", CHILD, str(fifo), "-"], capture_output=True, text=True,
                              timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail("read_state blocked on a FIFO")
    message = proc.stdout.splitlines()[-3]
    assert str(fifo) in message and "not a regular file but a named pipe (FIFO)" in message, proc.stdout


@FULL
def test_the_cli_refuses_a_bomb_with_exit_2(bombs, good, tmp_path, capsys):
    header = io.BytesIO()
    npformat.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (10 ** 18, 3)})
    huge = write_members(tmp_path / "huge.npz", {k: v for k, v in members(good[0]).items() if k != "velocities"},
                         extra=[("velocities.npy", header.getvalue())])
    for path, words in ((bombs["extra"], "bytes, more than a state file of the model of scene 'chain'"),
                        (huge, "velocities: header declares shape (1000000000000000000, 3)")):
        start = time.perf_counter()
        assert main(["run", *CHAIN, "--steps", "2", "--restart", str(path)]) == 2
        assert time.perf_counter() - start < 30
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"--restart: {path}: " in err and words in err, err
        assert "Traceback" not in err and "allow_pickle" not in err
