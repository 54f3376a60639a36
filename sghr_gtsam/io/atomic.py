"""Atomic file output: a reader never sees a half-written file, and a failed write leaves the old
file (or nothing) in place. The temporary file lives in the target's folder so that ``os.replace``
is a same-filesystem rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from ..types import InputError

# mkstemp creates files 0600; finished outputs get the usual 0666 & ~umask instead. The umask can
# only be read by setting it, so read it once at import rather than on every write.
_UMASK = os.umask(0)
os.umask(_UMASK)


def fsync_dir(folder: Path) -> None:
    """Make the rename itself durable (POSIX); not possible on every platform, hence best effort."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for writers that take a file name (open3d, rerun).

    The temporary name ends with ``path``'s own suffix, because those writers choose the format
    from the extension. On success the file is fsynced and renamed onto ``path``; on an exception
    it is removed and the exception propagates. The temporary name starts with a dot, so
    ``list_scans`` never picks it up. Missing folders are created; ``InputError`` when ``path`` is a folder or
    cannot be written.
    """
    path = Path(path)
    folder = path.parent
    if path.is_dir():
        raise InputError(f"cannot write {path}: it is a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=f".tmp{path.suffix}")
    except OSError as e:  # the temporary's name would only confuse: say which output could not be written
        raise InputError(f"cannot write {path}: {e.strerror or e}") from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(folder)


@contextlib.contextmanager
def atomic_write(
    path: str | Path, mode: str = "w", encoding: str | None = None, newline: str | None = None
) -> Iterator[IO[Any]]:
    """``open(path, mode, encoding=..., newline=...)`` that only replaces ``path`` when the block
    completes without error.

    ``mode``: "w"/"wt" (text, UTF-8 unless ``encoding`` is given) or "wb". ``newline=""`` is what
    the csv module wants.
    """
    if mode not in ("w", "wt", "wb"):
        raise ValueError(f"atomic_write supports modes 'w', 'wt' and 'wb', not {mode!r}")
    if "b" not in mode and encoding is None:
        encoding = "utf-8"
    with atomic_path(path) as tmp:
        with open(tmp, mode, encoding=encoding, newline=newline) as f:
            yield f
