"""The ``map`` stage: local incremental SfM per cluster (paper section 3.2).

Without ``WORK/clusters.json`` every image is in one cluster and the models go to
``WORK/sparse/0``, ``WORK/sparse/1``, ... (largest first).  With it, cluster ``k``'s models go to
``WORK/clusters/C<k>/<m>/`` for the ``merge`` stage.  Each cluster is a self-contained
:class:`sfm.mapper_input.MapperInput` built from the database and handed to an executor
(``sfm.executors``), so clusters run in parallel or on other machines.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sfm.colmap_io import read_model, write_model
from sfm.database import Database
from sfm.errors import InputError, NoModelError
from sfm.executors import LocalExecutor
from sfm.mapper_input import CameraPrior, MapperInput, MapperOptions
from sfm.model import Reconstruction
from sfm.recording import Recorder, log_model
from sfm.stages import Ledger, database_fingerprint, fingerprint, options_record
from sfm.workspace import CLUSTERS, DATABASE, read_json, update_report

log = logging.getLogger(__name__)


def load_payloads(db_path: Path, clusters: list[list[str]] | None, fixed_intrinsics: bool,
                  min_inliers: int, labels: list[str] | None = None) -> list[MapperInput]:
    """One :class:`MapperInput` per cluster (``None``: all images) from the database; images
    are named, everything else is arrays: the payload needs nothing from the caller's disk."""
    with Database(db_path, readonly=True) as db:
        images = db.read_images()
        cams = db.read_cameras()
        geoms = db.read_two_view_geometries(min_config=2, min_inliers=min_inliers)
        by_name = {im.name: iid for iid, im in images.items()}
        groups = [sorted(images)] if clusters is None else [sorted(by_name[n] for n in c) for c in clusters]
        keypoints = db.read_all_keypoints(sorted({i for g in groups for i in g}))
    payloads = []
    for k, ids in enumerate(groups):
        local = {iid: n for n, iid in enumerate(ids)}
        cameras = {
            c: CameraPrior(cams[c].model, cams[c].width, cams[c].height, cams[c].params,
                           cams[c].prior_focal_length, fixed=fixed_intrinsics and cams[c].model == "PINHOLE")
            for c in sorted({images[i].camera_id for i in ids})
        }
        pairs = [(local[a], local[b], g.inlier_matches.astype(np.int64), int(g.config))
                 for (a, b), g in geoms.items() if a in local and b in local]
        payloads.append(MapperInput(
            image_ids=list(ids), names=[images[i].name for i in ids], camera_ids=[images[i].camera_id for i in ids],
            cameras=cameras, keypoints=[keypoints.get(i, np.zeros((0, 2)))[:, :2].astype(np.float64) for i in ids],
            pairs=pairs, label=labels[k] if labels else f"C{k}",
        ))
    return payloads


def write_models(models: list[Reconstruction], folder: Path) -> list[dict]:
    """Models to ``folder/0``, ``folder/1``, ... (stale numbered folders removed first)."""
    if folder.exists():
        for old in folder.iterdir():
            if old.is_dir() and old.name.isdigit():
                shutil.rmtree(old)
    out = []
    for m, model in enumerate(models):
        write_model(model, folder / str(m))
        out.append({"path": str(folder / str(m)), **model.summary()})
    return out


@dataclass(frozen=True)
class MapResult:
    num_images: int
    num_clusters: int
    models: list[dict]
    clusters: list[dict]
    time_s: float
    direct: bool  # models written to sparse/ (one cluster), not clusters/ for merging


