"""Progress of long loops and the task a log line comes from, in any process.

A loop that can take more than a few seconds reports how far it is with :func:`report`: images
registered in a cluster, merge steps, the iterations of a final bundle adjustment with their
cost.  An event is a log record on the logger ``sfm.progress`` (not propagated to the root
logger: it is not a message for the log file), so it reaches the parent process from a worker
through the same channel as the worker's log messages (``sfm.execution.logs``); in the parent,
the functions registered with :func:`listen` receive it, whichever process it came from.  The
command line draws them as progress bars; nothing listens in the Python API.

:func:`task` names the task the current code works for (``C3``: cluster 3's local SfM); every
log record made inside it carries the name as ``record.task`` (:class:`TaskFilter`), so a line
in ``WORK/log.txt`` says which cluster it comes from, also when a worker process wrote it.

:func:`stage` records which stage runs, so that a run stopped by a signal can say where it
stopped (:func:`where`); :func:`bar` is the progress bar of a loop in this process, shown only
when :func:`show_bars` allows it.
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import os
import sys
from collections.abc import Callable, Iterator
from typing import Any

from tqdm import tqdm

LOGGER = logging.getLogger("sfm.progress")
LOGGER.propagate = False
LOGGER.setLevel(logging.INFO)

_task: contextvars.ContextVar[str] = contextvars.ContextVar("sfm_task", default="")
_listeners: list[Callable[[dict, str], None]] = []
_show_bars: bool | None = None  # None: when stderr is a terminal
_where = {"stage": "", "detail": ""}
# The command line's supervisor (``sfm.execution.processes``) names a file here: :func:`stage`
# keeps it up to date, so the supervisor can say where a run it stopped was.
STATUS_FILE_ENV = "GRAPHSFM_STATUS_FILE"


def report(kind: str, done: int, total: int | None = None, **info: Any) -> None:
    """One progress event: ``done`` of ``total`` units of ``kind`` (``"registered"``,
    ``"ba"``, ...) with any other facts (``cost=...``), for the task of :func:`task`."""
    if LOGGER.isEnabledFor(logging.INFO):
        LOGGER.info("%s %s/%s", kind, done, total, extra={"progress": {"kind": kind, "done": done, "total": total, **info}})


@contextlib.contextmanager
def task(label: str) -> Iterator[None]:
    """Log records and progress events inside the block carry ``label`` (``record.task``)."""
    token = _task.set(label)
    try:
        yield
    finally:
        _task.reset(token)


def current_task() -> str:
    return _task.get()


class TaskFilter(logging.Filter):
    """Sets ``record.task`` (the :func:`task` label, ``""`` outside one) on records that came
    without it (records from a worker process already have theirs)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "task"):
            record.task = _task.get()
        return True


@contextlib.contextmanager
def listen(callback: Callable[[dict, str], None]) -> Iterator[None]:
    """``callback(event, task)`` receives every progress event inside the block."""
    _listeners.append(callback)
    try:
        yield
    finally:
        _listeners.remove(callback)


class _Dispatch(logging.Handler):
    def emit(self, record: logging.LogRecord) -> None:
        event = getattr(record, "progress", None)
        if event is None:
            return
        label = getattr(record, "task", None)
        for callback in list(_listeners):
            try:
                callback(event, _task.get() if label is None else label)
            except Exception:  # noqa: BLE001 - a display must never stop the run
                self.handleError(record)


LOGGER.addHandler(_Dispatch())
LOGGER.addFilter(TaskFilter())


def stage(name: str, detail: str = "") -> None:
    """The stage that runs now (and how far it is), for :func:`where`."""
    _where["stage"], _where["detail"] = name, detail
    path = os.environ.get(STATUS_FILE_ENV)
    if path:
        try:
            with open(path, "w") as f:
                f.write(where())
        except OSError:
            pass


def where() -> str:
    """``"map (2 of 4 clusters finished)"``: the stage :func:`stage` last named."""
    if not _where["stage"]:
        return "start-up"
    return _where["stage"] + (f" ({_where['detail']})" if _where["detail"] else "")


def show_bars(enabled: bool | None) -> None:
    """Progress bars on (True), off (False), or when stderr is a terminal (None, the default)."""
    global _show_bars
    _show_bars = enabled


def bars_shown() -> bool:
    return sys.stderr.isatty() if _show_bars is None else _show_bars


def bar(iterable: Any = None, *, total: int | None = None, desc: str, unit: str, **kwargs: Any) -> tqdm:
    """A progress bar on stderr over ``iterable`` or up to ``total`` for a loop in this process
    (hidden unless :func:`bars_shown`; gone when the loop ends: the stage's log line stays)."""
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=not bars_shown(), leave=False,
                dynamic_ncols=True, **kwargs)


@contextlib.contextmanager
def bar_for(kind: str, desc: str, unit: str, total: int | None = None) -> Iterator[tqdm]:
    """A :func:`bar` moved by the progress events of ``kind`` (from this process or a worker),
    with the last event's ``cost`` beside it."""
    shown = bar(total=total, desc=desc, unit=unit)

    def on_event(event: dict, task: str) -> None:
        if event["kind"] != kind:
            return
        if event.get("total") is not None:
            shown.total = event["total"]
        shown.n = event["done"]
        if event.get("cost") is not None:
            shown.set_postfix_str(f"cost {event['cost']:.6g}", refresh=False)
        shown.refresh()

    try:
        with listen(on_event):
            yield shown
    finally:
        shown.close()
