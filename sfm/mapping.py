"""The ``map`` stage: local incremental SfM per cluster (paper section 3.2).

Without ``WORK/clusters.json`` every image is in one cluster and the models go to
``WORK/sparse/0``, ``WORK/sparse/1``, ... (largest first).  With it, cluster ``k``'s models go to
``WORK/clusters/C<k>/<m>/`` for the ``merge`` stage.  Each cluster is a self-contained
:class:`sfm.mapper_input.MapperInput` built from the database, so it can run anywhere.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sfm.colmap_io import write_model
from sfm.database import Database
from sfm.errors import InputError, NoModelError
from sfm.incremental import reconstruct_incremental
from sfm.mapper_input import CameraPrior, MapperInput, MapperOptions
from sfm.model import Reconstruction
from sfm.recording import Recorder
from sfm.workspace import CLUSTERS, DATABASE, REPORT, read_json, write_json_atomic

log = logging.getLogger(__name__)


def load_payloads(db_path: Path, clusters: list[list[str]] | None, fixed_intrinsics: bool,
                  min_inliers: int, labels: list[str] | None = None) -> list[MapperInput]:
    """One :class:`MapperInput` per cluster (``None``: all images) from the database."""
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
        cam_ids = sorted({images[i].camera_id for i in ids})
        cameras = {
            c: CameraPrior(cams[c].model, cams[c].width, cams[c].height, cams[c].params,
                           cams[c].prior_focal_length, fixed=fixed_intrinsics and cams[c].model == "PINHOLE")
            for c in cam_ids
        }
        pairs = [
            (local[a], local[b], g.inlier_matches.astype(np.int64), int(g.config))
            for (a, b), g in geoms.items()
            if a in local and b in local
        ]
        payloads.append(MapperInput(
            image_ids=list(ids), names=[images[i].name for i in ids], camera_ids=[images[i].camera_id for i in ids],
            cameras=cameras, keypoints=[keypoints.get(i, np.zeros((0, 2)))[:, :2].astype(np.float64) for i in ids],
            pairs=pairs, label=labels[k] if labels else f"C{k}",
        ))
    return payloads


@dataclass(frozen=True)
class MapResult:
    num_images: int
    num_clusters: int
    models: list[dict]
    time_s: float


def _write_models(models: list[Reconstruction], folder: Path) -> list[dict]:
    if folder.exists():
        for old in folder.iterdir():
            if old.is_dir() and old.name.isdigit():
                shutil.rmtree(old)
    out = []
    for m, model in enumerate(models):
        write_model(model, folder / str(m))
        out.append({"path": str(folder / str(m)), **model.summary()})
    return out


def run_map(workspace: Path, options: MapperOptions, recorder: Recorder | None = None) -> MapResult:
    """Incremental SfM of every cluster (or of all images) in ``workspace``."""
    recorder = recorder or Recorder.disabled()
    workspace = Path(workspace)
    t0 = time.perf_counter()
    db_path = workspace / DATABASE
    if not db_path.exists():
        raise InputError(f"no database at {db_path}: run extract and match (or synth) first")
    clusters_file = workspace / CLUSTERS
    clusters = None
    if clusters_file.exists():
        clusters = [c["members"] for c in read_json(clusters_file)["clusters"]]
    payloads = load_payloads(db_path, clusters, fixed_intrinsics=not options.refine_given_intrinsics, min_inliers=options.min_num_matches)
    recorder.stage("map")
    results = []
    for k, payload in enumerate(payloads):
        models = reconstruct_incremental(payload, options, recorder)
        folder = workspace / "sparse" if clusters is None else workspace / "clusters" / f"C{k}"
        results.append(_write_models(models, folder))
    flat = [m for r in results for m in r]
    elapsed = time.perf_counter() - t0
    num_images = sum(len(p.names) for p in payloads)
    if clusters is None:
        report = {"images": num_images, "models": flat, "T_SfM": round(elapsed, 3), "options": asdict(options)}
        if flat:
            best = flat[0]
            report.update({k: best[k] for k in ("registered", "points", "mean_track_length", "mean_reprojection_error")})
            if len(flat) > 1:
                report["warnings"] = [f"{len(flat)} models: the images did not form one connected reconstruction"]
        write_json_atomic(workspace / REPORT, report)
    if not flat:
        raise NoModelError("no model could be made: no image pair could be reconstructed (too few inliers or too small baselines)")
    log.info("map: %d models, largest %d/%d images registered, %.1f s", len(flat), flat[0]["registered"], num_images, elapsed)
    return MapResult(num_images, len(payloads), flat, round(elapsed, 3))
