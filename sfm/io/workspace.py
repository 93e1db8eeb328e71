"""The workspace a run leaves (its files: the ``sfm.io`` package docstring): names and atomic writes.

Every file a stage writes goes to a temporary name in the same folder and is renamed into
place, so an interrupted run never leaves a half-written file behind.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from sfm.core.progress import STATUS_FILE_ENV
from sfm.errors import DamagedFileError, WorkspaceBusyError

log = logging.getLogger(__name__)

DATABASE = "database.db"
CLUSTERS = "clusters.json"
MERGE = "merge.json"
REPORT = "report.json"
RECORDING = "recording.rrd"
LOG = "log.txt"
#: Beside a georegistered model's files: the ENU origin and the fit (``sfm.evaluation.georegistration``).
GEOREGISTRATION = "georegistration.json"
LOCK = "run.lock"
EXTRACT_STATE = "extract.json"


def write_json_atomic(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` via a temporary file and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(obj, f, indent=1)
            f.write("\n")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_json(path: Path) -> Any:
    """The JSON file ``path``; one that does not parse is a :class:`DamagedFileError`."""
    try:
        with open(path) as f:
            return json.load(f)
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
        raise DamagedFileError(path, f"not valid JSON: {exc}") from exc


GONE_OWNER_WAIT_S = 3.0


def _flock(fd: int, fcntl, wait_s: float = 0.0) -> bool:
    """Take the exclusive lock on ``fd``, trying for up to ``wait_s`` seconds."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except OSError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)


def _gone(owner: str) -> bool:
    """Whether the process named by a lock file's ``pid N, ...`` line no longer exists."""
    try:
        pid = int(owner.split(",")[0].split()[1])
    except (IndexError, ValueError):
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


class WorkspaceLock:
    """``WORK/run.lock``: one run at a time in a workspace.

    The run holds an exclusive ``flock`` on the file and writes its process id and command into
    it; a second run is refused at once (:class:`WorkspaceBusyError`, naming the owner).  The
    kernel drops the lock when its process ends, however it ends (``kill -9`` too), so the lock
    of a run that is gone is taken over without asking (after up to ``GONE_OWNER_WAIT_S`` when
    the process the file names is gone but its run is still exiting).  Nested use in one process (the command
    line, then :func:`sfm.stages.reconstruct.reconstruct`) shares the one lock.
    """

    _held: dict[str, list] = {}  # resolved path -> [fd, depth]

    def __init__(self, workspace: Path, command: str = "") -> None:
        self.path = Path(workspace) / LOCK
        self.command = command

    def __enter__(self) -> WorkspaceLock:
        key = str(self.path.resolve())
        if key in self._held:
            self._held[key][1] += 1
            return self
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX: no lock
            return self
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        if not _flock(fd, fcntl):
            owner = os.pread(fd, 4096, 0).decode(errors="replace").strip()
            # A supervisor killed with -9 has just taken its run with it (PR_SET_PDEATHSIG): the
            # lock is released as that run exits, a moment later.
            if not (_gone(owner) and _flock(fd, fcntl, wait_s=GONE_OWNER_WAIT_S)):
                os.close(fd)
                raise WorkspaceBusyError(f"workspace {self.path.parent} is in use by another run "
                                         f"({owner or 'a run that is starting'}): wait for it to end, or stop it")
        previous = os.pread(fd, 4096, 0).decode(errors="replace").strip()
        if previous:
            log.info("%s: the run that held it (%s) is gone: taken over", self.path, previous)
        # Under the command line's supervisor (sfm.execution.processes) its process id: the one to stop.
        supervisor = os.getppid() if os.environ.get(STATUS_FILE_ENV) else os.getpid()
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {supervisor}, {self.command or 'graphsfm'}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n"
                  .encode(), 0)
        self._held[key] = [fd, 1]
        return self

    def __exit__(self, *exc) -> None:
        key = str(self.path.resolve())
        held = self._held.get(key)
        if held is None:
            return
        held[1] -= 1
        if held[1] == 0:
            del self._held[key]
            os.ftruncate(held[0], 0)  # the file stays (empty): removing it would race a new run
            os.close(held[0])


def write_georegistration(model_folder: Path, registration: dict | None) -> None:
    """``model_folder/georegistration.json`` with the registration, or none at all."""
    path = Path(model_folder) / GEOREGISTRATION
    if registration is None:
        path.unlink(missing_ok=True)
    else:
        write_json_atomic(path, registration)


def read_georegistration(model_folder: Path) -> dict | None:
    """The registration a model folder holds, or None."""
    path = Path(model_folder) / GEOREGISTRATION
    return read_json(path) if path.is_file() else None


def numbered_folders(folder: Path) -> list[Path]:
    """The model folders ``folder/0``, ``folder/1``, ... in number order (none: ``[]``)."""
    if not Path(folder).is_dir():
        return []
    return sorted((d for d in Path(folder).iterdir() if d.is_dir() and d.name.isdigit()), key=lambda d: int(d.name))


def image_dir_of(workspace: Path) -> Path | None:
    """The image folder the extract stage read (``WORK/extract.json``), if it still exists: where
    the recording finds the images of a workspace whose extraction ran earlier."""
    path = Path(workspace) / EXTRACT_STATE
    try:
        image_dir = Path(read_json(path)["image_dir"]) if path.exists() else None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return image_dir if image_dir is not None and image_dir.is_dir() else None
