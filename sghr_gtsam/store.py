"""Each scan's features and refinement grids during a run: on disk, read back where a task needs them, so that no
process holds every scan's and a run's peak memory grows with the scans in flight, not with their number.

A stage's results are written as they arrive, as ``cache.Cache`` files (``<folder>/<kind>/<key>.npz``): into the
resume cache (``OUT/cache``) when the run keeps one, otherwise into a temporary folder (``Store``; ``pipeline.run``
puts it in the run's staging folder) removed when the run ends, fails or is stopped. The parallel stages send their
workers a ``Stored`` sequence instead of arrays: the folder and each scan's key, a few bytes a scan. Its item ``[k]``
is read from the folder through a memory of the last items used, ``LRU_BYTES`` per process; pair tasks run in
``pair_order``, so that a worker reads a scan once for the run of pairs that share it.

In the process that runs the pipeline, an entry that is missing or cannot be read is computed again from its scan
(and written back while the store is open): ``RunResult.features`` keeps working after a run's temporary folder is
removed. A worker has no scans: it raises ``InputError`` instead. On a Ray cluster of several machines the workers
read the folder where the pipeline wrote it, so it (like the scans) must be on a filesystem every node mounts at
the same path (``pipeline.register`` without a cache: give it ``store=Store(None, scratch=<such a folder>)``); a
worker that does not see it says so.
"""

from __future__ import annotations

import shutil
import socket
import tempfile
import weakref
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sghr_gtsam.cache import MISS, Cache, Kind, cached_map, entry_path, read_entry
from sghr_gtsam.types import InputError

LRU_BYTES = 512 * 2**20
"""What each process keeps of the items it read (``ScanFeatures``, ``Pyramid``, with the search structures its tasks
built on them). A pair task on 1-million-point room scans holds ~15 MB a scan (features and both pyramid levels),
so that is ~34 scans; a 3DMatch fragment ~8.5 MB, so a 60-fragment scene fits whole, and a run's workers, kept from
stage to stage (``executor.kept_workers``), build each scan's search structures and GICP clouds once instead of
once a stage (~10-25 ms a scan and level; 256 MB held half such a scene, gaining nothing:
the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md)."""


