"""Progress of a run's long stages, as the pipeline reports it: ``Progress`` says nothing (the API's default),
``TerminalProgress`` draws one rich bar with its ETA per stage (the command line's).

A stage is opened with ``progress.stage(label, total)``; it yields a ``tick`` that takes any arguments, so that
it serves as ``executor.parallel_map``'s ``on_result(k, result)``, as ``synchronize``'s ``on_iteration(record)``
and as a plain ``tick()``. Like the recording, progress only observes: nothing it does changes a result.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.console import Console

Tick = Callable[..., None]


def _ignore(*_: Any) -> None:
    return None


class Progress:
    """No output: the stages run unobserved."""

    @contextmanager
    def stage(self, label: str, total: int) -> Iterator[Tick]:
        """Observe a stage of ``total`` steps; ``tick`` once per step done."""
        yield _ignore

    def log(self, message: str) -> None:
        """A stage message, printed where it does not break the bars (here: nowhere)."""

    def close(self) -> None:
        """Stop drawing; the bars drawn so far stay on the terminal."""


QUIET = Progress()


class TerminalProgress(Progress):
    """One bar per stage on ``console`` (label, bar, done/total, elapsed, ETA), messages printed above them.
    A stage that takes more steps than announced (synchronization's polish after its ``total`` IRLS
    iterations) shows them in its label and is filled when it ends."""

    def __init__(self, console: Console) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )
        from rich.progress import Progress as RichProgress

        self.console = console
        self._bars = RichProgress(
            TextColumn("{task.description:<28}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            console=console,
            transient=False,
        )
        self._bars.start()

    @contextmanager
    def stage(self, label: str, total: int) -> Iterator[Tick]:
        task = self._bars.add_task(label, total=max(total, 1))
        done = 0

        def tick(*args: Any) -> None:
            nonlocal done
            done += 1
            stage = getattr(args[0], "stage", None) if len(args) == 1 else None
            if done > total and stage:  # steps beyond the announced ones: name them instead of overfilling
                self._bars.update(task, description=f"{label} · {stage}")
            else:
                self._bars.update(task, completed=min(done, total))

        try:
            yield tick
        finally:
            self._bars.update(task, description=label, completed=max(total, 1))
            self._bars.stop_task(task)

    def log(self, message: str) -> None:
        self.console.print(message, markup=False, highlight=False, soft_wrap=True)

    def close(self) -> None:
        self._bars.stop()
