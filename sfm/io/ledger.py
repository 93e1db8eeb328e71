"""Which results in a workspace are current: ``WORK/stages.json``, the stage ledger.

Every stage records the options it ran with and a fingerprint of its input, and marks itself
done only after its outputs are in place.  A rerun compares the options and the input it would
use with the record: a stage whose record matches is skipped (the log says so), one whose
options or input changed runs again, and so does everything after it, because a stage's output
is the next stage's input.  Inputs are fingerprinted by content (the image graph of the
database, the clusters, the local models), not by time stamps, so a stage that recomputes the
same result does not force the later ones to run again.

``map`` also records each cluster as it finishes, so a run killed during ``map`` keeps the
clusters that were done; ``extend`` (new images added to the finished model) records its
sub-steps and its clusters the same way, so a killed extension resumes where it stopped.  ``extract`` and ``match`` resume per image and per pair on their own
(the database is written one transaction per image or batch); the ledger only tells them when
their options changed, which makes their earlier rows stale.

Options that change how a stage runs but not what it computes (worker counts) are left out of
the record.  Results depend on the seed, which is recorded like any option.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np

from sfm.errors import DamagedFileError
from sfm.io.workspace import read_json, write_json_atomic

log = logging.getLogger(__name__)

LEDGER = "stages.json"
STAGES = ("extract", "match", "cluster", "map", "merge", "extend")
# How a stage runs, never what it computes.
EXECUTION_ONLY = frozenset({"num_workers", "workers"})


def options_record(*options: Any) -> dict:
    """The options that decide a stage's result, as JSON-able values (several dataclasses are
    merged; fields named in ``EXECUTION_ONLY`` are dropped)."""
    out: dict = {}
    for opt in options:
        d = dataclasses.asdict(opt) if dataclasses.is_dataclass(opt) else dict(opt)
        out.update({k: _plain(v) for k, v in d.items() if k not in EXECUTION_ONLY})
    return out


def _plain(v: Any) -> Any:
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, np.generic):
        return v.item()
    return v


def fingerprint(*parts: Any) -> str:
    """A short SHA-256 of JSON-able values and numpy arrays (dtype, shape and bytes)."""
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        elif isinstance(p, (bytes, bytearray)):
            h.update(p)
        else:
            h.update(json.dumps(_plain(p), sort_keys=True, default=str).encode())
        h.update(b"\x00")
    return h.hexdigest()[:20]


def files_fingerprint(root: Path, pattern: str = "**/*") -> str:
    """:func:`fingerprint` of the files under ``root`` matching ``pattern``: each one's path
    relative to ``root`` and its bytes, in path order."""
    root = Path(root)
    files = sorted(p for p in root.glob(pattern) if p.is_file()) if root.is_dir() else []
    return fingerprint(*[x for p in files for x in (p.relative_to(root).as_posix(), p.read_bytes())])


def changes(old: dict | None, new: dict) -> list[str]:
    """``key: old -> new`` for every option that differs (``[]`` when equal or no record)."""
    if not isinstance(old, dict):
        return []
    keys = sorted(set(old) | set(new))
    return [f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in keys if old.get(k) != new.get(k)]


_DB_TABLES = (  # what map and cluster read: cameras, images, keypoints, verified inlier matches
    "SELECT camera_id, model, width, height, params, prior_focal_length FROM cameras ORDER BY camera_id",
    "SELECT image_id, name, camera_id FROM images ORDER BY image_id",
    "SELECT image_id, rows, cols, data FROM keypoints ORDER BY image_id",
    "SELECT pair_id, rows, cols, data, config FROM two_view_geometries ORDER BY pair_id",
)
_db_cache: dict[tuple, str] = {}


def database_fingerprint(path: Path) -> str:
    """SHA-256 over the rows ``cluster`` and ``map`` read from ``database.db`` (cameras, images,
    keypoints, two-view geometries with their inlier matches); cached per file state."""
    path = Path(path)
    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    wal = path.with_name(path.name + "-wal")
    if wal.exists():
        key += (wal.stat().st_mtime_ns, wal.stat().st_size)
    if key in _db_cache:
        return _db_cache[key]
    h = hashlib.sha256()
    conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, timeout=60.0)
    try:
        for sql in _DB_TABLES:
            for row in conn.execute(sql):
                for v in row:
                    h.update(v if isinstance(v, bytes) else repr(v).encode())
                    h.update(b"|")
            h.update(b"\x00")
    finally:
        conn.close()
    _db_cache[key] = h.hexdigest()[:20]
    return _db_cache[key]


def resume_or_restart(workspace: Path, stage: str, options: dict, reset, what: str) -> Ledger:
    """For ``extract`` and ``match``, which resume row by row: when the options recorded by an
    earlier run differ from ``options``, ``reset()`` drops its now stale rows (the log says
    which options changed and ``what`` happens); the options are recorded."""
    ledger = Ledger(workspace)
    rec = ledger.record(stage)
    diff = changes(rec.get("options") if rec else None, options)
    if diff:
        log.warning("%s: options changed (%s): %s", stage, "; ".join(diff), what)
        reset()
    if rec is None or diff:
        ledger.start(stage, options, "")
    return ledger


class Ledger:
    """``WORK/stages.json``: per stage ``{"options", "input", "done", "output", ...}``."""

    def __init__(self, workspace: Path):
        self.path = Path(workspace) / LEDGER
        self.data: dict = {}
        if self.path.exists():
            try:
                data = read_json(self.path)
                self.data = data if isinstance(data, dict) else {}
            except (OSError, ValueError, DamagedFileError) as exc:
                log.warning("ignoring unreadable %s (every stage runs again): %s", self.path, exc)

    def record(self, stage: str) -> dict | None:
        rec = self.data.get(stage)
        return rec if isinstance(rec, dict) else None

    def is_current(self, stage: str, options: dict, input_fp: str) -> bool:
        rec = self.record(stage)
        return bool(rec and rec.get("done") and rec.get("options") == options and rec.get("input") == input_fp)

    def why_stale(self, stage: str, options: dict, input_fp: str) -> str:
        """Why ``stage`` must run: no record, an unfinished run, changed options or input."""
        rec = self.record(stage)
        if rec is None:
            return "no earlier run"
        diff = changes(rec.get("options"), options)
        if diff:
            return "options changed (" + "; ".join(diff) + ")"
        if rec.get("input") != input_fp:
            return "its input changed"
        return "the earlier run did not finish" if not rec.get("done") else "current"

    def start(self, stage: str, options: dict, input_fp: str, keep: dict | None = None) -> None:
        """Record that ``stage`` runs with ``options`` on ``input_fp``; the later stages' records
        are dropped (they were computed from what this stage is about to replace)."""
        dropped = [s for s in STAGES[STAGES.index(stage) + 1:] if self.data.pop(s, None) is not None]
        if dropped:
            log.info("%s: the earlier results of %s are stale and will be recomputed", stage, ", ".join(dropped))
        self.data[stage] = {"options": options, "input": input_fp, "done": False,
                            "started": time.strftime("%Y-%m-%dT%H:%M:%S"), **(keep or {})}
        self.save()

    def update(self, stage: str, **fields: Any) -> None:
        self.data.setdefault(stage, {}).update({k: _plain(v) for k, v in fields.items()})
        self.save()

    def finish(self, stage: str, output_fp: str, **fields: Any) -> None:
        self.update(stage, done=True, output=output_fp, finished=time.strftime("%Y-%m-%dT%H:%M:%S"), **fields)

    def save(self) -> None:
        write_json_atomic(self.path, self.data)
