"""Atomic output: a reader never sees a half-written file, and a failed write leaves the old
file (or nothing) in place. The temporary file lives in the target's folder so that ``os.replace``
is a same-filesystem rename. A folder of files is replaced the same way, as a set (``staged_folder``)."""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from sghr_gtsam.errors import InputError

# mkstemp creates files 0600 and mkdtemp folders 0700; finished outputs get the usual 0666 / 0777 & ~umask instead.
# The umask can only be read by setting it, so read it once at import rather than on every write.
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
    ``list_scans`` never picks it up. Missing folders are created; a symbolic link is followed (the file it leads
    to is replaced, the link stays); ``InputError`` when ``path`` is a folder, a device, a pipe or a socket (a
    rename would put a file in its place: ``/dev/null`` replaced, as root), or cannot be written.
    """
    path = Path(os.path.realpath(path))
    folder = path.parent
    if path.is_dir():
        raise InputError(f"cannot write {path}: it is a folder")
    if path.exists() and not path.is_file():
        raise InputError(f"cannot write {path}: it is not a regular file (a device, pipe or socket)")
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


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _remove_stale(out: Path, carry: str | None) -> None:
    """Remove what stopped runs left beside ``out``: staging folders (their ``carry`` subfolder, if ``out`` has none,
    goes back into ``out``) and, when the swap's fallback was stopped between its two renames, restore the previous
    results."""
    pattern = re.compile(rf"^\.{re.escape(out.name)}\.(tmp|old)-(\d+)-")
    if not out.parent.is_dir():
        return
    for path in sorted(out.parent.iterdir()):
        match = pattern.match(path.name)
        if not match or not path.is_dir() or _alive(int(match.group(2))) and int(match.group(2)) != os.getpid():
            continue
        if match.group(1) == "old" and not out.exists():
            os.rename(path, out)
            continue
        if carry and (path / carry).is_dir() and out.is_dir() and not (out / carry).exists():
            os.rename(path / carry, out / carry)
        shutil.rmtree(path, ignore_errors=True)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap two folders in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where that is not available."""
    renameat2 = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)
    if renameat2 is None:
        return False
    return renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0


def mounted(out: Path, carry: str | None = None) -> str | None:
    """Why ``staged_folder`` cannot swap results into ``out``: it, or its ``carry`` subfolder, is a mount point (the
    swap renames both, which a mount point refuses: EBUSY, or EXDEV across filesystems); None if neither is one."""
    out = Path(os.path.realpath(out))
    if os.path.ismount(out):
        return (
            f"{out} is a mount point: the results are swapped in by renaming the folder, which a mount point "
            f"refuses; write them into a folder inside it (e.g. {out / 'results'})"
        )
    if carry and os.path.ismount(out / carry):
        return (
            f"{out / carry} is a mount point: the results are swapped in by renaming the folder with its "
            f"{carry}, which a mount point refuses; mount the disk at a folder that holds {out.name} instead"
        )
    return None


def _swap_in(stage: Path, out: Path, carry: str | None) -> None:
    """Make the finished ``stage`` folder ``out``, carrying ``out``'s ``carry`` subfolder over; the old folder is
    removed. ``InputError`` when one of them is a mount point (``mounted``; a bind mount on the same filesystem
    is seen only here), ``out`` left as it was."""
    fsync_dir(stage)
    old = stage.with_name(stage.name.replace(".tmp-", ".old-", 1))
    carried = False
    try:
        if not out.exists():
            os.rename(stage, out)
        else:
            if carry and os.path.lexists(out / carry) and not os.path.lexists(stage / carry):  # a file too
                os.rename(out / carry, stage / carry)
                carried = True
            if not _exchange(stage, out):  # two renames; a stop between them is repaired by the next run
                os.rename(out, old)
                os.rename(stage, out)
                stage = old
            shutil.rmtree(stage, ignore_errors=True)  # the old folder, now at the staging name
    except OSError as e:
        with contextlib.suppress(OSError):  # put back what moved: the old results, then their cache
            if not out.exists() and old.exists():
                os.rename(old, out)
            if carried and not os.path.lexists(out / carry):
                os.rename(stage / carry, out / carry)
        if e.errno in (errno.EBUSY, errno.EXDEV):
            raise InputError(
                mounted(out, carry)
                or f"cannot swap the results into {out}: {e.filename} is a mount "
                "point (a bind mount?), which cannot be renamed"
            ) from None
        raise InputError(
            f"cannot swap the results into {out}: {e.strerror or e} ({e.filename}); the earlier "
            "results are left as they were"
        ) from None
    fsync_dir(out.parent)


