"""The reconstruction data model: cameras, images, 3D points with tracks.

Conventions (those of the whole ``sfm`` package, stated in its docstring):

* ``Image.cam_from_world_rotation`` / ``cam_from_world_translation``: ``x_cam = R @ X + t``
  (COLMAP's images.txt).  The camera centre is ``-R.T @ t``.
* Keypoints use OpenCV's pixel convention (pixel centres at integers); so do the principal points
  in ``Camera.params``.  COLMAP's files and database are shifted by 0.5 at the I/O boundary
  (``sfm.io.colmap_model``, ``sfm.io.database``), nowhere else.
* ``Image.point3D_ids[k]`` is the id of the 3D point that keypoint ``k`` observes, or -1.
* A ``Point3D`` track is a list of ``(image_id, keypoint_index)`` observations.

Data classes hold data.  ``Reconstruction`` keeps the three tables consistent (a point's track
and the images' ``point3D_ids`` always agree) and offers the few operations every stage needs;
algorithms live in their own modules.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from backend.camera_models import calibration_matrix, model_spec, reprojection_errors
from backend.sim3 import Sim3

INVALID_POINT3D = -1


@dataclass
class Camera:
    """Intrinsics of one physical camera (a group of images): COLMAP model name and params."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray

    def __post_init__(self) -> None:
        self.params = np.asarray(self.params, dtype=np.float64)
        spec = model_spec(self.model)
        if self.params.shape != (spec.num_params,):
            raise ValueError(
                f"camera {self.camera_id}: model {self.model} takes {spec.num_params} params "
                f"({', '.join(spec.param_names)}), got {self.params.shape}"
            )

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name
        return calibration_matrix(self.model, self.params)


@dataclass
class Image:
    """One image: its camera, its pose ``cam_from_world`` (if registered) and keypoints."""

    image_id: int
    name: str
    camera_id: int
    cam_from_world_rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    cam_from_world_translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    keypoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point3D_ids: np.ndarray | None = None  # noqa: N815 - COLMAP's name
    registered: bool = True

    def __post_init__(self) -> None:
        self.cam_from_world_rotation = np.asarray(self.cam_from_world_rotation, dtype=np.float64)
        self.cam_from_world_translation = np.asarray(self.cam_from_world_translation, dtype=np.float64)
        self.keypoints = np.asarray(self.keypoints, dtype=np.float64).reshape(-1, 2)
        if self.point3D_ids is None:
            self.point3D_ids = np.full(len(self.keypoints), INVALID_POINT3D, dtype=np.int64)
        else:
            self.point3D_ids = np.asarray(self.point3D_ids, dtype=np.int64)
            if len(self.point3D_ids) != len(self.keypoints):
                raise ValueError(f"image {self.name}: point3D_ids and keypoints differ in length")

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.cam_from_world_rotation.T @ self.cam_from_world_translation

    @property
    def num_points3D(self) -> int:  # noqa: N802
        return int(np.count_nonzero(self.point3D_ids != INVALID_POINT3D))


@dataclass
class Point3D:
    """A triangulated point: position, colour (RGB uint8), mean reprojection error, track."""

    xyz: np.ndarray
    track: list[tuple[int, int]] = field(default_factory=list)
    color: np.ndarray = field(default_factory=lambda: np.full(3, 128, dtype=np.uint8))
    error: float = -1.0

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, dtype=np.float64)
        self.color = np.asarray(self.color, dtype=np.uint8)


