"""The workspace a run leaves (its files: the ``sfm.io`` package docstring): names and atomic writes.

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
#: Beside a georegistered model's files: the ENU origin and the fit (``sfm.evaluation.georegistration``).
GEOREGISTRATION = "georegistration.json"


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
