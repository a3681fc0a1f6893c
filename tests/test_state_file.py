"""State files (``--out``, ``--restart``) are checked before their data is read: no file
can make a restart allocate more than its model's arrays, block, or show a traceback."""

import io
import os
import subprocess
import sys
import tracemalloc
import zipfile

import numpy as np
import pytest
from numpy.lib import format as npformat

import massspring as ms
from massspring.cli import main
from massspring.io.state import read_state, write_state

CHAIN = ["chain", "--set", "count=5", "--quiet"]


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A real state file of the 5-particle chain after 3 implicit steps, and its Simulation."""
    path = tmp_path_factory.mktemp("state") / "good.npz"
    sim = ms.load_scene("chain").with_params(count=5).simulation("implicit")
    for _ in range(3):
        sim.step()
    write_state(sim, path, scene="chain")
    return path, sim


def members(path):
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


def write_members(path, arrays, compression=zipfile.ZIP_DEFLATED, extra=()):
    """An npz of ``arrays`` (name -> array) plus ``extra`` raw (name, bytes) members."""
    with zipfile.ZipFile(path, "w", compression) as archive:
        for name, arr in arrays.items():
            buffer = io.BytesIO()
            npformat.write_array(buffer, np.asanyarray(arr), allow_pickle=True)
            archive.writestr(f"{name}.npy", buffer.getvalue())
        for name, data in extra:
            archive.writestr(name, data)
    return path


def zero_bomb(path, name, shape, base=None):
    """``base``'s members and a member ``name`` of ``shape`` float64 zeros, streamed and
    deflated (a few MB on disk, never whole in this process)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for key, arr in (base or {}).items():
            if key != name:
                buffer = io.BytesIO()
                npformat.write_array(buffer, arr)
                archive.writestr(f"{key}.npy", buffer.getvalue())
        with archive.open(f"{name}.npy", "w", force_zip64=True) as fh:
            npformat.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": shape})
            chunk, left = bytes(1 << 22), int(np.prod(shape)) * 8
            while left:
                fh.write(chunk[:min(left, len(chunk))])
                left -= min(left, len(chunk))
    return path


def refused(path, *words, model=None):
    """read_state's message for ``path``, checked to name the file and each of ``words``."""
    with pytest.raises(ValueError) as info:
        read_state(path, model)
    message = str(info.value)
    assert str(path) in message and "allow_pickle" not in message and "unsafe" not in message, message
    for word in words:
        assert word in message, (word, message)
    return message


def test_round_trip_is_bitwise(good):
    path, sim = good
    state = read_state(path, sim.model)
    assert state.positions.tobytes() == sim.positions.tobytes()
    assert state.velocities.tobytes() == sim.velocities.tobytes()
    assert (state.steps, state.dt, state.integrator, state.scene) == (3, sim.dt, "implicit", "chain")
    assert state.fingerprint == sim.model.fingerprint()


def test_a_deflated_bomb_is_refused_without_reading_it(good, tmp_path):
    path, sim = good
    base = members(path)
    extra = zero_bomb(tmp_path / "extra.npz", "extra", (50_000_000,), base)
    positions = zero_bomb(tmp_path / "positions.npz", "positions", (16_666_667, 3), base)
    assert os.path.getsize(extra) < 5e6 and os.path.getsize(positions) < 5e6
    tracemalloc.start()
    try:
        refused(extra, "extra", "not a member")
        refused(positions, "holds 16666667 particles", model=sim.model)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6  # the 400 MB arrays were never decompressed


def test_header_shapes_that_disagree_with_the_stored_size(good, tmp_path):
    path, _ = good
    data = members(path)
    buffer = io.BytesIO()
    npformat.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False, "shape": (10 ** 18,)})
    huge = buffer.getvalue() + bytes(64)
    with zipfile.ZipFile(tmp_path / "huge.npz", "w") as archive:
        for key, arr in data.items():
            if key != "velocities":
                out = io.BytesIO()
                npformat.write_array(out, arr)
                archive.writestr(f"{key}.npy", out.getvalue())
        archive.writestr("velocities.npy", huge)
    refused(tmp_path / "huge.npz", "velocities", "header declares shape")


@pytest.mark.parametrize("change, words", [
    (lambda d: d.update(extra=np.zeros(3)), ("'extra.npy'", "not a member")),
    (lambda d: d.pop("dt"), ("dt", "missing")),
    (lambda d: d.update(positions=np.array([object()] * 15, dtype=object).reshape(5, 3)), ("positions", "dtype")),
    (lambda d: d.update(positions=np.zeros((5, 2))), ("positions", "expected shape")),
    (lambda d: d.update(carried_x=np.zeros((7, 3))), ("carried_x", "a row per particle")),
    (lambda d: d.update(triangles=np.zeros((2, 4), dtype=np.int64)), ("triangles", "expected shape")),
    (lambda d: d.update(velocities=np.full((5, 3), np.nan)), ("velocities", "non-finite")),
])
def test_members_that_do_not_belong(good, tmp_path, change, words):
    data = members(good[0])
    change(data)
    refused(write_members(tmp_path / "bad.npz", data), *words)


@pytest.mark.parametrize("method", [zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA])
def test_other_compression_methods_are_refused(good, tmp_path, method):
    path = write_members(tmp_path / "bad.npz", members(good[0]), compression=method)
    refused(path, "compression method", str(method))


def test_junk_truncated_and_special_files(good, tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"PK\x03\x04" + bytes(100))
    refused(junk, "not a state file")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good[0].read_bytes()[:-200])
    refused(truncated, "not a state file")
    refused(tmp_path, "not a regular file")
    refused(tmp_path / "missing.npz", "cannot be read")
    fifo = tmp_path / "fifo.npz"
    os.mkfifo(fifo)
    script = f"from massspring.io.state import read_state\nread_state({str(fifo)!r})\n"
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and "not a regular file" in proc.stderr  # raised at once: no reader blocked


def test_the_cli_refuses_a_bomb_with_exit_2(good, tmp_path, capsys):
    bomb = zero_bomb(tmp_path / "bomb.npz", "extra", (50_000_000,), members(good[0]))
    assert main(["run", *CHAIN, "--steps", "2", "--restart", str(bomb)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--restart" in err and "extra" in err and "Traceback" not in err
