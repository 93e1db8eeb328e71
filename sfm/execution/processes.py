"""Stopping a run at once, with every process it started: the command line's supervisor.

``graphsfm`` runs each command in a child process (:func:`supervise`) and only waits for it.
The reason is the GIL: a long C++ call (one iteration of GTSAM's optimiser on a large final
BA, a big SIFT) holds it for seconds, and Python runs signal handlers between bytecodes of the
main thread only, so a process doing the work cannot promise to react to Ctrl-C in time.  The
waiting parent always can.  On SIGINT or SIGTERM it

1. takes a snapshot of the child's process tree (from ``/proc``: the pool workers, their fork
   server, a local Dask cluster's nannies and workers), then sends SIGTERM to each of them, and
   SIGKILL to those still alive after ``GRACE_S``; the child's process group (a new one, so
   Ctrl-C at the terminal reaches only the parent) is killed as well, which catches processes
   orphaned in between (a fork server outlives its parent otherwise);
2. prints one line saying which stage the run was in (the child writes it to a small status
   file, ``sfm.core.progress.stage``) and that rerunning resumes;
3. exits with 128 + the signal number (130 for Ctrl-C, 143 for SIGTERM).

Stopping mid-stage is safe: every workspace file is written under a temporary name and renamed,
and the database one transaction at a time, so the state on disk is the one a ``kill -9``
leaves, which a rerun resumes from.  A process that detached itself into a new session (a Rerun
viewer) is left alone.  When the child ends normally, whatever it left in its process group is
ended too.  Should the supervisor itself be killed (``kill -9``), the kernel kills the child
with it (``PR_SET_PDEATHSIG``), so no run goes on holding the workspace.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from sfm.core.progress import STATUS_FILE_ENV

GRACE_S = 1.0  # between SIGTERM and SIGKILL


class _Stop(Exception):
    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _stat(pid: int) -> tuple[int, int, int] | None:
    """``(ppid, pgrp, session)`` of ``pid`` from ``/proc/<pid>/stat``; None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()  # after "pid (comm) "; comm may hold spaces
    return int(fields[1]), int(fields[2]), int(fields[3])


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (children first), from ``/proc``."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            st = _stat(int(entry))
            if st is not None:
                children.setdefault(st[0], []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def _alive(pid: int) -> bool:
    st = Path(f"/proc/{pid}/status")
    try:
        return "State:\tZ" not in st.read_text()
    except OSError:
        return False


def end_tree(child: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL after ``GRACE_S``, to ``child``, its descendants in its session,
    and its process group; ``child`` is reaped."""
    st = _stat(child.pid)
    session = st[2] if st else None
    tree = [child.pid] + [p for p in descendants(child.pid) if session is None or (_stat(p) or (0, 0, -1))[2] == session]
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in tree:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        try:
            os.killpg(child.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass
        deadline = time.monotonic() + GRACE_S
        while time.monotonic() < deadline:
            child.poll()
            tree = [p for p in tree if _alive(p)]
            if not tree:
                break
            time.sleep(0.02)
        if not tree:
            break
    child.wait()


def group_members(pgid: int) -> list[int]:
    """The live processes of process group ``pgid``, from ``/proc``.  A zombie is not one: it
    has ended and holds nothing but its process id until its parent reaps it, and an orphan's
    parent is init, which reaps when it gets to it (a second or more in some containers)."""
    members = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            st = _stat(int(entry))
            if st is not None and st[1] == pgid and _alive(int(entry)):
                members.append(int(entry))
    return members


def _end_group(pgid: int) -> None:
    """Whatever a child that ended normally left in its process group (a fork server)."""
    try:
        os.killpg(pgid, signal.SIGTERM)
    except (ProcessLookupError, PermissionError):
        return
    deadline = time.monotonic() + GRACE_S
    while time.monotonic() < deadline:
        if not group_members(pgid):
            return
        time.sleep(0.02)
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _child_setup(parent: int) -> None:
    """In the child before it starts: a process group of its own (Ctrl-C at the terminal reaches
    the supervisor only), and SIGKILL when the supervisor dies (``kill -9`` of ``graphsfm``
    leaves no run behind that still holds the workspace)."""
    os.setpgrp()
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG, Linux
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass
    if os.getppid() != parent:  # the supervisor died before prctl
        os._exit(1)


def supervise(argv: list[str], on_stop: Callable[[int, str], None], env: dict[str, str] | None = None) -> int:
    """Run ``python argv...`` in a child process in its own process group, with this process's
    environment plus ``env``, and wait for it; on SIGINT or SIGTERM end it and everything it
    started, call ``on_stop(signum, where)`` (where: the stage the child last reported) and
    return 128 + signum.  Otherwise the child's exit code (128 + signal when a signal killed it)."""
    with tempfile.NamedTemporaryFile("w+", prefix="graphsfm-status-", delete=False) as status:
        status_path = status.name
    env = dict(os.environ, **(env or {}), **{STATUS_FILE_ENV: status_path})
    stop = {"signum": 0}

    def on_signal(signum, frame):
        if not stop["signum"]:
            stop["signum"] = signum
            raise _Stop(signum)

    saved = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    child = None
    try:
        parent = os.getpid()
        try:
            child = subprocess.Popen([sys.executable, *argv], env=env, stdin=subprocess.DEVNULL,
                                     preexec_fn=lambda: _child_setup(parent))
            code = child.wait()
        except _Stop as exc:
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C while ending the tree
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            if child is not None:
                end_tree(child)
            where = Path(status_path).read_text().strip() if Path(status_path).exists() else ""
            on_stop(exc.signum, where or "start-up")
            return 128 + exc.signum
        _end_group(child.pid)
        return 128 - code if code < 0 else code
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
        Path(status_path).unlink(missing_ok=True)
