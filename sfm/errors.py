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


class DamagedFileError(InputError, ValueError):
    """A file whose content cannot be read (a damaged database, JSON file or model): the message
    names it and says what to do (exit code 2).  Also a ``ValueError``, as a parse error is."""

    def __init__(self, path, detail: str, remedy: str = "") -> None:
        remedy = remedy or "delete it and rerun: the stage that writes it runs again"
        super().__init__(f"{path} is damaged ({detail}): {remedy}")
        self.path = path


class WorkspaceBusyError(InputError):
    """The workspace is in use by another run (exit code 2)."""


class NoModelError(GraphsfmError):
    """The input was read but no model could be made (exit code 3)."""

    exit_code = 3
