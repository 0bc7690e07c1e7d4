"""Writing a file so that a reader sees the old version or the new one, never half of one.

The one atomic writer of freeform (checkpoints, design records, ``run_info.json``): a temporary file in the target's
directory, flushed and fsynced, given the permissions an ordinary ``open()`` would give, renamed over the target
(``os.replace`` is atomic on POSIX and Windows), and the directory fsynced so that the rename survives a crash.
:func:`copy_atomically` gives a finished file a second name the same way (a numbered checkpoint beside ``last.pt``
is a copy of its bytes, not a second serialisation of a dataset-sized state).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def write_atomically(path: str | os.PathLike[str], write: Callable[[BinaryIO], None]) -> Path:
    """Create or replace ``path`` with what ``write(file)`` writes, atomically and durably; returns the path.

    On any failure (an ``OSError`` from a full disk, a quota, a vanished mount; or ``write``'s own exception) the
    temporary file is removed, ``path`` is left as it was, and the exception propagates.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())  # the bytes are on disk before the rename makes them visible
        # mkstemp creates the file 0600; a run directory on a shared cluster is read by the group (umask decides).
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def copy_atomically(source: str | os.PathLike[str], path: str | os.PathLike[str]) -> Path:
    """Create or replace ``path`` with a copy of ``source``'s bytes, atomically (:func:`write_atomically`); returns
    the path. A copy, not a hard link: a user who rolls ``last.pt`` back with ``cp`` writes into the file in place,
    and a link would carry that into the numbered checkpoint too."""
    def copy(f: BinaryIO) -> None:
        with open(source, "rb") as src:
            shutil.copyfileobj(src, f, 16 << 20)

    return write_atomically(path, copy)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # e.g. Windows cannot open directories; the rename is still atomic there
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


__all__ = ["copy_atomically", "write_atomically"]
