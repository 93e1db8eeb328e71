"""Cluster payloads read from the database: what the ``map`` and ``merge`` stages hand to the mapper.

A :class:`sfm.mapper.payload.MapperInput` holds one cluster's images, cameras, keypoints and
verified matches; :class:`ClusterPayloads` reads each from ``WORK/database.db`` only when it is
indexed, so memory holds the clusters in flight, not all of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sfm.features.sift import keypoint_scales
from sfm.io.database import Database
from sfm.mapper.payload import CameraPrior, MapperInput
from sfm.mapper.tracks import keypoint_match_counts
from sfm.stages.extract_writer import given_camera_ids


class ClusterPayloads(Sequence[MapperInput]):
    """One :class:`MapperInput` per cluster (``None``: all images), read from the database
    when indexed: each holds its cluster's keypoints (and their colours, when the database
    has them) and verified matches, so building them
    one at a time keeps memory to the clusters in flight.  Images are named, everything else
    is arrays: a payload needs nothing from the caller's disk.  ``labels``, ``names`` and
    ``sizes`` need no read.  With ``fixed_intrinsics`` the cameras the ``--intrinsics`` file gave
    are held fixed (``WORK/extract.json``; in a database made elsewhere, its PINHOLE cameras).
    ``calibration`` (camera id -> parameters) replaces the database's parameters of those cameras
    as their priors: the values the mapper starts from and tests its self-calibration against
    (``sfm.mapper.principal_point``, ``sfm.mapper.distortion``)."""

    def __init__(self, db_path: Path, clusters: list[list[str]] | None, fixed_intrinsics: bool,
                 min_inliers: int, labels: list[str] | None = None,
                 calibration: dict[int, np.ndarray] | None = None) -> None:
        self.db_path, self.fixed_intrinsics, self.min_inliers = Path(db_path), fixed_intrinsics, min_inliers
        self.calibration = dict(calibration or {})
        with Database(db_path, readonly=True) as db:
            self.images, self.cams = db.read_images(), db.read_cameras()
        given = given_camera_ids(self.db_path.parent)
        self.given = {c for c, cam in self.cams.items() if cam.model == "PINHOLE"} if given is None else given
        by_name = {im.name: iid for iid, im in self.images.items()}
        self.whole = clusters is None
        self.groups = [sorted(self.images)] if clusters is None else [sorted(by_name[n] for n in c) for c in clusters]
        self.labels = list(labels) if labels else [f"C{k}" for k in range(len(self.groups))]
        self.names = [[self.images[i].name for i in ids] for ids in self.groups]
        self.sizes = [len(ids) for ids in self.groups]

    def __len__(self) -> int:
        return len(self.groups)

    def __getitem__(self, k):  # type: ignore[override]
        if isinstance(k, slice):
            return [self[j] for j in range(len(self))[k]]
        ids, images, cams = self.groups[k], self.images, self.cams
        with Database(self.db_path, readonly=True) as db:
            # pairs with images outside the cluster too: they count each keypoint's matches
            geoms = db.read_two_view_geometries(min_config=2, min_inliers=self.min_inliers,
                                                image_ids=None if self.whole else ids, touching=True)
            keypoints = db.read_all_keypoints(ids)
            colors = db.read_keypoint_colors(ids)
        local = {iid: n for n, iid in enumerate(ids)}
        cameras = {
            c: CameraPrior(cams[c].model, cams[c].width, cams[c].height, self.calibration.get(c, cams[c].params),
                           cams[c].prior_focal_length, fixed=self.fixed_intrinsics and c in self.given)
            for c in sorted({images[i].camera_id for i in ids})
        }
        pairs = [(local[a], local[b], g.inlier_matches.astype(np.int32), int(g.config))
                 for (a, b), g in geoms.items() if a in local and b in local]
        match_counts = keypoint_match_counts((len(keypoints.get(i, ())) for i in ids),
                                             ((local[image], g.inlier_matches[:, side])
                                              for (a, b), g in geoms.items()
                                              for side, image in enumerate((a, b)) if image in local))
        del geoms
        return MapperInput(
            image_ids=list(ids), names=list(self.names[k]), camera_ids=[images[i].camera_id for i in ids],
            cameras=cameras, keypoints=[_with_scale(keypoints.pop(i, np.zeros((0, 2)))) for i in ids],
            pairs=pairs, label=self.labels[k], match_counts=match_counts,
            colors=[colors.pop(i, _NO_COLORS) for i in ids] if colors else None,
        )


_NO_COLORS = np.zeros((0, 3), np.uint8)  # an image whose keypoint colours are not in the database


def _with_scale(keypoints: np.ndarray) -> np.ndarray:
    """A database keypoint table as the payload's (K, 2) pixels, or (K, 3) pixels and scale."""
    scales = keypoint_scales(keypoints)
    xy = np.asarray(keypoints, np.float64)[:, :2]
    return xy if scales is None else np.column_stack([xy, scales])


def load_payloads(db_path: Path, clusters: list[list[str]] | None, fixed_intrinsics: bool,
                  min_inliers: int, labels: list[str] | None = None) -> list[MapperInput]:
    """Every :class:`ClusterPayloads` payload at once (small problems, tests)."""
    return list(ClusterPayloads(db_path, clusters, fixed_intrinsics, min_inliers, labels))
