"""How a worker's log messages and progress events reach the parent process.

Local pools (``sfm.execution.local``): each pool gets a multiprocessing queue; the pool's
initializer (:func:`init_worker`) replaces the worker's log handlers by one
:class:`logging.handlers.QueueHandler` on it, at the parent's level, and a
:class:`logging.handlers.QueueListener` thread in the parent (:class:`ForwardedLogs`) hands each
record to the logger of the same name there, where the parent's handlers (``WORK/log.txt``, the
console) and progress listeners (``sfm.core.progress``) take it.  This is the standard library's
recipe: records are formatted in the worker (no unpicklable arguments travel), they arrive as
they are made (a cluster's progress shows while it runs), and a worker that dies loses at most
the records still in its queue buffer.

Dask (``sfm.execution.dask_cluster``): a task's records are collected in the worker while it
runs (:func:`collect_records`) and return with its result, through the channel the result
takes anyway; the client replays them (:func:`replay`).  No connection from the workers back to
the client is needed, nothing is left running on the cluster, and a task retried on another
worker reports only the run that counted.  Progress events are not collected there: they would
arrive after the task ended.

Each record carries the task it came from (``record.task``, ``sfm.core.progress.task``), and
warnings of NumPy, OpenCV's Python layer and the rest are logged (``py.warnings``: in the log
file, not on the terminal) instead of printed.  So are the details of a failure that the
terminal reports as one line, its traceback (the logger :data:`DETAILS`, at INFO: in the log
file at every verbosity).  Workers ignore SIGINT: Ctrl-C reaches the whole process
group, and it is the parent that stops them (``sfm.execution.processes``).
"""

from __future__ import annotations

import logging
import logging.handlers
import signal
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

from sfm.core import progress

# The logger of what goes to WORK/log.txt only: a failure's traceback behind its one-line report.
DETAILS = "graphsfm.details"

_QUEUE_KEEP = ("name", "levelno", "levelname", "msg", "created", "msecs", "relativeCreated", "process",
               "processName", "thread", "threadName", "module", "filename", "funcName", "lineno", "pathname",
               "task", "progress")


def quiet_warnings() -> None:
    """Python warnings (NumPy's RuntimeWarnings and the like) go to the log, not to stderr;
    OpenCV's C++ log prints errors only."""
    logging.captureWarnings(True)
    warnings.simplefilter("default")
    try:
        import cv2

        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    except (ImportError, AttributeError):  # pragma: no cover - OpenCV always has it
        pass


def init_worker(queue, level: int) -> None:
    """Pool initializer: this worker's log records and progress events go to ``queue``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    handler = logging.handlers.QueueHandler(queue)
    handler.addFilter(progress.TaskFilter())
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level)
    for old in [h for h in progress.LOGGER.handlers if isinstance(h, logging.handlers.QueueHandler)]:
        progress.LOGGER.removeHandler(old)
    progress.LOGGER.addHandler(handler)
    quiet_warnings()


class _ToLogger(logging.Handler):
    """Parent side: a record from a worker goes to the logger of its name, as if made here."""

    def handle(self, record: logging.LogRecord) -> bool:
        logger = progress.LOGGER if hasattr(record, "progress") else logging.getLogger(record.name)
        if record.levelno >= logger.getEffectiveLevel() or hasattr(record, "progress"):
            logger.handle(record)
        return True

    def emit(self, record: logging.LogRecord) -> None:  # pragma: no cover - handle() does it
        self.handle(record)


@contextmanager
def forwarded_logs(context) -> Iterator[tuple]:
    """``(queue, level)`` for :func:`init_worker` in a pool of ``context``; records put on the
    queue are handled here until the block ends (and the ones still queued then)."""
    queue = context.Queue()
    listener = logging.handlers.QueueListener(queue, _ToLogger(), respect_handler_level=False)
    listener.start()
    try:
        yield queue, logging.getLogger().getEffectiveLevel()
    finally:
        listener.stop()
        queue.close()


class _Collect(logging.Handler):
    """Keeps the records of one thread (the task's: a Dask worker may run others beside it)."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[dict] = []
        self.thread = threading.get_ident()
        self.addFilter(progress.TaskFilter())

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self.thread or hasattr(record, "progress"):
            return
        d = {k: getattr(record, k) for k in _QUEUE_KEEP if hasattr(record, k)}
        d["msg"] = record.getMessage()
        if record.exc_info:
            d["msg"] += "\n" + logging.Formatter().formatException(record.exc_info)
        self.records.append(d)


@contextmanager
def collect_records(level: int) -> Iterator[list[dict]]:
    """The log records made in the block (at ``level`` and above), as plain dicts."""
    handler = _Collect()
    root = logging.getLogger()
    saved = root.level
    root.addHandler(handler)
    root.setLevel(level)
    try:
        with warnings.catch_warnings():
            logging.captureWarnings(True)
            warnings.simplefilter("default")
            yield handler.records
    finally:
        root.removeHandler(handler)
        root.setLevel(saved)


def replay(records: list[dict]) -> None:
    """Hand records collected by :func:`collect_records` to this process's loggers."""
    for d in records:
        record = logging.makeLogRecord({**d, "args": None, "exc_info": None})
        logger = logging.getLogger(record.name)
        if record.levelno >= logger.getEffectiveLevel():
            logger.handle(record)
