"""Atomic output files: the temporary files a killed run leaves are cleaned up, and
nothing else in an output directory is ever removed."""

import os
import subprocess
import sys

from massspring.cli import main
from massspring.io.files import atomic_output, remove_stale_temporaries, write_json


def dead_pid():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def look_alikes(directory):
    """Files a user may keep in an output directory that look like temporary files
    (of this program's older form, or of other programs), each holding its own name."""
    pid = dead_pid()
    names = [".notes.31337.orig.tmp", f".x.{pid}.y.tmp", ".a.1.b.tmp", f".s.npz.{pid}.abcdefgh.tmp",
             f".s.npz.massspring-{pid}.tmp", f"s.npz.massspring-{pid}-abcdefgh.tmp",
             f".s.npz.massspring-{pid}-abcdefgh.tmp.bak", f".s.npz.massspring-{pid}-ABCDEFGH.tmp",
             ".s.npz.massspring-99999999999999999999-abcdefgh.tmp"]
    for name in names:
        (directory / name).write_text(name)
    return names


def test_user_files_that_look_like_temporaries_survive(tmp_path):
    names = look_alikes(tmp_path)
    folder = tmp_path / f".d.massspring-{dead_pid()}-abcdefgh.tmp"  # a directory of our form
    folder.mkdir()
    (folder / "inside").write_text("kept")
    with atomic_output(tmp_path / "s.npz") as fh:
        fh.write(b"data")
    write_json(tmp_path / "m.json", {"a": 1})
    for name in names:
        assert (tmp_path / name).read_text() == name
    assert (folder / "inside").read_text() == "kept"
    assert (tmp_path / "s.npz").read_bytes() == b"data"


def test_the_cli_keeps_user_files(tmp_path):
    names = look_alikes(tmp_path)
    precious = tmp_path / ".notes.31337.orig.tmp"
    precious.write_text("precious")
    names.remove(precious.name)
    assert main(["run", "spring", "--steps", "5", "--quiet", "--out", str(tmp_path / "s.npz")]) == 0
    assert precious.read_text() == "precious"
    for name in names:
        assert (tmp_path / name).read_text() == name


def test_only_our_stale_temporaries_are_removed(tmp_path):
    stale = tmp_path / f".s.npz.massspring-{dead_pid()}-abc_1234.tmp"
    live = tmp_path / f".s.npz.massspring-{os.getpid()}-abc_1234.tmp"
    stale.write_text("half")
    live.write_text("in progress")
    remove_stale_temporaries(tmp_path)
    assert not stale.exists() and live.read_text() == "in progress"


def test_a_link_named_like_ours_is_not_followed(tmp_path):
    target = tmp_path / "target.txt"
    target.write_text("kept")
    link = tmp_path / f".s.npz.massspring-{dead_pid()}-abcdefgh.tmp"
    link.symlink_to(target)
    remove_stale_temporaries(tmp_path)
    assert target.read_text() == "kept" and link.is_symlink()