def run_map(workspace: Path, options: MapperOptions, recorder: Recorder | None = None, executor=None) -> MapResult:
    """Incremental SfM of every cluster (or of all images) in ``workspace``.

    Clusters that an earlier run with the same options and input finished (``WORK/stages.json``)
    are reused, not recomputed, so a run killed during ``map`` loses only the clusters in flight."""
    recorder = recorder or Recorder.disabled()
    executor = executor or LocalExecutor()
    workspace = Path(workspace)
    t0 = time.perf_counter()
    db_path = workspace / DATABASE
    if not db_path.exists():
        raise InputError(f"no database at {db_path}: run extract and match (or synth) first")
    clusters = None
    if (workspace / CLUSTERS).exists():
        clusters = [c["members"] for c in read_json(workspace / CLUSTERS)["clusters"]]
    # One cluster (all images fit): its models are final and go straight to sparse/.
    direct = clusters is None or len(clusters) == 1
    payloads = load_payloads(db_path, clusters, fixed_intrinsics=not options.refine_given_intrinsics,
                             min_inliers=options.min_num_matches)
    ledger = Ledger(workspace)
    opts, input_fp = options_record(options), fingerprint(database_fingerprint(db_path), clusters)
    done = _finished_clusters(ledger, opts, input_fp, workspace, direct)
    if done is None:
        if ledger.record("map"):
            log.info("map: runs again: %s", ledger.why_stale("map", opts, input_fp))
        for stale in (workspace / "clusters", workspace / "sparse"):  # never mixed with new results
            shutil.rmtree(stale, ignore_errors=True)
        ledger.start("map", opts, input_fp, keep={"clusters": {}})
        done = {}
    recorder.stage("map")
    per_cluster: list[dict] = [{} for _ in payloads]
    for k, p in enumerate(payloads):
        if p.label in done:
            per_cluster[k] = {**done[p.label], "reused": True}
            for m in range(len(done[p.label]["models"])) if recorder.enabled else ():
                model = read_model(_folder(workspace, direct, p.label) / str(m))
                log_model(recorder, f"clusters/{p.label}" + (f"/{m}" if m else ""), model)
    todo = [k for k, p in enumerate(payloads) if p.label not in done]
    if done:
        log.info("map: %d of %d clusters finished by an earlier run with the same options: skipped (%s)",
                 len(done), len(payloads), ", ".join(sorted(done)))
    for res in executor.run([payloads[k] for k in todo], options, recorder) if todo else ():
        k = todo[res.index]
        label = payloads[k].label
        written = write_models(res.models, _folder(workspace, direct, label))
        per_cluster[k] = {"cluster": label, "images": len(payloads[k].names), "worker": res.worker,
                          "models": written, "error": res.error}
        if res.error is None:  # a failed cluster is tried again by the next run
            ledger.data["map"]["clusters"][label] = per_cluster[k]
            ledger.save()
        for m, model in enumerate(res.models):
            log_model(recorder, f"clusters/{label}" + (f"/{m}" if m else ""), model)
    flat = [m for c in per_cluster for m in c["models"]]
    elapsed = time.perf_counter() - t0
    num_images = len({n for p in payloads for n in p.names})  # clusters overlap
    fields = {"images": num_images, "executor": executor.name, "scheduler": getattr(executor, "address", None),
              "clusters": per_cluster, "num_clusters": len(payloads),
              "mapper_options": asdict(options), "warnings": []}  # no stale warning of an earlier run
    if direct:
        flat.sort(key=lambda m: -m["registered"])
        fields["num_models"] = len(flat)
        if flat:
            fields.update({k: flat[0][k] for k in ("registered", "points", "mean_track_length", "mean_reprojection_error")})
        if len(flat) > 1:
            sizes = ", ".join(str(m["registered"]) for m in flat)
            fields["warnings"] = [f"{len(flat)} models: the images did not form one connected reconstruction (sizes {sizes})"]
    failed = fields["failed_clusters"] = [c["cluster"] for c in per_cluster if c["error"]]
    if failed:
        fields["warnings"].append(failed_clusters_warning(failed))
    for warning in fields["warnings"]:
        log.warning("%s", warning)
    update_report(workspace, fields, {"T_SfM": elapsed})
    ledger.finish("map", fingerprint(input_fp, opts, failed))
    if not flat:
        raise NoModelError("no model could be made: no image pair could be reconstructed (too few inliers or too small baselines)")
    log.info("map: %d clusters, %d local models, %.1f s", len(payloads), len(flat), elapsed)
    return MapResult(num_images, len(payloads), flat, per_cluster, round(elapsed, 3), direct)


def failed_clusters_warning(failed: list[str]) -> str:
    return f"{len(failed)} cluster(s) failed and are left out: {', '.join(failed)}"


def _folder(workspace: Path, direct: bool, label: str) -> Path:
    return workspace / "sparse" if direct else workspace / "clusters" / label


def _finished_clusters(ledger: Ledger, opts: dict, input_fp: str, workspace: Path, direct: bool) -> dict | None:
    """The clusters an earlier ``map`` with these options and this input finished, whose models
    are still on disk (``None``: no such run, start afresh)."""
    rec = ledger.record("map")
    if not rec or rec.get("options") != opts or rec.get("input") != input_fp:
        return None
    out = {}
    for label, entry in (rec.get("clusters") or {}).items():
        folder = _folder(workspace, direct, label)
        if all((folder / str(m) / "images.bin").exists() for m in range(len(entry.get("models", [])))):
            out[label] = entry
    return out
