"""The executors (``sghr_gtsam.executor``): in this process, the process pool and a local Ray instance give the same
results in the tasks' order, raise a task's error in the caller, and a run's poses do not depend on them."""

import importlib.util
import os
import signal
import threading
import time
import weakref

import numpy as np
import pytest
from typer.testing import CliRunner

from sghr_gtsam import cli
from sghr_gtsam.cli import _Stopped, app
from sghr_gtsam.config import Config
from sghr_gtsam.executor import KEPT_STATE_BYTES, _signals_held, kept_workers, parallel_map
from sghr_gtsam.pipeline import run
from sghr_gtsam.synthetic import make_scene, write_scene
from sghr_gtsam.types import InputError

NO_RAY = "the optional extra ray is not installed (pip install -e '.[ray]')"
BACKENDS = [
    pytest.param(1, None, id="in-process"),
    pytest.param(2, None, id="pool-2"),
    pytest.param(
        2, "local", id="ray-local-2", marks=pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason=NO_RAY)
    ),
]


@pytest.fixture(scope="module", autouse=True)
def _stop_ray():
    """The local Ray instance a test starts lives until the end of this module, not of the test session."""
    yield
    if importlib.util.find_spec("ray") is not None:
        import ray

        ray.shutdown()


def _square_late_first(shared: int, x: int) -> int:
    time.sleep(0.002 * (10 - x % 10))  # later tasks finish first: the results must still come back in order
    return shared * x * x


def _fails_at_five(shared: None, x: int) -> int:
    if x == 5:
        raise InputError(f"task {x} failed")
    return x


@pytest.mark.parametrize("workers, ray", BACKENDS)
def test_results_and_on_result_come_in_task_order(workers, ray):
    tasks = list(range(23))
    seen = []
    out = parallel_map(_square_late_first, 3, tasks, workers, lambda k, r: seen.append((k, r)), ray=ray)
    assert out == [3 * t * t for t in tasks]
    assert seen == list(enumerate(out))


def _array(shared: None, x: int) -> np.ndarray:
    return np.full(1000, x)


@pytest.mark.parametrize("workers, ray", BACKENDS)
def test_results_kept_as_keep_says_are_let_go_as_they_arrive(workers, ray):
    """With ``keep`` the list holds what it returns; each result itself is gone by the time the next one arrives
    (a stage whose results go to the store holds none of them)."""
    seen, alive = [], []

    def arrived(k, result):
        alive.append(sum(ref() is not None for ref in seen))
        seen.append(weakref.ref(result))

    out = parallel_map(_array, None, list(range(12)), workers, arrived, ray=ray, keep=lambda a: int(a[0]))
    assert out == list(range(12)) and alive == [0] * 12


@pytest.mark.parametrize("workers, ray", BACKENDS)
def test_a_failed_task_raises_its_error_and_the_next_stage_runs(workers, ray):
    with pytest.raises(InputError, match="^task 5 failed$"):
        parallel_map(_fails_at_five, None, list(range(12)), workers, ray=ray)
    assert parallel_map(_fails_at_five, None, [1, 2, 3], workers, ray=ray) == [1, 2, 3]


def _pid(shared: object, x: int) -> int:
    time.sleep(0.01)  # long enough that both workers take tasks
    return os.getpid()


def _sized(shared: bytes, x: int) -> tuple[int, int]:
    return len(shared), x


def test_kept_workers_serve_every_stage_of_the_block_each_with_its_own_shared_state():
    """The stages of a block run in the same worker processes (what a worker built for one stage serves the next),
    each with its own ``shared``; outside a block every stage starts new workers."""
    tasks = list(range(12))
    with kept_workers(2):
        first = set(parallel_map(_pid, None, tasks, 2))
        assert parallel_map(_square_late_first, 3, tasks, 2) == [3 * t * t for t in tasks]
        assert parallel_map(_square_late_first, 5, tasks, 2) == [5 * t * t for t in tasks]
        assert set(parallel_map(_pid, None, tasks, 2)) == first
        large = b"x" * (KEPT_STATE_BYTES + 1)  # too large to travel with every task: a pool of its own
        assert parallel_map(_sized, large, tasks, 2) == [(len(large), t) for t in tasks]
        assert set(parallel_map(_pid, None, tasks, 2)) == first
    assert len(first) == 2 and os.getpid() not in first
    assert not first & set(parallel_map(_pid, None, tasks, 2))


