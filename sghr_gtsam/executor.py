"""One way to run a stage's independent tasks over processes: ``parallel_map(fn, shared, tasks, workers, ray=...)``.

Every parallel stage (pairwise registration, refinement, loop closure, retries) calls it. A task is
``fn(shared, task)``; ``shared`` is the stage's read-only state, sent once to each worker: parameters and the
scans' features and grids as ``store.Stored`` handles (a folder and keys; the arrays are read from the folder where
a task needs them); tasks and results cross process boundaries one by one. Results come back in the tasks' order and
every task is a pure function of its inputs, so a run gives the same result for any number of workers. With
``ray`` (``Config.ray``) the same call runs on a Ray cluster instead (``executor_ray``). A run's stages share one
pool (``kept_workers``), so that what a worker read and built for one stage serves the next.

Workers start from a fork server, not by forking this process: kiss-matcher and open3d run TBB thread pools,
and a child forked from a process whose pool is running deadlocks in its first parallel call (seen here).
The server imports ``fn``'s module once, so each worker starts in milliseconds. ``start_server`` starts it
early, so that its imports (≈ 1.5 s) run on another core while the caller is still importing and loading.
"""

from __future__ import annotations

import itertools
import multiprocessing
import os
import pickle
import select
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import closing, contextmanager
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_SHARED: Any = None  # the running stage's shared state, in each worker


def default_workers() -> int:
    """Every core this process may run on."""
    return len(os.sched_getaffinity(0))


def start_server(modules: Sequence[str], workers: int | None = None, ray: str | None = None) -> None:
    """Start the fork server now, importing ``modules`` (those of the tasks to come), unless the stages will run
    in this process (one worker) or on Ray, or the server is running already. Without it the first
    ``parallel_map`` starts the server and waits for its imports."""
    workers = default_workers() if workers is None else workers
    if workers <= 1 or ray is not None or "forkserver" not in multiprocessing.get_all_start_methods():
        return
    _ensure_server(modules)


def _ensure_server(modules: Sequence[str]) -> None:
    """Start the fork server, importing ``modules``, unless it is running; with one OpenMP thread: a worker forked
    from a server whose OpenMP runtime (libgomp, started by importing open3d) has threads hung in its first parallel
    region (open3d's normals, seen here), and each worker has one core anyway (``_receive``)."""
    from multiprocessing import forkserver, resource_tracker

    forkserver.set_forkserver_preload(list(modules))
    saved = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"  # the server inherits this process's environment; this process keeps its own
    # The server inherits this thread's signal mask: SIGINT blocked, a terminal's Ctrl-C (sent to the whole group)
    # does not interrupt its imports, which printed a KeyboardInterrupt traceback; its workers ignore SIGINT anyway
    # (``_receive``), and this process, which unwinds the run, gets the signal as soon as the mask is restored.
    # The resource tracker starts first: starting, it unblocks SIGINT (after the same trick for itself).
    resource_tracker.ensure_running()
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        forkserver.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        if saved is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = saved


def _receive(shared: Any, started: Any, caller: int) -> None:
    """Worker start: keep the stage's state, end with the ``caller`` (``_end_with``) and take one core of its own.
    kiss-matcher's TBB and open3d's OpenMP size their thread pools by the cores a process may use; left at every
    core, two workers run four spinning threads on two cores and the stage ran slower than in one process (seen
    here)."""
    global _SHARED
    _SHARED = shared
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the caller alone unwinds
    _end_with(caller)
    with started.get_lock():
        index = started.value
        started.value += 1
    cores = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cores[index % len(cores)]})


def _end_with(caller: int) -> None:
    """End this worker as soon as the process ``caller`` ends. A caller killed outright (SIGKILL, the OOM killer)
    unwinds nothing: its workers waited for tasks for ever (~130 MB each, seen here), and with them the fork
    server and the resource tracker, which end once no worker holds their pipes. A worker is the fork server's
    child, so the caller is watched through a pidfd (readable once it has ended; Linux ≥ 5.3): where there is none,
    nothing is watched."""
    try:
        pidfd = os.pidfd_open(caller)
    except ProcessLookupError:  # ended already
        os._exit(1)
    except (AttributeError, OSError):  # no pidfd on this system
        return

    def watch() -> None:
        select.select([pidfd], [], [])
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="end-with-caller").start()


