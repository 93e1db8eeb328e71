"""The workspace a run leaves (DESIGN.md, "The workspace a run leaves"): paths and atomic writes.

Every file a stage writes goes to a temporary name in the same folder and is renamed into
place, so an interrupted run never leaves a half-written file behind.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

DATABASE = "database.db"
CLUSTERS = "clusters.json"
MERGE = "merge.json"
REPORT = "report.json"
RECORDING = "recording.rrd"
LOG = "log.txt"
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
    with open(path) as f:
        return json.load(f)


def update_report(workspace: Path, fields: dict, times: dict | None = None) -> dict:
    """Merge ``fields`` (and stage wall times under ``"times"``) into ``WORK/report.json``."""
    path = Path(workspace) / REPORT
    report = read_json(path) if path.exists() else {}
    report.update(fields)
    if times:
        report.setdefault("times", {}).update({k: round(float(v), 3) for k, v in times.items()})
        stages = ("T_feat", "T_match", "T_GC", "T_SfM", "T_merge", "T_BA")
        report["times"]["total"] = round(sum(report["times"].get(k, 0.0) for k in stages), 3)
    write_json_atomic(path, report)
    return report


def image_dir_of(workspace: Path) -> Path | None:
    """The image folder the extract stage read (``WORK/extract.json``), if it still exists: where
    the recording finds the images of a workspace whose extraction ran earlier."""
    path = Path(workspace) / EXTRACT_STATE
    try:
        image_dir = Path(read_json(path)["image_dir"]) if path.exists() else None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return image_dir if image_dir is not None and image_dir.is_dir() else None