def test_a_failed_task_in_a_kept_block_ends_its_workers_and_the_next_stage_starts_new_ones():
    with kept_workers(2):
        first = set(parallel_map(_pid, None, list(range(12)), 2))
        with pytest.raises(InputError, match="^task 5 failed$"):
            parallel_map(_fails_at_five, None, list(range(12)), 2)
        assert parallel_map(_fails_at_five, None, [1, 2, 3], 2) == [1, 2, 3]
        assert not first & set(parallel_map(_pid, None, list(range(12)), 2))


def test_ray_option_is_checked_before_any_work(monkeypatch, tmp_path):
    with pytest.raises(InputError, match="ray must be local, auto, host:port or ray://host:port"):
        Config(ray="cluster").validate()
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: object())  # as if installed
    for address in ("local", "auto", "head.example:6379", "ray://10.0.0.1:10001"):
        Config(ray=address).validate()
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)  # as if not
    for args in (["run", str(tmp_path), "--ray", "local"], ["demo", "--out", str(tmp_path / "demo"), "--ray", "auto"]):
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 2
        assert r.output.splitlines() == [
            "error: ray is not installed: pip install 'sghr_gtsam[ray]' (in a checkout: pip install -e '.[ray]')"
        ]
    assert not (tmp_path / "demo").exists()


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    d = tmp_path_factory.mktemp("executor") / "scene"
    write_scene(make_scene("room", 6), d)
    return d


@pytest.fixture(scope="module")
def in_process(room, tmp_path_factory):
    return run(room, tmp_path_factory.mktemp("one") / "out", Config(record=False, workers=1), log=lambda m: None)


@pytest.mark.parametrize("workers, ray", BACKENDS[1:])
def test_poses_are_bit_identical_whatever_the_executor(room, in_process, tmp_path, workers, ray):
    """Each task is a pure function of its inputs whose arithmetic does not depend on its threads (the in-process
    run uses every core, a worker one): no floating-point order differs, so the poses are equal to the last bit."""
    other = run(room, tmp_path / "out", Config(record=False, workers=workers, ray=ray), log=lambda m: None)
    np.testing.assert_array_equal(other.poses, in_process.poses)
    assert other.densify == in_process.densify
    assert other.densify["refine_tried"] > 0  # the refinement stage ran on the executor too


def test_each_thread_keeps_its_own_workers():
    """Two registrations in two threads: each block keeps its own pool, which the other block's end leaves alone."""
    tasks = list(range(12))
    first_done, second_started = threading.Event(), threading.Event()
    out = {}

    def first():
        with kept_workers(2):
            out["first"] = set(parallel_map(_pid, None, tasks, 2))
            second_started.wait(60)
        first_done.set()

    def second():
        with kept_workers(2):
            out["second"] = set(parallel_map(_pid, None, tasks, 2))
            second_started.set()
            first_done.wait(60)  # the first block has ended
            out["second, after"] = set(parallel_map(_pid, None, tasks, 2))

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert len(out["first"]) == len(out["second"]) == 2 and not out["first"] & out["second"]
    assert out["second, after"] == out["second"]


def test_a_run_starts_one_pool_for_all_its_stages(room, in_process, tmp_path, monkeypatch):
    """``pipeline.register`` keeps its workers from stage to stage (features, pairs, pyramids, refinement, loops):
    one pool in all, and the same poses as in one process."""
    from sghr_gtsam import executor

    started = []
    new_pool = executor._new_pool
    monkeypatch.setattr(executor, "_new_pool", lambda *a: started.append(a[0]) or new_pool(*a))
    other = run(room, tmp_path / "out", Config(record=False, workers=2), log=lambda m: None)
    np.testing.assert_array_equal(other.poses, in_process.poses)
    assert other.densify["refine_tried"] > 0 and started == [2]


@pytest.mark.parametrize("signum, stopped", [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, _Stopped)])
def test_a_signal_while_workers_start_acts_once_they_have(signum, stopped):
    """A stop between a worker's fork and the pool's note of its pid left a worker nobody ended (a traceback on
    stderr once the run had exited, CI). The signal must wait for the start-up even with another thread running,
    as rerun's, TBB's and rich's are: the kernel hands a process-directed signal to a thread that accepts it."""
    saved = signal.signal(signal.SIGTERM, cli._stop)
    idle = threading.Event()
    other = threading.Thread(target=idle.wait)
    other.start()
    steps = []
    try:
        with pytest.raises(stopped):
            with _signals_held():
                os.kill(os.getpid(), signum)
                time.sleep(0.2)  # where Python would act on a signal that was not held
                steps.append("workers started")
    finally:
        idle.set()
        other.join()
        signal.signal(signal.SIGTERM, saved)
    assert steps == ["workers started"]
