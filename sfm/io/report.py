"""``WORK/report.json``: what a run did, in one schema whatever the run.

Every key of :data:`SCHEMA` is always there (``None``, ``0`` or empty when it does not apply:
a one-cluster run has ``merged: false`` and ``merge_components: 0``, not a missing key), with
the unit its description gives; ``schema_version`` changes when a key changes meaning or goes.
Paths are absolute.  The stages fill their part as they finish (:func:`update_report`); a
command starts the report (:func:`start_run`: version, command line, start time) and ends it
(:func:`finish_run`: end time, status); the counts that the database and the final models hold
(keypoints per image, pairs tried and verified, images left unregistered and why) are read from
them when the final models are written (:func:`model_facts`).  README.md's "The workspace"
documents each key; ``tests/test_report.py`` checks runs against :data:`SCHEMA`.
"""

from __future__ import annotations

import datetime
import os
import statistics
from pathlib import Path
from typing import Any

from sfm.io.workspace import CLUSTERS, DATABASE, LOG, MERGE, RECORDING, REPORT, read_json, write_json_atomic

SCHEMA_VERSION = 1
_OPT_STR, _OPT_NUM = (str, type(None)), (int, float, type(None))

# key: (allowed JSON types, description with unit)
SCHEMA: dict[str, tuple[tuple[type, ...], str]] = {
    "schema_version": ((int,), "version of this schema"),
    "graphsfm_version": ((str,), "graphsfm's version"),
    "command": (_OPT_STR, "the command line (null from the Python API)"),
    "status": ((str,), "running, finished, failed or stopped"),
    "started": ((str,), "start time, ISO 8601 with UTC offset"),
    "finished": (_OPT_STR, "end time, ISO 8601 (null while running)"),
    "workspace": ((str,), "absolute path of the workspace"),
    "image_dir": (_OPT_STR, "absolute path of the image folder (null: started from a database)"),
    "files": ((dict,), "absolute paths: database, clusters (clusters.json), merge (merge.json), ledger, "
                       "log, recording (null when absent)"),
    "images": ((int,), "images in the database"),
    "bad_files": ((list,), "files skipped by extraction: {name, reason}"),
    "cameras": ((int,), "cameras in the database"),
    "keypoints_per_image": ((dict, type(None)), "keypoints per image: mean, median, min, max"),
    "pairs_tried": ((int,), "image pairs matched and verified (a two-view geometry row each)"),
    "pairs_verified": ((int,), "pairs with a verified geometry and enough inliers"),
    "median_inliers": ((int, float), "median inlier matches of the verified pairs"),
    "num_clusters": ((int,), "clusters of the image graph (1: no clustering)"),
    "clusters": ((list,), "per cluster: cluster, images, worker, models (path, registered, points, ...), "
                          "error, reused, left_out (image -> why its largest model left it out), unjoined "
                          "(why each other model did not join the largest as a whole)"),
    "failed_clusters": ((list,), "labels of the clusters whose local SfM failed"),
    "num_local_models": ((int,), "models made by the clusters' local SfM"),
    "merged": ((bool,), "whether local models were merged (false with one cluster)"),
    "merge_components": ((int,), "merge components (parts of the cluster graph), 0 when not merged"),
    "num_models": ((int,), "final models in sparse/"),
    "models": ((list,), "final models, largest first: path, cameras, images, registered, points, "
                        "observations, mean_track_length, mean_reprojection_error (px), final_ba (its last "
                        "final bundle adjustment: images, observations, parts, iterations, cost_before, "
                        "cost_after, rms_before_px, rms_after_px, stopped (why), solver_messages, time_s)"),
    "registered": ((int,), "images registered in the largest model (sparse/0)"),
    "points": ((int,), "3D points of the largest model"),
    "mean_track_length": (_OPT_NUM, "mean observations per point of the largest model"),
    "mean_reprojection_error_px": (_OPT_NUM, "mean reprojection error of the largest model, pixels"),
    "unregistered": ((list,), "images of the database in no final model: {name, reason}"),
    "georegistration": ((dict, type(None)), "the largest model's georegistration (GPS): origin_lat, origin_lon "
                                            "(degrees), origin_alt (m) of its east-north-up frame in metres, "
                                            "and the fit; null when not georegistered"),
    "accuracy": ((dict, type(None)), "against ground truth (graphsfm demo): registered, rotation error "
                                     "(deg), relative-pose AUC at 1/5/10 deg; null otherwise"),
    "extension": ((dict, type(None)), "graphsfm extend's summary: new_images, new_registered_in_model, "
                                      "own_models, ... and times_s per step; null otherwise"),
    "executor": (_OPT_STR, "local or dask"),
    "scheduler": (_OPT_STR, "the Dask scheduler's address (null: local)"),
    "workers": ((int, type(None)), "worker processes"),
    "warnings": ((list,), "what the run warned about, one line each"),
    "times_s": ((dict,), "wall time per stage, seconds: extract, match, cluster, map, merge, final_ba, "
                         "extend, total"),
}
STAGE_TIMES = ("extract", "match", "cluster", "map", "merge", "final_ba", "extend")