class _Lru:
    """Items by key; when an item is read, the least recently used are dropped while the items hold more than
    ``limit`` bytes (their ``nbytes`` as of then: search structures built since they were read count). The newest
    stays however large. The bytes are summed on a read only, not on every use: summing them on each use cost
    O(items) a call, 96 of a 500-scan building's 370 profiled seconds."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._items: OrderedDict[Any, Any] = OrderedDict()

    def get(self, key: Any, load: Callable[[], Any]) -> Any:
        item = self._items.get(key)
        if item is not None:
            self._items.move_to_end(key)
            return item
        item = self._items[key] = load()
        total = sum(v.nbytes for v in self._items.values())
        while total > self.limit and len(self._items) > 1:
            total -= self._items.popitem(last=False)[1].nbytes
        return item


_LRU = _Lru(LRU_BYTES)


@dataclass(frozen=True, eq=False)
class Stored(Sequence):
    """Scan k's stored ``kind`` at ``[k]`` (``features.local.FEATURES``, ``registration.refine.PYRAMIDS``), read
    from ``folder`` through this process's memory of ``LRU_BYTES``. Pickles as ``folder``, ``kind`` and ``keys``;
    where it was made it also recomputes a missing entry (``compute(k)``, module doc)."""

    folder: str
    kind: Kind
    keys: tuple[str, ...]
    _store: Store | None = field(default=None, repr=False)
    _compute: Callable[[int], Any] | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.keys)

    def __getitem__(self, k: int) -> Any:  # type: ignore[override] - no slices
        key = self.keys[k]
        return _LRU.get((self.folder, self.kind.name, key), lambda: self._read(k, key))

    def __reduce__(self) -> tuple:
        return Stored, (self.folder, self.kind, self.keys)

    def _read(self, k: int, key: str) -> Any:
        if self._store is None or self._compute is None:
            return _read_elsewhere(Path(self.folder), self.kind, key)
        disk = self._store.disk
        item = disk.load(self.kind, key) if self._store.open else MISS
        if item is MISS:
            item = self._compute(k)
            if self._store.open:
                disk.store(self.kind, key, item)
                disk.counts[self.kind.name]["computed"] += 1
        return item


def _read_elsewhere(folder: Path, kind: Kind, key: str) -> Any:
    """An entry read in a worker, which cannot compute it again."""
    path = entry_path(folder, kind.name, key)
    try:
        item = read_entry(path, kind)
    except Exception:  # noqa: BLE001 - a damaged entry, whatever broke while reading it
        item = MISS
    if item is not MISS:
        return item
    if not folder.is_dir():
        raise InputError(
            f"{folder} does not exist on {socket.gethostname()}: on a Ray cluster of several machines "
            f"the output folder must be on a filesystem every node mounts at the same path"
        )
    raise InputError(f"{path} is missing or damaged: was it changed while the run was using it?")


class Store:
    """A run's store, in the process that runs it: the folder of ``cache`` (``cache.Cache``), or without one a
    temporary folder in ``scratch`` (default: the system's), removed by ``close`` or, at the latest, when the store
    is garbage collected or the interpreter exits. ``disk``: the ``Cache`` that reads and writes the entries."""

    def __init__(self, cache: Cache | None, scratch: str | Path | None = None) -> None:
        self.cache = cache
        self._removal: weakref.finalize | None = None
        if cache is None:
            folder = Path(tempfile.mkdtemp(prefix=".store-", dir=scratch))
            self._removal = weakref.finalize(self, shutil.rmtree, folder, ignore_errors=True)
            cache = Cache(folder)
        self.disk = cache

    @property
    def folder(self) -> Path:
        return self.disk.folder

    @property
    def open(self) -> bool:
        """Whether its folder is there: a temporary one until ``close``."""
        return self._removal is None or self._removal.alive

    def close(self) -> None:
        """Remove a temporary folder (the resume cache stays)."""
        if self._removal is not None:
            self._removal()

    def map(
        self,
        kind: Kind,
        fn: Callable,
        shared: Any,
        tasks: Sequence,
        keys: Sequence[str],
        workers: int | None,
        on_result: Callable[[int, Any], None] | None,
        ray: str | None,
        keep: Callable[[Any], Any],
    ) -> list:
        """A per-scan stage (``cache.Cache.map``): each task's result read from the store or computed and written
        as it arrives; the list holds ``keep(result)``."""
        return self.disk.map(kind, fn, shared, tasks, keys, workers, on_result, ray, keep)

    def sequence(self, kind: Kind, keys: Sequence[str], compute: Callable[[int], Any]) -> Stored:
        """The scans' ``kind`` under ``keys`` as a ``Stored`` sequence; ``compute(k)`` makes item k again."""
        return Stored(str(self.folder), kind, tuple(keys), self, compute)


@dataclass(frozen=True)
class Attribute(Sequence):
    """``getattr(items[k], name)`` at ``[k]``, read on access: e.g. the scans' points, one scan at a time."""

    items: Sequence
    name: str

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, k: int) -> Any:  # type: ignore[override] - no slices
        return getattr(self.items[k], self.name)


def pair_order(ij: np.ndarray) -> np.ndarray:
    """The order to run pair tasks in: by their lower scan, then their higher one, so that the pairs of a scan run
    in a row and each worker's memory of the last items holds it."""
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    return np.lexsort((ij.max(axis=1), ij.min(axis=1)))


def pair_map(
    cache: Cache | None,
    kind: Kind,
    fn: Callable,
    shared: Any,
    ij: np.ndarray,
    tasks: Sequence,
    keys: Sequence[str | None],
    workers: int | None,
    on_result: Callable[[int, Any], None] | None,
    ray: str | None,
) -> list:
    """``cache.cached_map`` of one task a pair (row of ``ij``), run in ``pair_order``; results in the tasks' order
    (``on_result`` is told of them in the order they ran)."""
    order = pair_order(ij)
    ran = cached_map(
        cache, kind, fn, shared, [tasks[o] for o in order], [keys[o] for o in order], workers, on_result, ray
    )
    results: list = [None] * len(tasks)
    for o, result in zip(order, ran):
        results[o] = result
    return results
