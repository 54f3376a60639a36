"""``python -m sghr_gtsam`` and the ``sghr-gtsam`` console script (``main``)."""

import atexit
import signal


def main(prog_name: str | None = None) -> None:
    """The command line (``cli._main``). A SIGINT or SIGTERM while it loads waits until it can end the command in
    one line: raised in an import, it can be swallowed by the imported code or end in typer's silent exit."""
    arrived: list[int] = []
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda signum, frame: arrived.append(signum))
    atexit.register(_last)  # first registered, run last: after every library's exit handler
    from sghr_gtsam.cli import _main as command_line

    command_line(prog_name, arrived)


def _last() -> None:
    from sghr_gtsam.cli import skip_teardown

    skip_teardown()


if __name__ == "__main__":
    main("python -m sghr_gtsam")