def now() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


def new_report(workspace: Path) -> dict:
    """Every key of :data:`SCHEMA`, empty."""
    from sfm import __version__

    workspace = Path(workspace).resolve()
    return {
        "schema_version": SCHEMA_VERSION, "graphsfm_version": __version__, "command": None, "status": "running",
        "started": now(), "finished": None, "workspace": str(workspace), "image_dir": None,
        "files": files(workspace), "images": 0, "bad_files": [], "cameras": 0, "keypoints_per_image": None,
        "pairs_tried": 0, "pairs_verified": 0, "median_inliers": 0, "num_clusters": 0, "clusters": [],
        "failed_clusters": [], "num_local_models": 0, "merged": False, "merge_components": 0, "num_models": 0,
        "models": [], "registered": 0, "points": 0, "mean_track_length": None, "mean_reprojection_error_px": None,
        "unregistered": [], "georegistration": None, "accuracy": None, "extension": None, "executor": None,
        "scheduler": None, "workers": None, "warnings": [],
        "times_s": {**dict.fromkeys(STAGE_TIMES, 0.0), "total": 0.0},
    }


def files(workspace: Path) -> dict:
    """The workspace's files the report points to (absolute; null when absent)."""
    workspace = Path(workspace).resolve()

    def there(name: str) -> str | None:
        return str(workspace / name) if (workspace / name).exists() else None

    return {"database": there(DATABASE), "clusters": there(CLUSTERS), "merge": there(MERGE),
            "ledger": there("stages.json"), "log": there(LOG), "recording": there(RECORDING)}


def read_report(workspace: Path) -> dict:
    """``WORK/report.json`` with every key of the schema (an older report's other keys dropped)."""
    path = Path(workspace) / REPORT
    report = new_report(workspace)
    if path.exists():
        old = read_json(path)
        if isinstance(old, dict):
            report.update({k: v for k, v in old.items() if k in SCHEMA})
            report["times_s"] = {**report["times_s"], **(old.get("times_s") or {})} if isinstance(
                old.get("times_s"), dict) else new_report(workspace)["times_s"]
    return report


def update_report(workspace: Path, fields: dict, times: dict | None = None) -> dict:
    """Merge ``fields`` (keys of :data:`SCHEMA`) and stage wall times (``times``: keys of
    ``STAGE_TIMES``, seconds) into ``WORK/report.json``; the total is their sum."""
    unknown = set(fields) - set(SCHEMA)
    if unknown:
        raise KeyError(f"not report.json keys: {sorted(unknown)}")
    report = read_report(workspace)
    report.update(fields)
    if times:
        bad = set(times) - set(STAGE_TIMES)
        if bad:
            raise KeyError(f"not stage times: {sorted(bad)}")
        report["times_s"].update({k: round(float(v), 3) for k, v in times.items()})
        report["times_s"]["total"] = round(sum(report["times_s"][k] for k in STAGE_TIMES), 3)
    report["files"] = files(workspace)
    write_json_atomic(Path(workspace) / REPORT, report)
    return report


def start_run(workspace: Path, command: str | None, *, fresh: bool, **fields: Any) -> dict:
    """A command starts: its version, command line and start time; ``fresh``: every other key
    emptied (``reconstruct``), else the earlier run's results stay (a single stage)."""
    Path(workspace).mkdir(parents=True, exist_ok=True)
    report = new_report(workspace) if fresh else read_report(workspace)
    header = new_report(workspace)
    report.update({k: header[k] for k in ("schema_version", "graphsfm_version", "started")},
                  command=command, status="running", finished=None, **fields)
    report["files"] = files(workspace)
    write_json_atomic(Path(workspace) / REPORT, report)
    return report


