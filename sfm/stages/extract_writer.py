"""Where the ``extract`` stage writes: database rows, and the resume state in ``extract.json``.

:class:`ExtractWriter` is used by :func:`sfm.stages.extract.run_extract` (the stage), which hands it
each image as soon as its worker returns it. Each image is written (camera if new, image row,
keypoints, descriptors) in one transaction, so an interrupted run loses only the images in
flight, and a resumed run skips the images that already have keypoints in ``WORK/database.db``.
The colour of each keypoint (``sfm.features.colors``) goes into the same transaction.
``WORK/extract.json`` (written atomically) maps each shared camera's group key to its camera id,
so a resumed run puts new images on the cameras it made before, and lists the cameras whose
intrinsics the ``--intrinsics`` file gave (``given_intrinsics``: the mapper holds them fixed,
:func:`given_camera_ids`); the options a run used are
compared in the stage ledger, ``WORK/stages.json`` (:func:`extract_ledger`), which drops the
database when they changed.  COLMAP's tables hold nothing extra (the colours have a table of
their own).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sfm.io.database import Database
from sfm.errors import InputError
from sfm.features.cameras import CameraSpec
from sfm.io.ledger import Ledger, fingerprint, options_record, resume_or_restart
from sfm.io.workspace import DATABASE, read_json, write_json_atomic

if TYPE_CHECKING:
    from sfm.features.options import ExtractOptions

# The messages are the extract stage's: they keep its logger name (and its log configuration).
logger = logging.getLogger("sfm.stages.extract")

SIDECAR = "extract.json"


def _options_json(options: ExtractOptions) -> dict[str, Any]:
    d = dataclasses.asdict(options)
    d["intrinsics"] = None if options.intrinsics is None else str(options.intrinsics)
    d["masks"] = None if options.masks is None else str(options.masks)
    return d


def _masks_record(masks: Path) -> str:
    """A fingerprint of the mask folder: each mask's name, size and modification time."""
    files = sorted(p for p in Path(masks).rglob("*.png") if p.is_file())
    return fingerprint([(p.relative_to(masks).as_posix(), p.stat().st_size, p.stat().st_mtime_ns) for p in files])


def extract_options_record(options: ExtractOptions) -> dict:
    """What the ledger records of the extract options: the options, the intrinsics file by its
    content, the mask folder by its files' names, sizes and times."""
    record = options_record(options)
    if options.intrinsics is not None and Path(options.intrinsics).is_file():
        record["intrinsics"] = fingerprint(Path(options.intrinsics).read_bytes())
    if options.masks is not None and Path(options.masks).is_dir():
        record["masks"] = _masks_record(Path(options.masks))
    return record


def extract_ledger(workspace: Path, options: ExtractOptions) -> Ledger:
    """The stage ledger, after dropping the database when the options that decide the features
    or the cameras changed since the images in it were extracted (:func:`extract_options_record`):
    every image is then extracted again, and every later stage runs again."""
    record = extract_options_record(options)

    def reset() -> None:
        for name in (DATABASE, DATABASE + "-wal", DATABASE + "-shm", SIDECAR):
            (workspace / name).unlink(missing_ok=True)

    return resume_or_restart(workspace, "extract", record, reset,
                             "the database is deleted and every image is extracted again")


