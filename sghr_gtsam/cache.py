"""The resume cache: what the parallel stages computed, on disk in ``OUT/cache`` (``io.results.CACHE``), so that a
run killed in the middle and started again redoes only what is missing.

One file per result, ``OUT/cache/<kind>/<key>.npz`` (arrays only, no pickle), written atomically as each result
arrives (``io.atomic``): a scan's features (``features``) and refinement grids (``pyramids``), a pair's global
registration (``pairs``) and its re-registration from a synchronized guess (``refined``: refinement and loop
closures). A key is a digest of everything that made the result: the scan's points (``ScanStats.digest``), its given
keypoints and its centre, the parameters (voxel, radii, matcher, ICP distance, seed, the guess), the source of the
modules that compute them and the versions of the libraries they call; a change to any of them misses. An entry
that cannot be read (truncated, damaged, no regular file: a folder, a pipe, a link) is computed again and replaced,
never written through a link (``_clear``). Nothing removes old entries: delete
the folder to reclaim its space. During a run the features and grids are read back from these files where a task
needs them (``store``; a run without a cache writes the same files into a temporary folder).
"""

from __future__ import annotations

import hashlib
import os
import stat
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sghr_gtsam.executor import parallel_map
from sghr_gtsam.io.atomic import atomic_write

if TYPE_CHECKING:
    from sghr_gtsam.config import Config
    from sghr_gtsam.types import Scan

FORMAT = 2
"""Bumped when what a file holds changes meaning (2: each entry holds its own key)."""
KINDS = ("features", "pyramids", "pairs", "refined")
_SOURCES = (
    "features/local.py",
    "features/learned.py",
    "weights/patch_rooms.npz",
    "registration/pairwise.py",
    "registration/estimators.py",
    "registration/information.py",
    "registration/refine.py",
)
"""The modules whose code (and constants) and the weights that make the cached results."""
_LIBRARIES = ("numpy", "scipy", "open3d-cpu", "small-gicp", "kiss-matcher")
_STALE_SECONDS = 60.0
"""A write's temporary file older than this belongs to a killed run (a write takes milliseconds)."""


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "none"


_CODE: str | None = None


def _code() -> str:
    """Digest of the computing modules' source and the libraries' versions (once per process)."""
    global _CODE
    if _CODE is None:
        root = Path(__file__).resolve().parent
        h = hashlib.sha256()
        for name in _SOURCES:
            h.update((root / name).read_bytes())
        h.update(" ".join(_version(lib) for lib in _LIBRARIES).encode())
        _CODE = h.hexdigest()
    return _CODE


def _key(*parts: Any) -> str:
    h = hashlib.sha256(f"{FORMAT} {_code()}".encode())
    for part in parts:
        data = np.ascontiguousarray(part).tobytes() if isinstance(part, np.ndarray) else repr(part).encode()
        h.update(len(data).to_bytes(8, "little") + data)
    return h.hexdigest()


def scan_key(scan: Scan, voxel: float, config: Config) -> str:
    """A scan's features: its points, given keypoints and centre, the voxel, the radii and the descriptor."""
    given = scan.keypoints
    return _key(
        "scan",
        scan.statistics().digest,
        None if given is None else given.points,
        None if given is None else given.descriptors,
        scan.centre,
        float(voxel),
        config.normal_radius,
        config.fpfh_radius,
        config.descriptor,
    )


def pyramid_key(scan: str) -> str | None:
    """A scan's refinement grids, from its ``scan_key`` (None: not cached)."""
    return _key("pyramid", scan) if scan else None


def pair_key(a: str, b: str, config: Config) -> str | None:
    """A pair's global registration, from its scans' keys (None when one is not known: not cached)."""
    return _key("pair", a, b, config.matcher, config.icp_distance, config.seed, config.inlier_bar) if a and b else None


def refined_key(a: str, b: str, guess: np.ndarray, icp_distance: float, min_inliers: int) -> str | None:
    """A pair's re-registration from ``guess``, from its scans' keys (None when one is not known); ``min_inliers``
    decides whether it carries an information (``refine.refine_pair``)."""
    return _key("refined", a, b, np.asarray(guess, dtype=np.float64), icp_distance, min_inliers) if a and b else None


# --- what a file holds -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Kind:
    """One kind of entry, defined beside its result's type: the folder ``name`` (one of ``KINDS``), and how a
    result becomes arrays (``encode``; None: not stored) and comes back from them (``decode``, raising on arrays
    that do not make one). Module-level functions, so that a ``store.Stored`` handle pickles with its kind."""

    name: str
    encode: Callable[[Any], dict[str, np.ndarray] | None]
    decode: Callable[[dict[str, np.ndarray]], Any]


def entry_path(folder: str | Path, name: str, key: str) -> Path:
    """Where the result of the kind ``name`` under ``key`` lives in ``folder``."""
    return Path(folder) / name / f"{key}.npz"


_KEY = "_key"
"""The array of an entry that holds the key it was stored under: a file renamed or copied under another key (two
entries swapped) is another scan's or pair's result, which its readable arrays alone would not betray."""


