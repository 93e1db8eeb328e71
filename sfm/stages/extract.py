"""The ``extract`` stage: SIFT keypoints and RootSIFT descriptors of every image, into database.db.

:func:`run_extract` finds the images (``sfm.io.image_files``), reads their headers and EXIF,
gives each a camera (``sfm.features.cameras``) and, from its EXIF GPS, a position prior
(the database's ``pose_priors``, WGS84), runs :func:`sfm.features.extraction.extract_features`
on each in parallel (on an executor of ``sfm.execution``), and writes each image as soon as it
returns (``sfm.stages.extract_writer``).

Bad files (empty, truncated, not an image) are skipped with one warning line each and listed in
the result; the run goes on. Exact duplicate files are both kept, as COLMAP keeps them, with a
warning (they make a zero-baseline pair that verification sees as degenerate).

Resuming: images that already have keypoints in ``WORK/database.db`` are skipped; each image is
written as soon as its worker returns it (``sfm.stages.extract_writer``, which also keeps
``WORK/extract.json``), so an interrupted run loses only the images in flight.

Parallelism: one task per image on an executor (``sfm.execution``): workers decode the image,
run SIFT, read the colour of each keypoint from the colour image (``sfm.features.colors``; with
a recording, they also make the image's thumbnail from it) and return numpy arrays; only this
process writes the database and the recording.  On a remote
executor the tasks carry the image's bytes (no shared disk).  Local workers are capped by
memory (``sfm.features.worker_memory``).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from sfm.core import progress
from sfm.errors import InputError
from sfm.execution.local import LocalExecutor, WorkerDied
from sfm.features.cameras import CameraSpec, IntrinsicsTable, assign_cameras, read_intrinsics, warn_unused_lines
from sfm.features.extraction import extract_features
from sfm.features.options import ExtractOptions
from sfm.io.database import Database
from sfm.features.colors import keypoint_colors
from sfm.features.worker_memory import workers_for_memory
from sfm.io.image_files import (BadImageError, ImageInfo, find_images, mask_path, probe_image, read_gray, read_mask,
                                read_rgb)
from sfm.io.report import update_report
from sfm.io.workspace import DATABASE
from sfm.stages.extract_writer import SIDECAR, ExtractWriter, extract_ledger
from sfm.viz.frontend import log_image
from sfm.viz.recorder import Recorder
from sfm.viz.thumbnails import Thumbnail, make_thumbnail
from sfm.viz.tour import extract_text

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExtractResult:
    """What :func:`run_extract` did.

    num_images: image files found in the folder; num_extracted: images extracted by this run;
    num_skipped_existing: images that already had features; bad_files: (name, reason) of the
    files skipped as unusable; num_cameras: cameras in the database; mean_keypoints: mean number
    of keypoints over the images in the database; time_s: wall time of the run.
    """

    num_images: int
    num_extracted: int
    num_skipped_existing: int
    bad_files: list[tuple[str, str]]
    num_cameras: int
    mean_keypoints: float
    time_s: float


# ----------------------------------------------------------------------------- workers
@dataclass(frozen=True)
class _Job:
    name: str
    path: str
    options: ExtractOptions
    data: bytes | None = None  # the file's bytes, for workers on other machines (no shared disk)
    mask: str | None = None  # the mask file (``--masks``), if the image has one
    mask_data: bytes | None = None  # its bytes, for workers on other machines
    thumbnail_size: int = 0  # > 0: also return a thumbnail of this size for the recording


@dataclass(frozen=True)
class _Extracted:
    name: str
    error: str = ""
    info: ImageInfo | None = None
    keypoints: np.ndarray | None = None
    descriptors: np.ndarray | None = None
    digest: str = ""
    colors: np.ndarray | None = None  # (N, 3) uint8 RGB at each keypoint
    thumbnail: Thumbnail | None = None


def _probe_job(job: _Job) -> tuple[str, ImageInfo | None, str]:
    try:
        return job.name, probe_image(Path(job.path)), ""
    except BadImageError as exc:
        return job.name, None, str(exc)


def _extract_job(job: _Job) -> _Extracted:
    try:
        data = job.data if job.data is not None else Path(job.path).read_bytes()
        gray, info = read_gray(data)
        mask = None
        if job.mask is not None:
            mask = read_mask(job.mask_data if job.mask_data is not None else Path(job.mask).read_bytes(), info)
        keypoints, descriptors = extract_features(gray, job.options, mask)
        del gray
        rgb = read_rgb(data)  # one more decode: about 2% of SIFT's time
        colors = keypoint_colors(rgb, keypoints)
        thumbnail = make_thumbnail(rgb, job.thumbnail_size) if job.thumbnail_size else None
        del rgb
    except BadImageError as exc:
        return _Extracted(job.name, str(exc))
    except OSError as exc:
        return _Extracted(job.name, f"cannot read: {exc.strerror or exc}")
    except MemoryError:
        return _Extracted(job.name, "out of memory")
    except cv2.error as exc:
        last_line = (str(exc).strip().splitlines() or ["unknown"])[-1]
        return _Extracted(job.name, f"OpenCV error: {last_line}")
    digest = hashlib.blake2b(data, digest_size=16).hexdigest()
    return _Extracted(job.name, "", info, keypoints, descriptors, digest, colors, thumbnail)


def _with_bytes(jobs: Iterable[_Job]) -> Iterator[_Job]:
    """Jobs carrying their file's bytes (read lazily, as the executor asks for the next job),
    for workers on other machines."""
    for job in jobs:
        data = mask_data = None  # on a failed read the worker reports the error as it would locally
        try:
            data = Path(job.path).read_bytes()
            mask_data = Path(job.mask).read_bytes() if job.mask is not None else None
        except OSError:
            pass
        yield replace(job, data=data, mask_data=mask_data)


# ----------------------------------------------------------------------------- the stage
def _mask_of(options: ExtractOptions, name: str) -> str | None:
    """The mask file of image ``name`` (COLMAP's ``MASKS/<name>.png``), None without one."""
    if options.masks is None:
        return None
    path = mask_path(options.masks, name)
    return str(path) if path.is_file() else None


def _probe_all(jobs: list[_Job], executor, max_workers: int, bad: list[tuple[str, str]]) -> dict[str, ImageInfo]:
    """Each image's header (size, EXIF): on the local workers, or here when they are remote
    (header reads are cheaper than shipping every file)."""
    prober = LocalExecutor(1) if executor.remote else executor
    infos = {}
    for result in prober.map(_probe_job, jobs, max_workers=max_workers):
        name, info, error = result.value
        if info is None:
            logger.warning("skipping %s: %s", name, error)
            bad.append((name, error))
        else:
            infos[name] = info
    return infos


def _extract_all(
    jobs: list[_Job], infos: dict[str, ImageInfo], specs: dict[str, CameraSpec],
    writer: ExtractWriter, executor, max_workers: int, bad: list[tuple[str, str]], recorder: Recorder,
) -> int:  # fmt: skip
    first_by_digest: dict[str, str] = {}
    extracted = 0
    items = _with_bytes(jobs) if executor.remote else jobs
    results = executor.map(_extract_job, items, num_items=len(jobs), max_workers=max_workers)
    for result in progress.bar(results, total=len(jobs), desc="extract", unit="img"):
        r = result.value
        error, probed = r.error, infos[r.name]
        if not error and (r.info.width, r.info.height) != (probed.width, probed.height):
            error = "the file changed while it was being read"
        if error:
            logger.warning("skipping %s: %s", r.name, error)
            bad.append((r.name, error))
            continue
        if r.digest in first_by_digest:
            logger.warning(
                "%s is an exact copy of %s; both are kept (as in COLMAP), but they form a "
                "zero-baseline pair", r.name, first_by_digest[r.digest],
            )  # fmt: skip
        first_by_digest.setdefault(r.digest, r.name)
        writer.write(r.name, specs[r.name], r.keypoints, r.descriptors, r.colors, probed.gps)
        if r.thumbnail is not None:
            log_image(recorder, r.name, r.thumbnail, r.keypoints)
        extracted += 1
    return extracted


def run_extract(
    image_dir: Path, workspace: Path, options: ExtractOptions = ExtractOptions(), executor=None,
    recorder: Recorder | None = None,
) -> ExtractResult:
    """Extract features of every image under ``image_dir`` into ``workspace/database.db``.

    ``executor``: where SIFT runs (``sfm.execution``; default: a local pool of one process per
    core, fewer when memory is short); the database is written here, by this process only.
    ``recorder``: each image's thumbnail and keypoints, and the stage's text, go to it.

    Skips images that already have keypoints there; raises :class:`InputError` when no image is
    found or usable, when the intrinsics file is malformed or disagrees with an image's size, or
    when ``camera_mode`` single/per-folder would give one camera two sizes. The database is
    closed (complete on its own, no WAL file) when this returns or raises.
    """
    t0 = time.perf_counter()
    progress.stage("extract")
    executor = executor or LocalExecutor()
    recorder = recorder or Recorder.disabled()
    image_dir, workspace = Path(image_dir), Path(workspace)
    if not image_dir.is_dir():
        raise InputError(f"--images: {image_dir} is a file, not a folder of images" if image_dir.exists()
                         else f"image folder not found: {image_dir}")
    names = find_images(image_dir)
    if not names:
        raise InputError(f"no images found in {image_dir}")
    table: IntrinsicsTable | None = None
    if options.masks is not None and not Path(options.masks).is_dir():
        raise InputError(f"mask folder not found: {options.masks}")
    if options.intrinsics is not None:
        table = read_intrinsics(options.intrinsics)
        warn_unused_lines(table, names)
    workspace.mkdir(parents=True, exist_ok=True)
    bad: list[tuple[str, str]] = []
    extracted = 0
    ledger = extract_ledger(workspace, options)
    with Database(workspace / DATABASE) as db:
        writer = ExtractWriter(db, workspace / SIDECAR, image_dir, options)
        done = writer.names_with_keypoints()
        todo = [n for n in names if n not in done]
        skipped = len(names) - len(todo)
        if skipped:
            logger.info("%d of %d images already have features in %s: skipped", skipped,
                        len(names), db.path)  # fmt: skip
        thumbnail_size = recorder.options.thumbnail_size if recorder.requested else 0  # no wait for the stream
        recorder.image_dir = image_dir
        jobs = [_Job(n, str(image_dir / n), options, mask=_mask_of(options, n), thumbnail_size=thumbnail_size)
                for n in todo]
        if jobs:
            max_workers = workers_for_memory(options.max_image_size)
            try:
                infos = _probe_all(jobs, executor, max_workers, bad)
                specs = assign_cameras(infos, options.camera_mode, table, options.camera_model)
                writer.check_reused(specs)
                jobs = [j for j in jobs if j.name in infos]
                extracted = _extract_all(jobs, infos, specs, writer, executor, max_workers, bad, recorder)
            except WorkerDied as exc:
                raise RuntimeError(
                    "a feature-extraction worker died (out of memory on a large image?); rerun to resume, "
                    "maybe with fewer workers or a smaller max_image_size"
                ) from exc
        if extracted == 0 and skipped == 0:
            first = f" (e.g. {bad[0][0]}: {bad[0][1]})" if bad else ""
            raise InputError(f"no usable images in {image_dir}: {len(bad)} unreadable files{first}")
        if extracted:
            writer.save()
        num_with_keypoints = len(db.images_with_keypoints())
        mean_keypoints = db.num_keypoints() / max(num_with_keypoints, 1)
        num_cameras = db.num_cameras()
        if recorder.enabled:
            log_extract(recorder, db, options, bad)
    ledger.finish("extract", "")
    update_report(workspace, {"image_dir": str(image_dir.resolve()),
                              "bad_files": [{"name": n, "reason": r} for n, r in bad]},
                  {"extract": time.perf_counter() - t0})
    result = ExtractResult(len(names), extracted, skipped, bad, num_cameras, mean_keypoints,
                           time.perf_counter() - t0)  # fmt: skip
    logger.info(
        "extract: %d images extracted, %d skipped (already done), %d unusable; %d cameras; "
        "%.0f keypoints per image; %.1f s", result.num_extracted, skipped, len(bad), num_cameras,
        mean_keypoints, result.time_s,
    )  # fmt: skip
    return result


def log_extract(recorder: Recorder, db: Database, options: ExtractOptions, bad: list[tuple[str, str]]) -> None:
    """The images this run did not extract (a resumed run) read again for their thumbnails,
    then the stage's text of the tour."""
    recorder.stage("extract")
    images = db.read_images()
    for image_id, record in sorted(images.items(), key=lambda kv: kv[1].name):
        if record.name not in recorder.thumbnails:
            thumb = recorder.thumbnail(record.name)
            keypoints = db.read_keypoints(image_id)
            if thumb is not None and len(keypoints):
                log_image(recorder, record.name, thumb, keypoints)
    counts = np.array(list(db.keypoint_counts().values()), dtype=np.int64)
    recorder.tour("extract", extract_text(counts, db.num_cameras(), options, bad))