def _call(fn: Callable[[Any, T], R], task: T) -> R:
    return fn(_SHARED, task)


def parallel_map(
    fn: Callable[[Any, T], R],
    shared: Any,
    tasks: Sequence[T],
    workers: int | None = None,
    on_result: Callable[[int, R], None] | None = None,
    ray: str | None = None,
    keep: Callable[[R], Any] | None = None,
) -> list:
    """``[fn(shared, t) for t in tasks]`` over ``workers`` processes (None: every core; 1: in this process), or
    on the Ray cluster ``ray`` (``Config.ray``) over ``workers`` of its CPUs (None: all).

    ``fn`` must be a module-level function; ``shared`` and the results must pickle. ``on_result(k, result)``
    is called in this process, in task order, as results arrive (progress, recording, storing). ``keep``: the
    list holds ``keep(result)`` instead of each result (what a stage keeps of results stored elsewhere). Within
    a ``kept_workers`` block of as many workers, the block's pool runs the tasks.
    """
    if ray is not None:
        from sghr_gtsam.executor_ray import ray_map

        if workers is None and ray == "local":
            workers = default_workers()
        # closing: a failing on_result ends the cluster's actors now, not when the generator is collected
        with closing(ray_map(fn, shared, tasks, workers, ray)) as results:
            return [_arrived(k, result, on_result, keep) for k, result in enumerate(results)]
    workers = default_workers() if workers is None else workers
    kept = next((k for k in _BLOCKS.open if k.workers == workers), None)
    workers = min(workers, len(tasks))
    if workers <= 1 or "forkserver" not in multiprocessing.get_all_start_methods():
        return [_arrived(k, fn(shared, task), on_result, keep) for k, task in enumerate(tasks)]
    _ensure_server([fn.__module__])
    state = pickle.dumps(shared) if kept is not None else b""
    if kept is None or len(state) > KEPT_STATE_BYTES:
        with _new_pool(workers, shared) as pool:
            return _pool_map(pool, fn, [(_call, fn, task) for task in tasks], on_result, keep)
    if kept.pool is None:
        kept.pool = _new_pool(kept.workers, None)
    stage = next(_STAGES)
    try:
        return _pool_map(kept.pool, fn, [(_call_staged, fn, stage, state, task) for task in tasks], on_result, keep)
    except BaseException:
        pool, kept.pool = kept.pool, None  # its workers are ended (_pool_map): the next stage starts new ones
        pool.shutdown()
        raise


KEPT_STATE_BYTES = 2**20
"""In a ``kept_workers`` block a stage's ``shared`` travels with each of its tasks (a worker unpickles it once a
stage). The pipeline's are store handles and parameters: 8.4 KB on a 60-scan run, ~140 bytes more a scan, so this
bound is reached near 7,000 scans, where copying it costs ~2 ms (measured) of a task's 0.1-0.3 s. A larger one
gets a pool of its own."""


class _Kept:
    """A ``kept_workers`` block's pool, started by its first stage."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.pool: ProcessPoolExecutor | None = None


class _Blocks(threading.local):
    """The open ``kept_workers`` blocks of a thread: a block belongs to the thread that opened it (runs in two
    threads keep a pool each)."""

    def __init__(self) -> None:
        self.open: list[_Kept] = []


_BLOCKS = _Blocks()
_STAGES = itertools.count()
_STAGE: int | None = None  # the stage whose shared state a kept worker holds


@contextmanager
def kept_workers(workers: int | None, ray: str | None = None) -> Iterator[None]:
    """Within the block, the stages that run over ``workers`` processes share one pool of them instead of starting
    a pool each: a worker's memory of the scans it read, with the search structures and GICP clouds built on them
    (``store.LRU_BYTES``), then serves every stage, not one. On a 3DMatch scene of 60 fragments (two workers) the
    pyramid levels were built 840 times for 120 (refinement and two rounds of loop closure, each in each worker),
    246 times in one pool (the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md). Nothing is kept under Ray
    or with one worker; a stage asking for another number of workers, or run by another thread, gets a pool of its
    own. Results do not depend on it: tasks are pure functions."""
    workers = default_workers() if workers is None else workers
    if workers <= 1 or ray is not None or any(k.workers == workers for k in _BLOCKS.open):
        yield
        return
    kept = _Kept(workers)
    _BLOCKS.open.append(kept)
    try:
        yield
    finally:
        _BLOCKS.open.remove(kept)
        if kept.pool is not None:
            kept.pool.shutdown()


def _new_pool(workers: int, shared: Any) -> ProcessPoolExecutor:
    context = multiprocessing.get_context("forkserver")
    return ProcessPoolExecutor(
        workers, mp_context=context, initializer=_receive, initargs=(shared, context.Value("i", 0), os.getpid())
    )


def _call_staged(fn: Callable[[Any, T], R], stage: int, state: bytes, task: T) -> R:
    """A task of a stage run in a kept pool: the stage's shared state unpickled once, on its first task here."""
    global _SHARED, _STAGE
    if _STAGE != stage:
        _SHARED, _STAGE = pickle.loads(state), stage
    return fn(_SHARED, task)