@dataclass
class Reconstruction:
    """Cameras, images and 3D points with consistent observations."""

    cameras: dict[int, Camera] = field(default_factory=dict)
    images: dict[int, Image] = field(default_factory=dict)
    points3D: dict[int, Point3D] = field(default_factory=dict)  # noqa: N815
    _next_point_id: int = 1
    # What the last final BA that refined the model did (sfm.mapper.bundle_adjuster's
    # final_ba_summary); None for a model read from files.
    final_ba: dict | None = field(default=None, compare=False)

    # ------------------------------------------------------------------ building
    def add_camera(self, camera: Camera) -> None:
        self.cameras[camera.camera_id] = camera

    def add_image(self, image: Image) -> None:
        if image.camera_id not in self.cameras:
            raise KeyError(f"image {image.name}: camera {image.camera_id} not in the reconstruction")
        self.images[image.image_id] = image

    def add_point3D(  # noqa: N802
        self,
        xyz: np.ndarray,
        track: list[tuple[int, int]],
        color: np.ndarray | None = None,
        point3D_id: int | None = None,  # noqa: N803
    ) -> int:
        """Add a point observed by ``track`` and return its id (a fresh one unless given)."""
        if point3D_id is None:
            point3D_id = self._next_point_id
        elif point3D_id in self.points3D:
            raise KeyError(f"point {point3D_id} exists")
        self._next_point_id = max(self._next_point_id, point3D_id + 1)
        point = Point3D(xyz, [], np.full(3, 128, np.uint8) if color is None else color)
        self.points3D[point3D_id] = point
        for image_id, kp in track:
            self.add_observation(point3D_id, image_id, kp)
        return point3D_id

    def add_observation(self, point3D_id: int, image_id: int, keypoint_idx: int) -> None:  # noqa: N803
        image = self.images[image_id]
        current = image.point3D_ids[keypoint_idx]
        if current != INVALID_POINT3D and current != point3D_id:
            raise ValueError(f"keypoint {keypoint_idx} of {image.name} already observes point {current}")
        if current == point3D_id:
            return
        image.point3D_ids[keypoint_idx] = point3D_id
        self.points3D[point3D_id].track.append((image_id, int(keypoint_idx)))

    def remove_observation(self, image_id: int, keypoint_idx: int, min_track_length: int = 2) -> None:
        """Detach a keypoint from its point; the point is deleted if its track gets too short."""
        image = self.images[image_id]
        pid = int(image.point3D_ids[keypoint_idx])
        if pid == INVALID_POINT3D:
            return
        image.point3D_ids[keypoint_idx] = INVALID_POINT3D
        point = self.points3D[pid]
        point.track = [(i, k) for i, k in point.track if not (i == image_id and k == keypoint_idx)]
        if len(point.track) < min_track_length:
            self.remove_point3D(pid)

    def remove_point3D(self, point3D_id: int) -> None:  # noqa: N802, N803
        point = self.points3D.pop(point3D_id)
        for image_id, kp in point.track:
            self.images[image_id].point3D_ids[kp] = INVALID_POINT3D

    def remove_image(self, image_id: int, min_track_length: int = 2) -> None:
        """Remove an image and its observations; points left with too short tracks go too."""
        image = self.images[image_id]
        for kp in np.flatnonzero(image.point3D_ids != INVALID_POINT3D):
            self.remove_observation(image_id, int(kp), min_track_length)
        del self.images[image_id]

    # ------------------------------------------------------------------ queries
    @property
    def registered_image_ids(self) -> list[int]:
        return sorted(i for i, im in self.images.items() if im.registered)

    @property
    def num_observations(self) -> int:
        return sum(len(p.track) for p in self.points3D.values())

    @property
    def mean_track_length(self) -> float:
        return self.num_observations / len(self.points3D) if self.points3D else 0.0

    def image_by_name(self, name: str) -> Image:
        for image in self.images.values():
            if image.name == name:
                return image
        raise KeyError(name)

    def observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All observations as arrays ``(point3D_ids, image_ids, keypoint_indices)``."""
        pids, iids, kps = [], [], []
        for image_id, image in self.images.items():
            idx = np.flatnonzero(image.point3D_ids != INVALID_POINT3D)
            pids.append(image.point3D_ids[idx])
            iids.append(np.full(len(idx), image_id, dtype=np.int64))
            kps.append(idx)
        if not pids:
            empty = np.zeros(0, dtype=np.int64)
            return empty, empty, empty
        return np.concatenate(pids), np.concatenate(iids), np.concatenate(kps).astype(np.int64)

    def reprojection_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """Per observation: ``(point3D_ids, error_px)`` (``backend.camera_models``); a point an
        image observes that is not in the model is a ``KeyError``."""
        known = np.fromiter(self.points3D.keys(), dtype=np.int64, count=len(self.points3D))
        order = np.argsort(known)
        known = known[order]
        xyz_all = np.array([p.xyz for p in self.points3D.values()], dtype=np.float64).reshape(-1, 3)[order]
        cam_ids = sorted(self.cameras)
        cam_index = {c: k for k, c in enumerate(cam_ids)}
        images = list(self.images.values())
        rows = [np.flatnonzero(im.point3D_ids != INVALID_POINT3D) for im in images]
        pids = np.concatenate([im.point3D_ids[r] for im, r in zip(images, rows)] + [np.zeros(0, np.int64)])
        if len(pids) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        at = np.minimum(np.searchsorted(known, pids), max(len(known) - 1, 0))
        missing = np.flatnonzero(known[at] != pids) if len(known) else np.arange(len(pids))
        if len(missing):
            owner = np.repeat(np.arange(len(images)), [len(r) for r in rows])[missing[0]]
            raise KeyError(f"image {images[owner].name} observes point {pids[missing[0]]}, which is not in the model")
        err = reprojection_errors(
            [self.cameras[c].model for c in cam_ids], [self.cameras[c].params for c in cam_ids],
            np.array([cam_index[im.camera_id] for im in images], dtype=np.int64),
            np.array([im.cam_from_world_rotation for im in images]).reshape(-1, 3, 3),
            np.array([im.cam_from_world_translation for im in images]).reshape(-1, 3),
            np.repeat(np.arange(len(images)), [len(r) for r in rows]), xyz_all[at],
            np.concatenate([im.keypoints[r] for im, r in zip(images, rows)]))
        return pids, err

    def update_point_errors(self) -> float:
        """Set every point's ``error`` to its mean reprojection error; return the overall mean."""
        pids, err = self.reprojection_errors()
        if len(pids) == 0:
            return float("nan")
        uniq, inv = np.unique(pids, return_inverse=True)
        sums = np.bincount(inv, weights=err)
        counts = np.bincount(inv)
        for pid, s, c in zip(uniq, sums, counts):
            self.points3D[int(pid)].error = float(s / c)
        return float(err.mean())

    def mean_reprojection_error(self) -> float:
        _, err = self.reprojection_errors()
        return float(err.mean()) if len(err) else float("nan")

    # ------------------------------------------------------------------ transforms
    def transform(self, sim_new_from_old: Sim3) -> None:
        """Map the whole model by a similarity (points, and every registered pose)."""
        for point in self.points3D.values():
            point.xyz = sim_new_from_old.apply(point.xyz)
        for image in self.images.values():
            r, t = sim_new_from_old.transform_pose(
                image.cam_from_world_rotation, image.cam_from_world_translation
            )
            image.cam_from_world_rotation, image.cam_from_world_translation = r, t

    def subset(self, image_ids: list[int] | set[int], min_track_length: int = 2) -> Reconstruction:
        """A deep copy restricted to ``image_ids``; points keep their ids and the observations in
        those images, and are dropped if fewer than ``min_track_length`` remain."""
        keep = set(image_ids)
        out = Reconstruction(_next_point_id=self._next_point_id)
        for image_id in sorted(keep):
            image = self.images[image_id]
            if image.camera_id not in out.cameras:
                out.add_camera(copy.deepcopy(self.cameras[image.camera_id]))
            new_image = copy.deepcopy(image)
            new_image.point3D_ids[:] = INVALID_POINT3D
            out.add_image(new_image)
        for pid, point in self.points3D.items():
            track = [(i, k) for i, k in point.track if i in keep]
            if len(track) >= min_track_length:
                out.add_point3D(point.xyz.copy(), track, point.color.copy(), point3D_id=pid)
                out.points3D[pid].error = point.error
        return out

    def copy(self) -> Reconstruction:
        return copy.deepcopy(self)

    def summary(self) -> dict:
        """Counts every report needs (registered images, points, track length, reprojection)."""
        return {
            "cameras": len(self.cameras),
            "images": len(self.images),
            "registered": len(self.registered_image_ids),
            "points": len(self.points3D),
            "observations": self.num_observations,
            "mean_track_length": round(self.mean_track_length, 4),
            "mean_reprojection_error": round(self.mean_reprojection_error(), 4),
            "final_ba": self.final_ba,
        }
