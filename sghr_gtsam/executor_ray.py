"""``executor.parallel_map`` on a Ray cluster (``Config.ray``; the optional extra ``pip install 'sghr_gtsam[ray]'``).

The cluster's workers are actors kept for the life of this process, as the fork server is: each imports the tasks'
modules once, takes one core of its node and one thread in its native pools, as a pool worker does. A stage's
``shared`` state goes into the object store once; each actor reads it at its first task of the stage and keeps it.
That state holds no arrays: the scans' features and grids travel as ``store.Stored`` handles, read by each actor
from the run's store folder through its own memory of the last items (``store.LRU_BYTES``, kept across stages).
Each actor has at most two tasks (one running, the next waiting), so that it never idles for a round trip and no
task waits behind a long one while another actor is free. Results come back in the tasks' order; a failed task,
Ctrl-C or SIGTERM ends the connection and its actors (the next stage connects anew) and raises as the process pool
does.

On a cluster of several machines, every node needs this project and its dependencies installed, at the same
version as the caller, and must see the scans (the tasks read them by path) and the run's store folder (the resume
cache ``OUT/cache``, or without one a temporary folder in the run's staging folder beside ``OUT``) at the same
paths: a shared filesystem. Shipping the arrays through Ray's object store instead would hold every scan's features
in the head node's object store (spilled to its disk), gaining nothing over a shared folder that the scans need
anyway; an actor that does not see the folder ends the run with one line saying so (``store``).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

import ray
from ray.exceptions import RayTaskError

from sghr_gtsam.types import InputError

T = TypeVar("T")
R = TypeVar("R")

_IN_FLIGHT = 2  # tasks an actor holds at most: one running, the next waiting


@ray.remote(num_cpus=1)
class _Worker:
    """One core of a node: runs tasks ``fn(shared, task)`` against the stage's shared state it holds."""

    def __init__(self, paths: list[str]) -> None:
        # The caller's import paths, as a pool worker has them: a task's module may lie in one (a test's folder);
        # the node's own come first, and a folder this node lacks is left out.
        sys.path += [p for p in paths if p not in sys.path and os.path.isdir(p)]
        self._ref: ray.ObjectRef | None = None
        self._shared: Any = None

    def node(self) -> str:
        return ray.get_runtime_context().get_node_id()

    def pin(self, slot: int) -> None:
        """Take one core of the node (the ``slot``-th actor on it), before any task: kiss-matcher's TBB and scipy's
        queries size their threads by the cores a process may use (``executor._receive``)."""
        cores = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cores[slot % len(cores)]})

    def run(self, fn: Callable[[Any, T], R], box: list[ray.ObjectRef], task: T) -> R:
        ref = box[0]  # in a list: Ray hands a top-level reference over as its value, read anew for every task
        if ref != self._ref:
            from threadpoolctl import threadpool_limits

            self._shared, self._ref = None, None  # the last stage's state goes before this one's arrives
            self._shared, self._ref = ray.get(ref), ref
            threadpool_limits(1)  # OpenMP (open3d, small_gicp) and BLAS as loaded by now: one thread each
        return fn(self._shared, task)

    def release(self) -> None:
        self._shared = self._ref = None


class _Cluster:
    """The connection and the actors started on it, kept from one stage to the next."""

    def __init__(self, address: str, workers: int | None):
        self.address = address
        self.actors: list[Any] = []
        self.slots: dict[str, int] = {}  # actors per node, for their cores
        if address == "local":
            kwargs: dict[str, Any] = {"address": "local", "num_cpus": workers}
        else:
            kwargs = {"address": address}
        sigterm = signal.getsignal(signal.SIGTERM)
        try:
            # ERROR: a local instance's start-up otherwise logs warnings meant for cluster operators.
            ray.init(include_dashboard=False, logging_level=logging.ERROR, **kwargs)
        except (ConnectionError, TimeoutError) as e:
            raise InputError(f"cannot connect to the Ray cluster at {address}: {e}") from None
        except SystemExit as e:  # SIGTERM while connecting, through ray.init's handler: the caller's gets it instead
            if e.code == signal.SIGTERM and callable(sigterm):
                sigterm(signal.SIGTERM, None)
            raise
        finally:
            if threading.current_thread() is threading.main_thread():
                # ray.init replaces the caller's SIGTERM handler by an exit of its own (the CLI's unwinds the run)
                signal.signal(signal.SIGTERM, sigterm)

    def cpus(self) -> int:
        return int(ray.cluster_resources().get("CPU", 0))

    def grow(self, n: int) -> list[Any]:
        """At least ``n`` actors, each pinned to a core of its node; the first ``n``."""
        new = [_Worker.remote(sys.path) for _ in range(n - len(self.actors))]
        for actor, node in zip(new, ray.get([a.node.remote() for a in new])):
            slot = self.slots.get(node, 0)
            self.slots[node] = slot + 1
            actor.pin.remote(slot)  # runs before the actor's first task (an actor runs a caller's calls in order)
        self.actors += new
        return self.actors[:n]


_CLUSTER: _Cluster | None = None


def _connect(address: str, workers: int | None) -> _Cluster:
    global _CLUSTER
    if _CLUSTER is None or _CLUSTER.address != address or not ray.is_initialized():  # (someone's ray.shutdown())
        _disconnect()
        _CLUSTER = _Cluster(address, workers)
    return _CLUSTER


def _disconnect() -> None:
    """End this process's actors (a cluster ends a job's actors with its connection) and a local instance, now:
    left to the interpreter's exit after a Ctrl-C, the shutdown crashed (a segmentation fault in 1 of 5 stops)."""
    global _CLUSTER
    _CLUSTER = None
    if ray.is_initialized():
        ray.shutdown()


def ray_map(
    fn: Callable[[Any, T], R], shared: Any, tasks: Sequence[T], workers: int | None, address: str
) -> Iterator[R]:
    """``fn(shared, t)`` for each of ``tasks`` over the Ray cluster at ``address`` (``Config.ray``) on ``workers``
    CPUs (None: every CPU of the cluster; 'local' needs a number), yielded in the tasks' order as they complete;
    ``executor.parallel_map`` is the public call."""

    if not tasks:
        return
    cluster = _connect(address, workers)
    results: dict[int, Any] = {}
    pending: dict[ray.ObjectRef, tuple[int, Any]] = {}
    queue = iter(enumerate(tasks))

    def submit(actor: Any) -> None:
        item = next(queue, None)
        if item is not None:
            pending[actor.run.remote(fn, box, item[1])] = (item[0], actor)

    try:
        cpus = cluster.cpus()
        if cpus < 1:
            raise InputError(f"the Ray cluster at {address} has no CPU")
        actors = cluster.grow(min(workers or cpus, cpus, len(tasks)))
        box = [ray.put(shared)]
        for _ in range(_IN_FLIGHT):
            for actor in actors:
                submit(actor)
        reported = 0
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            k, actor = pending.pop(ready[0])
            try:
                results[k] = ray.get(ready[0])
            except RayTaskError as e:  # the task's own exception, as the process pool raises it
                raise e.cause from e
            submit(actor)
            while reported in results:
                yield results.pop(reported)
                reported += 1
    except BaseException as e:  # Ctrl-C, SIGTERM, a failed task or caller: end the actors instead of finishing
        _disconnect()
        if isinstance(e, SystemError) and e.__cause__ is not None and "with an exception set" in str(e):
            raise e.__cause__ from None  # a signal handler's exception (the CLI's SIGTERM), wrapped by Ray's wait
        raise
    for actor in actors:
        actor.release.remote()
