"""What a command shows on the terminal and keeps in ``WORK/log.txt``.

:func:`setup_logging` makes both handlers of the root logger:

- stderr: INFO (``-v``: DEBUG, ``-q``: warnings and errors only), one line per message,
  ``I``/``W``/``E`` first and the task it comes from (``C3``) when the message does not name
  it already; written through tqdm so that it does not break a progress bar.
- ``WORK/log.txt``: INFO (``-v``: DEBUG), with time, level, process id, logger and task, so a
  line from a worker process says which cluster it worked for.  Python warnings (NumPy's, say)
  are logged here, not printed (``sfm.execution.logs.quiet_warnings``), and so is the
  traceback of a failure the terminal shows as one line (``sfm.execution.logs.DETAILS``).

Worker processes' records reach these handlers through ``sfm.execution.logs``.  Progress bars
(``sfm.core.progress``) are drawn when stderr is a terminal and ``-q`` is not given; otherwise
each stage's summary line is the progress report.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from tqdm import tqdm

from sfm.core import progress
from sfm.errors import InputError
from sfm.execution.logs import DETAILS, quiet_warnings
from sfm.io.workspace import LOG

LEVELS = {"quiet": logging.WARNING, "normal": logging.INFO, "debug": logging.DEBUG}


class _ConsoleFormatter(logging.Formatter):
    """``I C3: message``; the logger's name too with ``-v``."""

    def __init__(self, with_names: bool) -> None:
        super().__init__()
        self.with_names = with_names

    def format(self, record: logging.LogRecord) -> str:
        message = record.getMessage()
        task = getattr(record, "task", "")
        if task and not message.startswith(task + ":"):
            message = f"{task}: {message}"
        if self.with_names:
            message = f"{record.name}: {message}"
        if record.exc_info and self.with_names:
            message += "\n" + self.formatException(record.exc_info)
        return f"{record.levelname[0]} {message}"


class _FileFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        task = getattr(record, "task", "")
        record.where = f" [{task}]" if task else ""
        return super().format(record)


class _Console(logging.StreamHandler):
    """stderr, through ``tqdm.write`` while progress bars may be on screen."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = self.format(record)
            if progress.bars_shown():
                tqdm.write(message, file=self.stream)
            else:
                self.stream.write(message + "\n")
                self.stream.flush()
        except Exception:  # noqa: BLE001 - logging's own rule
            self.handleError(record)


def _not_warnings(record: logging.LogRecord) -> bool:
    """Python warnings and failures' details are for the log file, not the terminal."""
    return record.name not in ("py.warnings", DETAILS)


def teardown_logging() -> None:
    """Remove (and close) the handlers :func:`setup_logging` added."""
    root = logging.getLogger()
    for old in [h for h in root.handlers if getattr(h, "graphsfm", False)]:
        root.removeHandler(old)
        old.close()


def setup_logging(workspace: Path | None, verbosity: str = "normal") -> None:
    """The root logger's stderr and ``WORK/log.txt`` handlers at ``verbosity`` (``quiet``,
    ``normal``, ``debug``); progress bars off with ``quiet``."""
    level = logging.DEBUG if verbosity == "debug" else logging.INFO
    teardown_logging()
    root = logging.getLogger()
    root.setLevel(level)
    console = _Console(sys.stderr)
    console.setLevel(LEVELS[verbosity])
    console.setFormatter(_ConsoleFormatter(with_names=verbosity == "debug"))
    console.addFilter(progress.TaskFilter())
    console.addFilter(_not_warnings)
    handlers: list[logging.Handler] = [console]
    if workspace is not None:
        try:
            handler = logging.FileHandler(Path(workspace) / LOG)
        except OSError as exc:
            raise InputError(f"cannot write to workspace {workspace}: {exc.strerror}") from exc
        handler.setLevel(level)
        handler.setFormatter(_FileFormatter("%(asctime)s %(levelname)s %(process)d %(name)s%(where)s: %(message)s"))
        handler.addFilter(progress.TaskFilter())
        handlers.append(handler)
    for handler in handlers:
        handler.graphsfm = True  # type: ignore[attr-defined]
        root.addHandler(handler)
    # Dask's own INFO lines (connections, worker starts) are for -v.
    logging.getLogger("distributed").setLevel(logging.DEBUG if verbosity == "debug" else logging.WARNING)
    quiet_warnings()
    progress.show_bars(False if verbosity == "quiet" else None)
