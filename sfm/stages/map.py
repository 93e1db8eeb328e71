"""The ``map`` stage: local incremental SfM per cluster (paper section 3.2).

Without ``WORK/clusters.json`` every image is in one cluster and the models go to
``WORK/sparse/0``, ``WORK/sparse/1``, ... (largest first).  With it, cluster ``k``'s models go to
``WORK/clusters/C<k>/<m>/`` for the ``merge`` stage.  Each cluster is a self-contained
:class:`sfm.mapper.payload.MapperInput` built from the database and handed to an executor
(``sfm.execution.local``), so clusters run in parallel or on other machines.
"""

from __future__ import annotations

import copy
import logging
import shutil
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sfm.io.colmap_model import read_model, write_model
from sfm.io.database import Database
from sfm.errors import InputError, NoModelError
from sfm.execution.local import LocalExecutor
from sfm.mapper.payload import CameraPrior, MapperInput, MapperOptions
from sfm.core.model import Reconstruction
from sfm.viz.recorder import Recorder, log_model
from sfm.features.sift import keypoint_scales
from sfm.io.ledger import Ledger, database_fingerprint, fingerprint, options_record
from sfm.io.workspace import CLUSTERS, DATABASE, read_json, update_report

log = logging.getLogger(__name__)


class ClusterPayloads(Sequence[MapperInput]):
    """One :class:`MapperInput` per cluster (``None``: all images), read from the database
    when indexed: each holds its cluster's keypoints and verified matches, so building them
    one at a time keeps memory to the clusters in flight.  Images are named, everything else
    is arrays: a payload needs nothing from the caller's disk.  ``labels``, ``names`` and
    ``sizes`` need no read."""

    def __init__(self, db_path: Path, clusters: list[list[str]] | None, fixed_intrinsics: bool,
                 min_inliers: int, labels: list[str] | None = None) -> None:
        self.db_path, self.fixed_intrinsics, self.min_inliers = Path(db_path), fixed_intrinsics, min_inliers
        with Database(db_path, readonly=True) as db:
            self.images, self.cams = db.read_images(), db.read_cameras()
        by_name = {im.name: iid for iid, im in self.images.items()}
        self.whole = clusters is None
        self.groups = [sorted(self.images)] if clusters is None else [sorted(by_name[n] for n in c) for c in clusters]
        self.labels = list(labels) if labels else [f"C{k}" for k in range(len(self.groups))]
        self.names = [[self.images[i].name for i in ids] for ids in self.groups]
        self.sizes = [len(ids) for ids in self.groups]

    def __len__(self) -> int:
        return len(self.groups)

    def subset(self, indices: list[int]) -> ClusterPayloads:
        out = copy.copy(self)
        out.groups, out.labels = [self.groups[k] for k in indices], [self.labels[k] for k in indices]
        out.names, out.sizes = [self.names[k] for k in indices], [self.sizes[k] for k in indices]
        return out

    def __getitem__(self, k):  # type: ignore[override]
        if isinstance(k, slice):
            return [self[j] for j in range(len(self))[k]]
        ids, images, cams = self.groups[k], self.images, self.cams
        with Database(self.db_path, readonly=True) as db:
            geoms = db.read_two_view_geometries(min_config=2, min_inliers=self.min_inliers,
                                                image_ids=None if self.whole else ids)
            keypoints = db.read_all_keypoints(ids)
        local = {iid: n for n, iid in enumerate(ids)}
        cameras = {
            c: CameraPrior(cams[c].model, cams[c].width, cams[c].height, cams[c].params,
                           cams[c].prior_focal_length, fixed=self.fixed_intrinsics and cams[c].model == "PINHOLE")
            for c in sorted({images[i].camera_id for i in ids})
        }
        pairs = [(local[a], local[b], g.inlier_matches.astype(np.int32), int(g.config))
                 for (a, b), g in geoms.items() if a in local and b in local]
        del geoms
        return MapperInput(
            image_ids=list(ids), names=list(self.names[k]), camera_ids=[images[i].camera_id for i in ids],
            cameras=cameras, keypoints=[_with_scale(keypoints.pop(i, np.zeros((0, 2)))) for i in ids],
            pairs=pairs, label=self.labels[k],
        )


def _with_scale(keypoints: np.ndarray) -> np.ndarray:
    """A database keypoint table as the payload's (K, 2) pixels, or (K, 3) pixels and scale."""
    scales = keypoint_scales(keypoints)
    xy = np.asarray(keypoints, np.float64)[:, :2]
    return xy if scales is None else np.column_stack([xy, scales])


def load_payloads(db_path: Path, clusters: list[list[str]] | None, fixed_intrinsics: bool,
                  min_inliers: int, labels: list[str] | None = None) -> list[MapperInput]:
    """Every :class:`ClusterPayloads` payload at once (small problems, tests)."""
    return list(ClusterPayloads(db_path, clusters, fixed_intrinsics, min_inliers, labels))


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
    clusters, clusters_warnings = None, []
    if (workspace / CLUSTERS).exists():
        clusters_json = read_json(workspace / CLUSTERS)
        clusters = [c["members"] for c in clusters_json["clusters"]]
        clusters_warnings = clusters_json.get("warnings", [])
    # One cluster (all images fit): its models are final and go straight to sparse/.
    direct = clusters is None or len(clusters) == 1
    payloads = ClusterPayloads(db_path, clusters, fixed_intrinsics=not options.refine_given_intrinsics,
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
    per_cluster: list[dict] = [{} for _ in payloads.labels]
    for k, label in enumerate(payloads.labels):
        if label in done:
            per_cluster[k] = {**done[label], "reused": True}
            for m in range(len(done[label]["models"])) if recorder.enabled else ():
                model = read_model(_folder(workspace, direct, label) / str(m))
                log_model(recorder, f"clusters/{label}" + (f"/{m}" if m else ""), model)
    todo = [k for k, label in enumerate(payloads.labels) if label not in done]
    if done:
        log.info("map: %d of %d clusters finished by an earlier run with the same options: skipped (%s)",
                 len(done), len(payloads), ", ".join(sorted(done)))
    for res in executor.run(payloads.subset(todo), options.for_model(direct), recorder) if todo else ():
        k = todo[res.index]
        label = payloads.labels[k]
        written = write_models(res.models, _folder(workspace, direct, label))
        per_cluster[k] = {"cluster": label, "images": payloads.sizes[k], "worker": res.worker,
                          "models": written, "error": res.error}
        if res.error is None:  # a failed cluster is tried again by the next run
            ledger.data["map"]["clusters"][label] = per_cluster[k]
            ledger.save()
        for m, model in enumerate(res.models):
            log_model(recorder, f"clusters/{label}" + (f"/{m}" if m else ""), model)
    flat = [m for c in per_cluster for m in c["models"]]
    elapsed = time.perf_counter() - t0
    num_images = len({n for names in payloads.names for n in names})  # clusters overlap
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
    fields["warnings"] = clusters_warnings + fields["warnings"]  # the cluster stage logged its own
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
