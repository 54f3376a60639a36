"""The one error the tool reports as the user's: bad input, said in a line (the readers raise it too, so it
sits below everything that reads), and what the command line says when it is stopped."""


class InputError(ValueError):
    """Bad user input; the CLI prints its message on one line and exits non-zero."""


def stopped(signal_name: str) -> str:
    """The line a command stopped by the signal ``signal_name`` (SIGINT, SIGTERM) ends with."""
    return f"stopped by {signal_name}: nothing written, earlier results left as they were"
