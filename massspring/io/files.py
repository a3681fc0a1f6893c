"""Output files written atomically: a reader never sees a half-written file.

A file is written under a temporary name ``.NAME.massspring-PID-XXXXXXXX.tmp`` in the
same directory (PID: the writing process, X: random) and renamed when complete. A
process killed mid-write (SIGKILL) leaves its temporary file behind; the next write to
that directory removes temporary files of this form whose process is gone. No other
file is ever removed: only regular files (not links or directories) whose whole name
has this form, which only this module writes.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import stat
import tempfile
from pathlib import Path

TAG = "massspring"
_TEMP = re.compile(rf"^\..+\.{TAG}-([0-9]+)-[a-z0-9_]{{8}}\.tmp$")


def _temp_name(path):
    """mkstemp's arguments for a temporary file of ``path`` (its random part is 8 of a-z0-9_)."""
    return dict(prefix=f".{path.name}.{TAG}-{os.getpid()}-", suffix=".tmp", dir=path.parent)


_CLEANED = set()  # directories this process has cleaned: later writes there skip the scan


def remove_stale_temporaries(directory):
    """Delete the temporary files of this module in ``directory`` whose writing process
    has ended (see the module's docstring for which files those are); once per
    directory and process, so that writing many files into one costs no rescans."""
    key = os.path.realpath(directory)
    if key in _CLEANED:
        return
    _CLEANED.add(key)
    try:
        entries = list(Path(directory).iterdir())
    except OSError:
        return
    for entry in entries:
        match = _TEMP.match(entry.name)
        if match and 0 < int(match.group(1)) < 2 ** 31 and not _alive(int(match.group(1))):
            with contextlib.suppress(OSError):
                if stat.S_ISREG(entry.lstat().st_mode):
                    entry.unlink()


def _alive(pid):
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def atomic_path(path):
    """A temporary path in ``path``'s directory for a writer that wants a file name
    (meshio): the file is renamed to ``path`` when the block completes, and removed if
    the block raises (the exception propagates; an existing ``path`` is untouched)."""
    path = Path(path)
    remove_stale_temporaries(path.parent)
    fd, tmp = tempfile.mkstemp(**_temp_name(path))
    os.close(fd)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes it private; give it a normal file's mode
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_output(path):
    """Open ``path`` for binary writing under a temporary name in the same directory
    (``atomic_path``): a reader never sees it half-written."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        yield fh


def check_writable(path, name, suffixes=None) -> Path:
    """Refuse, before any long work, an output path that ``atomic_output`` could not write:
    raises ValueError starting with ``name`` (the option or argument) and saying why.

    ``suffixes``: the accepted file name endings (e.g. (".gif",)). The check creates and
    removes the temporary file a write would use, which catches missing or read-only
    directories, directories or pipes in place of files, names too long and special file
    systems.
    """
    if path is None or str(path) == "":
        raise ValueError(f"{name}: empty path")
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise ValueError(f"{name}: {str(path)!r} must end in {' or '.join(suffixes)}")
    try:
        if path.is_dir():
            raise ValueError(f"{name}: {str(path)!r} is a directory")
        if path.exists() and not path.is_file():  # a FIFO would block a reader or an appending writer
            raise ValueError(f"{name}: {str(path)!r} is not a regular file (a pipe, socket or device)")
        if not path.parent.is_dir():
            raise ValueError(f"{name}: directory {str(path.parent)!r} does not exist")
        fd, tmp = tempfile.mkstemp(**_temp_name(path))
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise ValueError(f"{name}: cannot write {str(path)!r}: {exc.strerror or exc}") from None
    return path


def write_json(path, data):
    """Write ``data`` to ``path`` as indented JSON, atomically, creating its folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as fh:
        fh.write(json.dumps(data, indent=1).encode())