class ExtractWriter:
    """Writes extracted images into the database and keeps ``extract.json`` in step."""

    def __init__(self, db: Database, sidecar: Path, image_dir: Path, options: ExtractOptions):
        self.db, self.sidecar, self.options = db, sidecar, options
        self.image_dir = str(image_dir.resolve())
        self.image_ids = db.image_id_by_name()
        self.image_cameras = {r.name: r.camera_id for r in db.read_images().values()}
        self.cameras = db.read_cameras()
        self.next_camera_id = max(self.cameras, default=0) + 1
        data = self._load() if self.image_ids else {}  # a new database: forget old cameras
        cameras = data.get("cameras")
        self.camera_ids = {
            str(k): v for k, v in (cameras.items() if isinstance(cameras, dict) else ())
            if isinstance(v, int) and v in self.cameras  # a kill may leave ids never committed
        }  # fmt: skip
        given = data.get("given_intrinsics")
        self.given = {v for v in (given if isinstance(given, list) else ()) if isinstance(v, int) and v in self.cameras}

    def _load(self) -> dict:
        if not self.sidecar.exists():
            return {}
        try:
            data = read_json(self.sidecar)
            return data if isinstance(data, dict) else {}
        except (OSError, ValueError) as exc:
            logger.warning("ignoring unreadable %s: %s", self.sidecar, exc)
            return {}

    def save(self) -> None:
        write_json_atomic(self.sidecar, {
            "version": 1, "image_dir": self.image_dir, "options": _options_json(self.options),
            "cameras": self.camera_ids, "given_intrinsics": sorted(self.given),
        })  # fmt: skip

    def names_with_keypoints(self) -> set[str]:
        with_kp = self.db.images_with_keypoints()
        return {n for n, i in self.image_ids.items() if i in with_kp}

    def check_reused(self, specs: dict[str, CameraSpec]) -> None:
        """A camera reused from an earlier run must have the size of its new images."""
        for name, spec in specs.items():
            camera_id = self.camera_ids.get(spec.key)
            cam = self.cameras.get(camera_id) if camera_id is not None else None
            if cam is not None and (cam.width, cam.height) != (spec.width, spec.height):
                raise InputError(
                    f"{name} is {spec.width}x{spec.height} but camera {camera_id}, made for its "
                    f"group by an earlier run, is {cam.width}x{cam.height}; use camera_mode auto"
                )

    def _camera_id(self, name: str, spec: CameraSpec) -> int:
        if name in self.image_cameras:  # an image row without keypoints: keep its camera
            return self.image_cameras[name]
        if spec.key in self.camera_ids:
            return self.camera_ids[spec.key]
        camera_id = self.next_camera_id
        self.next_camera_id += 1
        if spec.shared:  # record before the commit: a kill in between leaves a dangling entry,
            self.camera_ids[spec.key] = camera_id  # which the next run drops, never a lost key
        if spec.given:
            self.given.add(camera_id)
        if spec.shared or spec.given:
            self.save()
        self.db.add_camera(spec.model, spec.width, spec.height, spec.params,
                           spec.prior_focal_length, camera_id=camera_id)  # fmt: skip
        return camera_id

    def write(self, name: str, spec: CameraSpec, keypoints: np.ndarray, descriptors: np.ndarray,
              colors: np.ndarray | None = None, gps: tuple[float, float, float] | None = None):
        """One image (its camera if new, its row, keypoints, descriptors, keypoint colours and EXIF
        GPS as a WGS84 pose prior) in one transaction."""
        with self.db.transaction():
            camera_id = self._camera_id(name, spec)
            image_id = self.image_ids.get(name)
            if image_id is None:
                image_id = self.db.add_image(name, camera_id)
            if gps is not None:
                self.db.write_pose_prior(image_id, camera_id, gps)
            self.db.write_keypoints(image_id, keypoints)
            self.db.write_descriptors(image_id, descriptors)
            if colors is not None:
                self.db.write_keypoint_colors(image_id, colors)
        self.image_ids[name] = image_id
        self.image_cameras[name] = camera_id


def given_camera_ids(workspace: Path) -> set[int] | None:
    """Ids of the cameras whose intrinsics the ``--intrinsics`` file gave, from
    ``WORK/extract.json``; None when the workspace has no such record (a database made
    elsewhere, or by ``graphsfm synth``)."""
    path = Path(workspace) / SIDECAR
    try:
        data = read_json(path) if path.exists() else None
    except (OSError, ValueError):
        return None
    given = data.get("given_intrinsics") if isinstance(data, dict) else None
    return {v for v in given if isinstance(v, int)} if isinstance(given, list) else None
