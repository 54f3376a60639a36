"""The one error the tool reports as the user's: bad input, said in a line (the readers raise it too, so it
sits below everything that reads), and what the command line says when it is stopped."""


class InputError(ValueError):
    """Bad user input; the CLI prints its message on one line and exits non-zero."""


def one_line(error: BaseException) -> str:
    """A library's error message on one line (its whitespace collapsed), or its type's name when it says nothing."""
    return " ".join(str(error).split()) or type(error).__name__


def stopped(signal_name: str, written: str | None = None) -> str:
    """The line a command stopped by the signal ``signal_name`` (SIGINT, SIGTERM) ends with; ``written``: the
    results folder, when the stop came after the run had swapped its results in."""
    if written is not None:
        return f"stopped by {signal_name} after the results were written: {written} is complete"
    return f"stopped by {signal_name}: nothing written, earlier results left as they were"
