"""The one error the tool reports as the user's: bad input, said in a line (the readers raise it too, so it
sits below everything that reads)."""


class InputError(ValueError):
    """Bad user input; the CLI prints its message on one line and exits non-zero."""
