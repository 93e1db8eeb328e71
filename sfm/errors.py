"""Errors a user sees as one line, each with its exit code (the command line's contract).

0: a model was written; 1: unexpected internal error (details in WORK/log.txt);
2: bad arguments or no usable input; 3: input was read but no model could be made.
"""


class GraphsfmError(Exception):
    """Base class of the errors the CLI reports as one line."""

    exit_code = 1


class InputError(GraphsfmError):
    """Bad arguments, missing or unusable input (exit code 2)."""

    exit_code = 2


class NoModelError(GraphsfmError):
    """The input was read but no model could be made (exit code 3)."""

    exit_code = 3