def _folders(top: Path) -> set[str]:
    return {d for d, _, _ in os.walk(top)}


def _remove_empty(out: Path, carry: str | None, created: bool, existed: set[str]) -> None:
    """After a failed run: the folders of ``out``'s ``carry`` that hold nothing and were not there before it
    (``existed``: a ``carry`` linked to a user's folder keeps its empty sub-folders), and ``out`` itself if the run
    created it and left it empty (a first run that failed before storing anything leaves no
    ``OUT/cache/features``). Entries a failed run stored stay, for the next run to resume from."""
    folders = [Path(d) for d, _, _ in os.walk(out / carry, topdown=False) if d not in existed] if carry else []
    for folder in folders + ([out] if created else []):
        try:
            folder.rmdir()
        except OSError:  # not empty, or a mount point
            pass


def _lock(out: Path) -> int | None:
    """The lock of the one writer of ``out``: an ``flock`` on ``.<name>.lock`` beside it, holding the writer's pid;
    its descriptor (None where the file system has no locks). ``InputError`` when another process holds it."""
    path = out.with_name(f".{out.name}.lock")
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666 & ~_UMASK)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip()
            os.close(fd)
            raise InputError(
                f"{out} is being written by another run{f' (pid {holder})' if holder else ''}: wait for "
                f"it to end, or choose another output folder"
            ) from None
        except OSError as e:
            os.close(fd)
            if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP):
                return None
            raise
        try:  # the holder removes the file as it lets go: a lock on that file is no lock on the path
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


def _unlock(out: Path, fd: int | None) -> None:
    if fd is not None:
        with contextlib.suppress(OSError):
            os.unlink(out.with_name(f".{out.name}.lock"))
        os.close(fd)


@contextlib.contextmanager
def staged_folder(out: Path, carry: str | None = None) -> Iterator[Path]:
    """A new folder beside ``out`` to write a folder's files into; swapped in as ``out`` when the block completes,
    removed when it raises (also on KeyboardInterrupt), so a stop at any point leaves ``out`` as it was. ``carry``:
    a subfolder of ``out`` written in place during the block (a resume cache) and kept across the swap; its folders
    left empty by a block that raised are removed (``_remove_empty``). Stale
    folders of stopped runs are removed first. A symbolic link ``out`` is followed: the folder it leads to is
    replaced, the link stays. One writer of ``out`` at a time: a second one gets ``InputError`` (``_lock``)."""
    out = Path(os.path.realpath(out))
    created = not out.exists()
    existed = _folders(out / carry) if carry else set()
    lock = None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        lock = _lock(out)
        _remove_stale(out, carry)
        stage = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-{os.getpid()}-"))
        os.chmod(stage, 0o777 & ~_UMASK)  # mkdtemp makes it 0700: the results are for others to read as well
    except OSError as e:
        _unlock(out, lock)
        if e.errno == errno.ENAMETOOLONG and len(os.fsencode(out.name)) <= 255:  # the staging name is longer
            raise InputError(
                f"output folder name {out.name[:20]}... is {len(os.fsencode(out.name))} bytes: the "
                f"results are staged beside it as .{out.name[:8]}...tmp-PID-XXXXXXXX, a name up to 22 "
                f"bytes longer, which the file system refuses; choose a shorter name"
            ) from None
        raise InputError(f"cannot write the output folder {out}: {e.strerror or e}") from None
    except BaseException:
        _unlock(out, lock)
        raise
    try:
        yield stage
        _swap_in(stage, out, carry)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        _remove_empty(out, carry, created, existed)
        raise
    finally:
        _unlock(out, lock)
