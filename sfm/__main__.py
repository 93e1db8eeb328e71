"""The program ``graphsfm`` (also ``python -m sfm``): a supervisor that starts the command in a
child process at once, and the child that runs it.

Two processes, for Ctrl-C: the parent only waits, so it can always end the run and every process
the run started (``sfm.execution.processes``).  The command line itself (flags, commands, the
one-line errors) is ``sfm.cli``, which the child imports.

This module imports next to nothing, and a command's start and end are arranged for speed,
since every command pays them:

1. The parent starts the child before it parses the arguments; the child parses them and
   reports a bad one itself (same line, same exit code).  The parent parses them only should it
   have to stop the run, to say which command stopped (:func:`sfm.cli.stopped`).
2. The child of a command that runs a local process pool starts the pool's fork server
   (``sfm.execution.process_pool``) first, before importing the command line and its stages:
   the server's imports (the whole pipeline) run beside the child's instead of after them, on
   the way to the first pool.  The arguments are not parsed yet, so
   :func:`runs_local_pool` reads the few words it needs from the raw command line; a wrong
   guess costs an idle server, never a result.
3. When the command has returned, the child collects its garbage once and then freezes what is
   left (``gc.freeze``): the interpreter's shutdown runs several full collections, each walking
   every object of the libraries imported (NumPy, SciPy, OpenCV, GTSAM, Rerun), and that walk
   was most of the time between a command's last line and its exit.  Everything else
   of the shutdown happens as usual (``atexit`` handlers, each module's objects released, the
   standard streams flushed); only cyclic garbage made during the shutdown itself is left to
   the end of the process.
"""

from __future__ import annotations

import gc
import os
import sys
from pathlib import Path

# Commands whose stages may run tasks in a local process pool (``sfm.execution.local``).
POOLED = {"extract", "match", "map", "reconstruct", "extend", "demo"}


def runs_local_pool(argv: list[str]) -> bool:
    """Whether the command line ``argv`` names a command of ``POOLED`` that keeps the local
    executor (no ``--executor dask``) and more than one worker (no ``--workers 1``, and a
    machine of more than one core when ``--workers`` is left at its default, one per core)."""
    command = next((word for word in argv if not word.startswith("-")), None)
    if command not in POOLED or "-h" in argv or "--help" in argv:
        return False
    value = {}
    for i, word in enumerate(argv):
        flag, _, attached = word.partition("=")
        if flag in ("--workers", "--executor"):
            value[flag] = attached or (argv[i + 1] if i + 1 < len(argv) else "")
    workers = value.get("--workers", "0")
    if value.get("--executor", "local") != "local" or workers == "1":
        return False
    from sfm.execution.process_pool import usable_cores

    return workers != "0" or usable_cores() > 1


def main() -> int:
    """Run ``graphsfm ARGS`` (``sys.argv``): supervised in a child where the platform allows
    (``/proc``, POSIX), here otherwise and in that child.  The exit code (``sfm.errors``)."""
    from sfm.core.progress import STATUS_FILE_ENV

    argv = sys.argv[1:]
    if os.name == "posix" and Path("/proc/self/stat").exists() and STATUS_FILE_ENV not in os.environ:
        from sfm.execution.processes import supervise

        # The resource tracker of a run that was stopped unlinks its semaphores without a warning.
        child = ["-W", "ignore:resource_tracker:UserWarning", "-c", _child_program(), *argv]
        # No Python process of the run puts the working directory first on its path (Python
        # 3.11+; _child_program): the fork server imports the pipeline before any code of ours
        # could say where from.
        return supervise(child, lambda signum, where: _stopped(argv, signum, where), env={"PYTHONSAFEPATH": "1"})
    if runs_local_pool(argv):
        from sfm.execution.process_pool import start_pool_server

        start_pool_server()
    from sfm.cli import main as run_command

    code = run_command(argv)
    gc.collect()  # what the command left: its finalizers run now
    gc.freeze()  # the shutdown's collections skip the rest (module docstring, 3.)
    return code


def _child_program() -> str:
    """The child's Python program: this module's :func:`main`, imported from the folder this
    very ``sfm`` package was imported from.  ``python -m`` and ``-c`` put the working directory
    first on the path, where a user's own ``sfm.py``, ``sfm/``, ``graph/`` or ``backend/``
    would otherwise be imported instead of graphsfm's (``PYTHONSAFEPATH``, which :func:`main`
    sets for the child and every Python process it starts, keeps the working directory off
    their paths from Python 3.11 on)."""
    root = str(Path(__file__).resolve().parents[1])
    return f"import sys; sys.path.insert(0, {root!r}); from sfm.__main__ import main; sys.exit(main())"


def _stopped(argv: list[str], signum: int, where: str) -> None:
    """The supervisor's line (and workspace notes) for a run a signal stopped."""
    from sfm.cli import stopped

    stopped(argv, signum, where)


if __name__ == "__main__":
    sys.exit(main())
