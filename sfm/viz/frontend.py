"""Rerun views of the front-end stages: image thumbnails with keypoints, the verified graph."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from sfm.io.database import Database
from sfm.viz.recorder import Recorder
from sfm.io.workspace import DATABASE

log = logging.getLogger(__name__)

THUMBNAIL = 256


def log_images(recorder: Recorder, image_dir: Path, workspace: Path) -> None:
    """``images/<name>``: a thumbnail (longer side 256 px) and its keypoints, at stage extract."""
    if not recorder.enabled:
        return
    import cv2
    import rerun as rr

    from sfm.io.image_files import read_gray

    recorder.stage("extract")
    with Database(Path(workspace) / DATABASE, readonly=True) as db:
        images = db.read_images()
        keypoints = db.read_all_keypoints()
    for image_id, record in sorted(images.items()):
        try:
            gray, _ = read_gray((Path(image_dir) / record.name).read_bytes())
        except Exception as exc:  # noqa: BLE001 - a thumbnail is not worth failing for
            log.debug("no thumbnail for %s: %s", record.name, exc)
            continue
        scale = THUMBNAIL / max(gray.shape[:2])
        thumb = cv2.resize(gray, (max(1, round(gray.shape[1] * scale)), max(1, round(gray.shape[0] * scale))), interpolation=cv2.INTER_AREA)
        kps = keypoints.get(image_id, np.zeros((0, 2)))[:, :2]
        recorder.log(f"images/{record.name}", rr.Image(thumb))
        recorder.log(f"images/{record.name}/keypoints", rr.Points2D((kps + 0.5) * scale - 0.5, radii=0.5))


def log_verified_graph(recorder: Recorder, workspace: Path, min_inliers: int = 15) -> None:
    """``graph/images`` at stage match: nodes are images, edges verified pairs (weight = inliers)."""
    if not recorder.enabled:
        return
    recorder.stage("match")
    with Database(Path(workspace) / DATABASE, readonly=True) as db:
        images = db.read_images()
        i, j, w = db.verified_pairs(min_inliers)
    ids = sorted(images)
    index = {v: k for k, v in enumerate(ids)}
    names = [images[v].name for v in ids]
    recorder.log_image_graph(names, np.array([index[int(a)] for a in i], dtype=np.int64),
                             np.array([index[int(b)] for b in j], dtype=np.int64), w)