def read_entry(path: Path, kind: Kind) -> Any:
    """The result of ``kind`` stored at ``path``, ``MISS`` when there is none; raises when it cannot be read, is
    not a regular file (a folder; a pipe, a device or a symbolic link is never opened) or holds another key's
    result."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return MISS
    if not stat.S_ISREG(mode):
        raise ValueError(f"{path.name} is not a regular file")
    with np.load(path, allow_pickle=False) as archive:
        arrays = {name: archive[name] for name in archive.files}  # reading each checks its CRC
    if str(arrays.pop(_KEY, "")) != path.stem:
        raise ValueError(f"{path.name} holds another entry's result")
    return kind.decode(arrays)


class Cache:
    """The cache in ``folder`` (created on the first write) and what this run took from it: ``counts[kind]`` the
    results ``cached`` (read back) and ``computed``, ``unreadable`` the entries that could not be read."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.counts = {kind: {"cached": 0, "computed": 0} for kind in KINDS}
        self.unreadable = 0
        self._remove_stale()

    def report(self) -> dict:
        """What report.json says of the cache."""
        return {**self.counts, "unreadable": self.unreadable}

    def _path(self, kind: Kind, key: str) -> Path:
        return entry_path(self.folder, kind.name, key)

    def _remove_stale(self) -> None:
        """Temporary files of writes a killed run left (``io.atomic``'s hidden names)."""
        if not self.folder.is_dir():
            return
        now = time.time()
        for path in self.folder.glob("*/.*.tmp.npz"):
            try:
                if now - path.stat().st_mtime > _STALE_SECONDS:
                    path.unlink()
            except OSError:
                pass

    def load(self, kind: Kind, key: str | None) -> Any:
        """The stored result, or ``MISS`` (also when its file cannot be read)."""
        if key is None:
            return MISS
        try:
            return read_entry(self._path(kind, key), kind)
        except Exception:  # noqa: BLE001 - a damaged entry is recomputed, whatever broke while reading it
            self.unreadable += 1
            return MISS

    def store(self, kind: Kind, key: str | None, result: Any) -> None:
        arrays = None if key is None else kind.encode(result)
        if arrays is not None:
            path = self._path(kind, key)
            _clear(path)
            with atomic_write(path, "wb") as f:
                np.savez(f, **arrays, **{_KEY: np.array(key)})

    def map(
        self,
        kind: Kind,
        fn: Callable,
        shared: Any,
        tasks: Sequence,
        keys: Sequence[str | None],
        workers: int | None,
        on_result: Callable[[int, Any], None] | None = None,
        ray: str | None = None,
        keep: Callable[[Any], Any] | None = None,
    ) -> list:
        """``executor.parallel_map(fn, shared, tasks, workers, on_result, ray, keep)`` for the tasks whose ``keys``
        miss the cache, each result stored as it arrives; the others read back. ``on_result`` is told of the
        cached results first, then of the computed ones as they arrive; ``keep(result)`` is what the list holds
        (default: the result)."""
        results: list = [MISS] * len(tasks)
        todo = []
        for k, key in enumerate(keys):
            result = self.load(kind, key)
            if result is MISS:
                todo.append(k)
                continue
            if on_result is not None:
                on_result(k, result)
            results[k] = result if keep is None else keep(result)

        def arrived(m: int, result: Any) -> None:
            self.store(kind, keys[todo[m]], result)
            if on_result is not None:
                on_result(todo[m], result)

        for k, result in zip(todo, parallel_map(fn, shared, [tasks[k] for k in todo], workers, arrived, ray, keep)):
            results[k] = result
        self.counts[kind.name]["cached"] += len(tasks) - len(todo)
        self.counts[kind.name]["computed"] += len(todo)
        return results


def _clear(path: Path) -> None:
    """Make way for an entry at ``path`` where something that is no entry's file stands: a symbolic link is removed
    (written through, it replaced the user's file it leads to), so are a pipe, a device or a socket; a folder is
    moved aside to a hidden name (``.<name>.folder-XXXX``: what it holds is kept)."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if stat.S_ISDIR(mode):
        os.rename(path, tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.folder-"))
    elif not stat.S_ISREG(mode):
        path.unlink()


def unusable(folder: str | Path) -> str | None:
    """Why ``folder`` cannot hold a cache, or None: it, or the folder of one of its kinds, is something else than a
    folder (a file, a broken link). The run then keeps no cache rather than failing at its first write."""
    folder = Path(folder)
    for path in (folder, *(folder / kind for kind in KINDS)):
        if os.path.lexists(path) and not path.is_dir():
            return f"{path} is not a folder"
    return None


MISS = object()
"""``Cache.load``'s answer for a result it does not hold."""


def cached_map(
    cache: Cache | None,
    kind: Kind,
    fn: Callable,
    shared: Any,
    tasks: Sequence,
    keys: Sequence[str | None],
    workers: int | None,
    on_result: Callable[[int, Any], None] | None = None,
    ray: str | None = None,
    keep: Callable[[Any], Any] | None = None,
) -> list:
    """``cache.map(...)``, or ``executor.parallel_map`` of every task without a cache."""
    if cache is None:
        return parallel_map(fn, shared, tasks, workers, on_result, ray, keep)
    return cache.map(kind, fn, shared, tasks, keys, workers, on_result, ray, keep)