def _pool_map(
    pool: ProcessPoolExecutor, fn: Callable, calls: list[tuple], on_result: Callable | None, keep: Callable | None
) -> list:
    """``pool.submit(*call)`` of each call, results in order; ends the pool's workers if anything fails."""
    try:
        # One future a task keeps both workers busy when task costs vary (a wrong pair costs more than a right
        # one). Futures, not pool.map: map cancels the pending ones when stopped, and the pool's manager thread
        # of Python < 3.12 then fails on them with a traceback on stderr.
        with _main_not_rerun(fn), _signals_held():
            futures = [pool.submit(*call) for call in calls]  # starts the workers
        results = []
        for k in range(len(futures)):
            future, futures[k] = futures[k], None  # a future holds its result: let it go once taken
            results.append(_arrived(k, future.result(), on_result, keep))
        return results
    except BaseException:  # Ctrl-C, SIGTERM, a failed task: end the workers instead of finishing the tasks
        # A graceful shutdown waited for ever on a worker stopped at start-up (seen after SIGINT); the pool's
        # process table is private, but there is no public way to end its workers before Python 3.14.
        processes = list((getattr(pool, "_processes", None) or {}).values())
        for process in processes:
            process.terminate()
        for process in processes:
            process.join(5)
        # A worker ended while sending its result leaves half a message in the result pipe, and the manager
        # thread then waits for ever for the rest (1 stop in ~20, seen here): with the workers' copies of the
        # pipe's write end gone, closing ours ends that wait with EOF.
        results_pipe = getattr(pool, "_result_queue", None)
        if results_pipe is not None:
            results_pipe._writer.close()
        raise


def _arrived(k: int, result: R, on_result: Callable[[int, R], None] | None, keep: Callable[[R], Any] | None) -> Any:
    """What a backend does with task ``k``'s result as it arrives, in task order: tell ``on_result``, keep it."""
    if on_result is not None:
        on_result(k, result)
    return result if keep is None else keep(result)


@contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM wait while the block runs, then act as they would have: while a pool's workers start, or
    while modules import (an extension module interrupted in its initialisation fails with an ImportError and
    leaves a half-made module). One arriving between a worker's fork and the pool's note of its pid left a worker
    nobody ended: once this process had exited and its semaphores were gone, the worker's start-up failed with a
    traceback on stderr (CI, 1 run in ~5). A thread mask cannot hold them: a process-directed signal goes to any
    thread not blocking it (rerun's, TBB's, rich's), and Python runs its handler in the main thread at once. So the
    handlers note the signal and it is raised again after."""
    held = (signal.SIGINT, signal.SIGTERM)
    arrived: list[int] = []
    try:
        saved = {s: signal.signal(s, lambda signum, frame: arrived.append(signum)) for s in held}
    except ValueError:  # not the main thread: Python delivers no signal here
        yield
        return
    try:
        yield
    finally:
        for s, handler in saved.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)  # None: set outside Python
        for s in dict.fromkeys(arrived):
            signal.raise_signal(s)


@contextmanager
def _main_not_rerun(fn: Callable) -> Iterator[None]:
    """Workers re-import the caller's ``__main__`` script unless it has no file; a script without an
    ``if __name__ == "__main__":`` guard then runs again in every worker (and hung in open3d, seen here). A task
    defined outside ``__main__`` needs none of it, so the script's file is hidden while the workers start."""
    main = sys.modules["__main__"]
    path = getattr(main, "__file__", None)
    if fn.__module__ == "__main__" or path is None or getattr(main, "__spec__", None) is not None:
        yield
        return
    del main.__file__
    try:
        yield
    finally:
        main.__file__ = path
