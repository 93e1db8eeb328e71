"""The ``extract`` stage: SIFT keypoints and RootSIFT descriptors of every image, into database.db.

DESIGN.md, "The algorithm", step 1. :func:`run_extract` is the stage; :func:`extract_features`
(decoded image in, arrays out, no I/O) is the library function under it.

Conventions:

- Detector: OpenCV SIFT (``cv2.SIFT_create``); contrastThreshold 0.02 is COLMAP's default peak
  threshold (0.02 / 3 per octave layer on a [0, 1] image; OpenCV's own default is 0.04) and
  edgeThreshold 10 COLMAP's too; both are options. ``enable_precise_upscale=True``: OpenCV's
  default doubling of the image for the first octave maps upsampled pixel i to i / 2 instead
  of i / 2 - 0.25, which biases every keypoint by +0.25 px in x and y; the precise upscale has
  no such bias, so keypoints are in OpenCV's pixel-centre convention (a test rotates an image
  by 90 degrees and finds 90% of the keypoints within 0.3 px of where they must be).
- Images whose longer side exceeds ``max_image_size`` are shrunk with ``cv2.INTER_AREA`` before
  SIFT (SIFT never sees the full image); keypoints are mapped back to full-resolution pixels with
  OpenCV's pixel-centre convention ``x = (x_small + 0.5) * sx - 0.5`` (likewise y) and their
  scale multiplied by the mean of ``sx, sy``.
- At most ``max_num_features`` keypoint *locations* per image, each with at most
  ``MAX_ORIENTATIONS`` (2) orientations: COLMAP's meaning of the option (it caps the
  detections, then gives each up to ``max_num_orientations = 2`` descriptors), so a busy image
  holds about 1.2 x ``max_num_features`` keypoints (OpenCV's own ``nfeatures`` counts each
  orientation as a keypoint: 8,192 keypoints were only ~6,700 locations, and the oblique views
  of sceaux_castle found too few matches to register).  Which locations: by default the
  largest-scale ones, COLMAP's documented rule ("maximum number of features to detect, keeping
  larger-scale features"); coarse blobs recur across viewpoint and resolution changes where
  the finest ones are texture and noise (lund_door, 12 images of 8,192 locations each: AUC@1
  0.959 -> 0.975); ``keep_features="strongest"`` keeps the highest SIFT response instead
  (OpenCV's rule).  SIFT detects every keypoint; the kept ones get the descriptors
  ``detectAndCompute`` gives them (computed for the kept ones alone on large images, from the
  same doubled-image pyramid: :data:`DESCRIBE_ALL_PIXELS`).  Stored in the order kept.
- Keypoints are float32 rows ``(x, y, scale, orientation)``: the 4-column layout COLMAP reads.
  ``scale = KeyPoint.size / 2`` (OpenCV's size is the diameter ``2 sigma`` of the keypoint's
  Gaussian scale; COLMAP's and VLFeat's scale is ``sigma``), ``orientation =
  radians(KeyPoint.angle)`` in [0, 2 pi): OpenCV's angle is the dominant gradient direction in
  image axes (x right, y down), which is COLMAP's convention too. x, y use OpenCV's pixel centres
  in memory; ``Database.write_keypoints`` shifts them to COLMAP's (+0.5).
- Descriptors: RootSIFT (Arandjelovic & Zisserman 2012; COLMAP's default ``L1_ROOT``): each
  128-vector is L1-normalised and square-rooted (which gives unit L2 norm), then quantised as
  COLMAP does: ``uint8(min(round(512 * d), 255))``. Dividing the stored bytes by 512 gives the
  unit vector back (up to rounding and the rare clipping). With ``root_sift=False`` the vector
  is L2-normalised instead, then quantised the same way.
- Images, EXIF and grey levels: ``sfm.io.image_files``; cameras and ``--intrinsics``: ``sfm.features.cameras``.
- Bad files (empty, truncated, not an image) are skipped with one warning line each and listed
  in the result; the run goes on. Exact duplicate files are both kept, as COLMAP keeps them,
  with a warning (they make a zero-baseline pair that verification sees as degenerate).

Resuming: images that already have keypoints in ``WORK/database.db`` are skipped; each image is
written as soon as its worker returns it (``sfm.stages.extract_writer``, which also keeps
``WORK/extract.json``), so an interrupted run loses only the images in flight.

Parallelism: a ``ProcessPoolExecutor`` started as ``sfm.execution.process_pool`` says (forked from a
fork server that imported this module once, safe with OpenCV's threads; a worker killed by the
kernel raises ``BrokenProcessPool`` instead of hanging as ``multiprocessing.Pool`` would);
workers decode and run SIFT with ``cv2.setNumThreads(1)`` and return numpy arrays; only the
parent writes the database. ``num_workers = 1`` runs in-process. The workers import the
caller's main module, so a script that calls :func:`run_extract` with several workers needs the
usual ``if __name__ == "__main__":`` guard (the CLI has it).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from sfm.io.database import Database
from sfm.errors import InputError
from sfm.stages.extract_writer import SIDECAR, ExtractWriter, extract_ledger
from sfm.io.image_files import (
    BadImageError,
    ImageInfo,
    downscale,
    find_images,
    probe_image,
    read_gray,
    workers_for_memory,
)
from sfm.features.cameras import (
    CAMERA_MODES,
    CameraSpec,
    IntrinsicsTable,
    assign_cameras,
    read_intrinsics,
    warn_unused_lines,
)
from sfm.execution.process_pool import pool_context
from sfm.features.sift import detect_and_select, quantize_descriptors  # noqa: F401 (re-exported)
from sfm.io.workspace import DATABASE

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExtractOptions:
    """Options of ``graphsfm extract`` (defaults in the fields).

    max_image_size: images whose longer side is larger are shrunk to it (INTER_AREA) before
        SIFT; keypoints are still in full-resolution pixels.
    max_num_features: keypoint locations kept per image, each with up to 2 orientations
        (COLMAP's meaning).
    keep_features: one of largest_scale|strongest: which locations ``max_num_features``
        keeps: the largest-scale ones (COLMAP's rule) or those of highest SIFT response.
    camera_mode: one of auto|single|per-folder|per-image. auto: one camera per image size, EXIF
        make/model and EXIF focal; single: one camera for all images (they must have one size);
        per-folder: one camera per sub-folder; per-image: one camera per image.
    intrinsics: file of 'IMAGE_NAME WIDTH HEIGHT FX FY CX CY [...]' lines (name '*': every
        image; OpenCV pixel centres); the images it names get PINHOLE cameras with these values.
    num_workers: processes that decode images and run SIFT (0: one per core, fewer when memory
        is short: SIFT needs about 1.7 GB per worker at 3200 px; 1: in-process).
    root_sift: RootSIFT descriptors (L1-normalise, square root), else L2-normalised SIFT.
    contrast_threshold: OpenCV SIFT contrastThreshold (DoG peaks below it / 3 are dropped);
        0.02 is COLMAP's default peak threshold (0.02 / 3 octave layers) in the same units.
    edge_threshold: OpenCV SIFT edgeThreshold (curvature ratio limit; COLMAP's is 10 too).
    """

    max_image_size: int = 3200
    max_num_features: int = 8192
    keep_features: str = "largest_scale"
    camera_mode: str = "auto"
    intrinsics: Path | None = None
    num_workers: int = 0
    root_sift: bool = True
    contrast_threshold: float = 0.02
    edge_threshold: float = 10.0

    def __post_init__(self) -> None:
        if self.camera_mode not in CAMERA_MODES:
            raise ValueError(
                f"camera_mode must be one of {'|'.join(CAMERA_MODES)}, got {self.camera_mode!r}"
            )
        if self.max_image_size < 16:
            raise ValueError(
                f"max_image_size must be at least 16 pixels, got {self.max_image_size}"
            )
        if self.keep_features not in ("largest_scale", "strongest"):
            raise ValueError(f"keep_features must be largest_scale|strongest, got {self.keep_features!r}")
        if self.max_num_features < 1:
            raise ValueError(f"max_num_features must be positive, got {self.max_num_features}")
        if self.num_workers < 0:
            raise ValueError(f"num_workers must be >= 0 (0: all cores), got {self.num_workers}")
        if not (self.contrast_threshold > 0 and self.edge_threshold > 0):
            raise ValueError("contrast_threshold and edge_threshold must be positive")
        if self.intrinsics is not None and not isinstance(self.intrinsics, Path):
            object.__setattr__(self, "intrinsics", Path(self.intrinsics))


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


# ----------------------------------------------------------------------------- library
def detect_sift(gray: np.ndarray, options: ExtractOptions) -> tuple[np.ndarray, np.ndarray]:
    """SIFT on an 8-bit grey image as given: ``(keypoints (N, 4) float32 x, y, scale,
    orientation; descriptors (N, 128) uint8)``: at most ``max_num_features`` locations, each
    with at most ``MAX_ORIENTATIONS`` orientations, chosen by ``keep_features`` (module
    docstring; :func:`sfm.features.sift.detect_and_select`), in the order kept."""
    return detect_and_select(gray, options.contrast_threshold, options.edge_threshold,
                             options.max_num_features, options.keep_features, options.root_sift)


def extract_features(gray: np.ndarray, options: ExtractOptions) -> tuple[np.ndarray, np.ndarray]:
    """:func:`detect_sift` on ``gray`` shrunk to ``max_image_size``, keypoints in ``gray``'s
    pixels (OpenCV convention: ``x = (x_small + 0.5) * sx - 0.5``, scale times mean(sx, sy))."""
    small, sx, sy = downscale(gray, options.max_image_size)
    keypoints, descriptors = detect_sift(small, options)
    if (sx, sy) != (1.0, 1.0):
        keypoints[:, 0] = (keypoints[:, 0] + 0.5) * sx - 0.5
        keypoints[:, 1] = (keypoints[:, 1] + 0.5) * sy - 0.5
        keypoints[:, 2] *= (sx + sy) / 2.0
    return keypoints, descriptors


# ----------------------------------------------------------------------------- workers
@dataclass(frozen=True)
class _Job:
    name: str
    path: str
    options: ExtractOptions
    data: bytes | None = None  # the file's bytes, for workers on other machines (no shared disk)


@dataclass(frozen=True)
class _Extracted:
    name: str
    error: str = ""
    info: ImageInfo | None = None
    keypoints: np.ndarray | None = None
    descriptors: np.ndarray | None = None
    digest: str = ""


def _init_worker() -> None:
    cv2.setNumThreads(1)  # one image per process; OpenCV's own threads would oversubscribe


def _probe_job(job: _Job) -> tuple[str, ImageInfo | None, str]:
    try:
        return job.name, probe_image(Path(job.path)), ""
    except BadImageError as exc:
        return job.name, None, str(exc)


def _extract_job(job: _Job) -> _Extracted:
    try:
        data = job.data if job.data is not None else Path(job.path).read_bytes()
        gray, info = read_gray(data)
        keypoints, descriptors = extract_features(gray, job.options)
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
    return _Extracted(job.name, "", info, keypoints, descriptors, digest)


Mapper = Callable[[Callable[[Any], Any], Iterable[Any]], Iterator[Any]]


def _with_bytes(jobs: Iterable[_Job]) -> Iterator[_Job]:
    """Jobs carrying their file's bytes (read lazily, one window at a time), for remote workers."""
    for job in jobs:
        try:
            data = Path(job.path).read_bytes()
        except OSError:
            data = None  # the worker reports the error as it would for a local read
        yield _Job(job.name, job.path, job.options, data)


@contextmanager
def _mapper(num_workers: int, num_jobs: int, executor=None) -> Iterator[Mapper]:
    """An ordered ``map``: on a distributed ``executor`` (its ``imap``; headers are probed here,
    images travel as bytes), over a local process pool (``sfm.execution.process_pool``), or the built-in
    map for one worker."""
    if executor is not None and hasattr(executor, "imap"):
        def remote(func, items):
            if func is _probe_job:  # header reads: cheaper here than shipping every file
                return map(func, items)
            return executor.imap(func, _with_bytes(items))

        yield remote
        return
    workers = min(num_workers, num_jobs)
    if workers <= 1:
        yield lambda func, items: map(func, items)
        return
    pool = ProcessPoolExecutor(workers, mp_context=pool_context(), initializer=_init_worker)
    ok = False
    try:
        yield lambda func, items: pool.map(func, items)
        ok = True
    except BrokenProcessPool as exc:
        raise RuntimeError(
            "a feature-extraction worker died (out of memory on a large image?); rerun to resume, "
            "maybe with fewer workers or a smaller max_image_size"
        ) from exc
    finally:
        pool.shutdown(wait=ok, cancel_futures=True)


# ----------------------------------------------------------------------------- the stage
def _probe_all(
    jobs: list[_Job], mapper: Mapper, bad: list[tuple[str, str]]
) -> dict[str, ImageInfo]:
    infos = {}
    for name, info, error in mapper(_probe_job, jobs):
        if info is None:
            logger.warning("skipping %s: %s", name, error)
            bad.append((name, error))
        else:
            infos[name] = info
    return infos


def _extract_all(
    jobs: list[_Job], infos: dict[str, ImageInfo], specs: dict[str, CameraSpec],
    writer: ExtractWriter, mapper: Mapper, bad: list[tuple[str, str]],
) -> int:  # fmt: skip
    first_by_digest: dict[str, str] = {}
    extracted = 0
    results = mapper(_extract_job, jobs)
    for r in tqdm(results, total=len(jobs), desc="extract", unit="img", disable=None):
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
        writer.write(r.name, specs[r.name], r.keypoints, r.descriptors)
        extracted += 1
    return extracted


def run_extract(
    image_dir: Path, workspace: Path, options: ExtractOptions = ExtractOptions(), executor=None
) -> ExtractResult:
    """Extract features of every image under ``image_dir`` into ``workspace/database.db``.

    ``executor``: a distributed executor (:class:`sfm.execution.dask_cluster.DaskExecutor`) to run SIFT on
    its workers; the database is written here, by this process only.

    Skips images that already have keypoints there; raises :class:`InputError` when no image is
    found or usable, when the intrinsics file is malformed or disagrees with an image's size, or
    when ``camera_mode`` single/per-folder would give one camera two sizes. The database is
    closed (complete on its own, no WAL file) when this returns or raises.
    """
    t0 = time.perf_counter()
    image_dir, workspace = Path(image_dir), Path(workspace)
    if not image_dir.is_dir():
        raise InputError(f"image folder not found: {image_dir}")
    names = find_images(image_dir)
    if not names:
        raise InputError(f"no images found in {image_dir}")
    table: IntrinsicsTable | None = None
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
        jobs = [_Job(n, str(image_dir / n), options) for n in todo]
        if jobs:
            workers = options.num_workers or workers_for_memory(options.max_image_size)
            with _mapper(workers, len(jobs), executor) as mapper:
                infos = _probe_all(jobs, mapper, bad)
                specs = assign_cameras(infos, options.camera_mode, table)
                writer.check_reused(specs)
                jobs = [j for j in jobs if j.name in infos]
                extracted = _extract_all(jobs, infos, specs, writer, mapper, bad)
        if extracted == 0 and skipped == 0:
            first = f" (e.g. {bad[0][0]}: {bad[0][1]})" if bad else ""
            raise InputError(f"no usable images in {image_dir}: {len(bad)} unreadable files{first}")
        if extracted:
            writer.save()
        num_with_keypoints = len(db.images_with_keypoints())
        mean_keypoints = db.num_keypoints() / max(num_with_keypoints, 1)
        num_cameras = db.num_cameras()
    ledger.finish("extract", "")
    result = ExtractResult(len(names), extracted, skipped, bad, num_cameras, mean_keypoints,
                           time.perf_counter() - t0)  # fmt: skip
    logger.info(
        "extract: %d images extracted, %d skipped (already done), %d unusable; %d cameras; "
        "%.0f keypoints per image; %.1f s", result.num_extracted, skipped, len(bad), num_cameras,
        mean_keypoints, result.time_s,
    )  # fmt: skip
    return result