def finish_run(workspace: Path, status: str) -> dict:
    """The run ended (``finished``, ``failed`` or ``stopped``): its end time."""
    return update_report(workspace, {"status": status, "finished": now()})


def check_report(report: dict) -> list[str]:
    """What in ``report`` breaks :data:`SCHEMA` (missing, unknown or mistyped keys)."""
    problems = [f"missing {k}" for k in SCHEMA if k not in report]
    problems += [f"unknown {k}" for k in report if k not in SCHEMA]
    for key, (types, _) in SCHEMA.items():
        value = report.get(key)
        if key in report and not (isinstance(value, types) and not (isinstance(value, bool) and bool not in types)):
            problems.append(f"{key}: {type(value).__name__} is not {'/'.join(t.__name__ for t in types)}")
    return problems


def model_facts(workspace: Path, final_names: list[set[str]], clusters: list[dict] | None = None) -> dict:
    """The report's counts from the database and the final models (the registered image names
    of each, largest first): keypoints per image, pairs, and the images no final model holds,
    each with the reason (no keypoints, no verified pair, its cluster failed, or why each
    cluster's largest model left it out: the map stage's ``left_out`` of ``clusters``, the
    report's when not given)."""
    from sfm.io.database import Database

    workspace = Path(workspace)
    with Database(workspace / DATABASE, readonly=True) as db:
        names = {i: r.name for i, r in db.read_images().items()}
        counts = db.keypoint_counts()
        tried = db.num_two_view_geometries()
        id1, id2, inliers = db.verified_pairs(min_inliers=1)
        cameras = db.num_cameras()
    per_image = [counts.get(i, 0) for i in names]
    keypoints = None
    if per_image:
        keypoints = {"mean": round(statistics.fmean(per_image), 1), "median": float(statistics.median(per_image)),
                     "min": min(per_image), "max": max(per_image)}
    with_pair = {names[int(i)] for i in id1} | {names[int(i)] for i in id2}
    failed: dict[str, str] = {}
    clusters_path = workspace / CLUSTERS
    if clusters is None:
        clusters = read_report(workspace)["clusters"]
    errors = {c["cluster"]: c.get("error") for c in clusters if c.get("error")}
    if clusters_path.exists() and errors:
        for k, c in enumerate(read_json(clusters_path)["clusters"]):
            label = f"C{c.get('id', k)}"
            if label in errors:
                for name in c["members"]:
                    failed.setdefault(name, f"its cluster {label} failed: {errors[label]}")
    left_out: dict[str, list[str]] = {}
    for c in clusters:
        for name, reason in (c.get("left_out") or {}).items():
            left_out.setdefault(name, []).append(reason if len(clusters) == 1 else f"{c['cluster']}: {reason}")
    registered = set().union(*final_names) if final_names else set()
    unregistered = []
    for image_id, name in sorted(names.items(), key=lambda kv: kv[1]):
        if name in registered:
            continue
        if counts.get(image_id, 0) == 0:
            reason = "no keypoints"
        elif name not in with_pair:
            reason = "no verified pair with another image"
        elif name in failed:
            reason = failed[name]
        elif name in left_out:
            reason = "; ".join(left_out[name])
        else:
            reason = "no model registered it (too few verified matches to the registered images for a pose)"
        unregistered.append({"name": name, "reason": reason})
    return {"images": len(names), "cameras": cameras, "keypoints_per_image": keypoints, "pairs_tried": tried,
            "pairs_verified": int(len(inliers)),
            "median_inliers": float(statistics.median(inliers.tolist())) if len(inliers) else 0,
            "unregistered": unregistered}


def models_fields(written: list[dict]) -> dict:
    """``models`` (absolute paths) and the largest model's counts."""
    models = [{**m, "path": os.path.abspath(m["path"])} for m in written]
    best = models[0] if models else {}
    return {"models": models, "num_models": len(models), "registered": best.get("registered", 0),
            "points": best.get("points", 0), "mean_track_length": best.get("mean_track_length"),
            "mean_reprojection_error_px": best.get("mean_reprojection_error")}
