"""The ``match`` stage (DESIGN.md, algorithm steps 2-4): pairs, descriptor matching, verification.

:func:`run_match` reads images, cameras, keypoints and descriptors from ``WORK/database.db``,
selects pairs (``sfm.matching.pairs``), matches descriptors (:func:`match_descriptors`), verifies each pair
(``sfm.matching.verification``) and writes raw matches and two-view geometries back, one transaction per
batch of pairs, so a killed run loses at most one batch. Pairs that already have a two-view
geometry row are skipped: rerunning resumes.

Descriptor matching is :func:`sfm.matching.descriptors.match_descriptors`.

Parallelism: a process pool (``sfm.execution.process_pool``; scripts need the ``if __name__ == "__main__"``
guard) of ``num_workers`` (one OpenCV and BLAS thread each) reading features from the database
(an LRU cache): only pair ids and results travel. A dead worker raises ``BrokenProcessPool``;
finished batches stay. Any number of workers gives the same results (seeds per pair).
"""

from __future__ import annotations

import logging
import os
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from sfm.io.database import Database
from sfm.io.database_schema import CameraRecord, TwoViewGeometry
from sfm.matching.descriptors import match_descriptors, normalize_descriptors
from sfm.errors import InputError
from sfm.matching.pairs import select_pairs
from sfm.execution.process_pool import pool_context
from sfm.io.ledger import options_record, resume_or_restart
from sfm.matching.verification import VerifyOptions, pair_seed, to_colmap_pixels, verify_pair

logger = logging.getLogger(__name__)

BATCH_PAIRS = 100
BATCH_REMOTE = 64  # pairs per task on a distributed executor (one image's row, in exhaustive order)
CACHE_BYTES = 256 * 2**20
_V = VerifyOptions()


@dataclass(frozen=True)
class MatchOptions:
    """Options of the ``match`` stage.

    pairs: which pairs to match, one of auto|exhaustive|retrieval (auto: exhaustive below
      exhaustive_threshold images, else retrieval)
    top_k: retrieval keeps each image's top_k most similar images (VLAD)
    sequential: also match each image with the next N images in name order (0: off)
    matcher: nearest-neighbour search, one of auto|brute|flann (brute: exact; flann: KD-tree,
      approximate; auto: brute unless both images have many features)
    max_ratio: Lowe's ratio test on descriptor distances (COLMAP's max_ratio)
    cross_check: keep only mutual nearest neighbours
    max_error_px: verification inlier threshold in pixels (Sampson distance, H transfer error)
    confidence, max_iterations: RANSAC confidence and iteration cap of verification
    min_num_inliers: a pair with fewer inliers is not verified
    max_h_inlier_ratio: H inliers / E-or-F inliers above this mark a pair planar or panoramic
    num_workers: worker processes (0: all cores)
    seed: seed of the vocabulary, FLANN and RANSAC; the same seed gives the same matches
    """

    pairs: str = "auto"
    top_k: int = 30
    sequential: int = 0
    exhaustive_threshold: int = 200
    matcher: str = "auto"
    max_ratio: float = 0.8
    cross_check: bool = True
    max_error_px: float = _V.max_error_px
    confidence: float = _V.confidence
    max_iterations: int = _V.max_iterations
    min_num_inliers: int = _V.min_num_inliers
    max_h_inlier_ratio: float = _V.max_h_inlier_ratio
    num_workers: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.matcher not in ("auto", "brute", "flann"):
            raise ValueError(f"matcher must be one of auto|brute|flann, got {self.matcher!r}")
        if self.pairs not in ("auto", "exhaustive", "retrieval"):
            raise ValueError(f"pairs must be one of auto|exhaustive|retrieval, got {self.pairs!r}")
        if not 0 < self.max_ratio <= 1 or self.top_k < 1 or self.sequential < 0:
            raise ValueError("need 0 < max_ratio <= 1, top_k >= 1 and sequential >= 0")

    def verify_options(self) -> VerifyOptions:
        return VerifyOptions(self.max_error_px, self.confidence, self.max_iterations,
                             self.min_num_inliers, self.max_h_inlier_ratio)  # fmt: skip


@dataclass(frozen=True)
class MatchResult:
    """What ``run_match`` did.

    num_pairs_considered: pairs selected; num_pairs_skipped_existing of them already had a
    geometry; num_pairs_processed were matched now. num_verified and median_inliers describe all
    verified pairs in the database afterwards (config >= 2, >= min_num_inliers). Times are summed
    over pairs (worker seconds: descriptor matching, verification); time_total_s is wall time.
    """

    num_images: int
    num_pairs_considered: int
    num_pairs_skipped_existing: int
    num_pairs_processed: int
    num_verified: int
    median_inliers: float
    time_match_s: float
    time_verify_s: float
    time_total_s: float


# ------------------------------------------------------------------------------ one pair
class _PairProcessor:
    """Matches and verifies pairs, reading features from a database through an LRU cache."""

    def __init__(self, load: Callable[[int], tuple[np.ndarray, np.ndarray]], camera_of: dict[int, int],
                 cameras: dict[int, CameraRecord], options: MatchOptions) -> None:  # fmt: skip
        """``load``: image id -> (keypoints, uint8 descriptors); ``camera_of``: image id -> camera
        id; ``cameras``: camera id -> record."""
        self.load, self.camera_of, self.cameras, self.options = load, camera_of, cameras, options
        self.verify_options = options.verify_options()
        self._cache: OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()
        self._cache_bytes = 0

    def features(self, image_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keypoints, unit float32 descriptors, their C-contiguous transpose) of an image."""
        if image_id in self._cache:
            self._cache.move_to_end(image_id)
            return self._cache[image_id]
        keypoints, descriptors = self.load(image_id)
        unit = normalize_descriptors(descriptors)
        item = (keypoints, unit, np.ascontiguousarray(unit.T))
        self._cache[image_id] = item
        self._cache_bytes += sum(a.nbytes for a in item)
        while self._cache_bytes > CACHE_BYTES and len(self._cache) > 2:
            _, old = self._cache.popitem(last=False)
            self._cache_bytes -= sum(a.nbytes for a in old)
        return item

    def __call__(
        self, pair: tuple[int, int]
    ) -> tuple[int, int, np.ndarray, TwoViewGeometry, float, float]:
        id1, id2 = int(pair[0]), int(pair[1])
        (kp1, d1, _), (kp2, d2, d2t) = self.features(id1), self.features(id2)
        seed = pair_seed(self.options.seed, id1, id2)
        o = self.options
        t0 = time.perf_counter()
        matches = match_descriptors(d1, d2, o.max_ratio, o.cross_check, o.matcher, seed=seed, normalized=True,
                                    transposed2=d2t)  # fmt: skip
        t1 = time.perf_counter()
        cam1, cam2 = self.cameras[self.camera_of[id1]], self.cameras[self.camera_of[id2]]
        geometry = verify_pair(kp1, kp2, matches, cam1, cam2, self.verify_options, seed)
        return id1, id2, matches.astype(np.uint32), geometry, t1 - t0, time.perf_counter() - t1


_WORKER: _PairProcessor | None = None


def _init_worker(db_path: str, camera_of, cameras, options: MatchOptions) -> None:
    global _WORKER
    cv2.setNumThreads(1)
    from threadpoolctl import threadpool_limits  # scikit-learn's dependency

    threadpool_limits(1)
    _WORKER = _PairProcessor(_db_loader(Database(db_path, readonly=True)), camera_of, cameras, options)


def _work(pair: tuple[int, int]):
    assert _WORKER is not None
    return _WORKER(pair)


def _db_loader(db: Database) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
    return lambda image_id: (db.read_keypoints(image_id), db.read_descriptors(image_id))


@dataclass
class _Batch:
    """Pairs for a remote worker, with the features and cameras they need (no database there)."""

    pairs: list[tuple[int, int]]
    features: dict[int, tuple[np.ndarray, np.ndarray]]
    camera_of: dict[int, int]
    cameras: dict[int, CameraRecord]
    options: MatchOptions


def _work_batch(batch: _Batch) -> list:
    processor = _PairProcessor(batch.features.__getitem__, batch.camera_of, batch.cameras, batch.options)
    return [processor(pair) for pair in batch.pairs]


def _remote_batches(db: Database, todo: list[tuple[int, int]], camera_of, cameras, options: MatchOptions,
                    size: int) -> Iterator[_Batch]:
    """Consecutive pairs (exhaustive order keeps one image fixed) with their images' features."""
    for start in range(0, len(todo), size):
        pairs = todo[start:start + size]
        ids = sorted({i for p in pairs for i in p})
        features = {i: (db.read_keypoints(i), db.read_descriptors(i)) for i in ids}
        cams = {camera_of[i] for i in ids}
        yield _Batch(pairs, features, {i: camera_of[i] for i in ids}, {c: cameras[c] for c in cams}, options)


# ------------------------------------------------------------------------------ the stage
def _usable_images(db: Database, ordered_ids: list[int], names: dict[int, str]) -> list[int]:
    """Images with keypoints and as many descriptors; the others are skipped with a warning."""
    usable = []
    for image_id in ordered_ids:
        n = len(db.read_keypoints(image_id))
        n_desc = len(db.read_descriptors(image_id)) if n else 0
        if n == 0:
            logger.warning("image %s has no keypoints: skipped", names[image_id])
        elif n_desc != n:
            logger.warning("image %s has %d keypoints but %d descriptors: skipped",
                           names[image_id], n, n_desc)  # fmt: skip
        else:
            usable.append(image_id)
    return usable


def run_match(workspace: Path, options: MatchOptions = MatchOptions(), executor=None) -> MatchResult:
    """Match and verify the selected pairs of ``workspace/database.db`` (see module docstring).

    ``executor``: a distributed executor (:class:`sfm.execution.dask_cluster.DaskExecutor`); pairs then
    travel in batches with their images' features, and only this process writes the database."""
    start = time.perf_counter()
    db_path = Path(workspace) / "database.db"
    if not db_path.is_file():
        raise InputError(f"no database at {db_path}: run `graphsfm extract` first")
    with Database(db_path) as db:
        images = db.read_images()
        if not images:
            raise InputError(f"no images in {db_path}")
        names = {i: r.name for i, r in images.items()}
        ordered = sorted(images, key=lambda i: names[i])
        usable = _usable_images(db, ordered, names)
        if len(usable) < 2:  # one image: nothing to match, no model to make
            raise InputError(f"{len(usable)} image(s) in {db_path} with keypoints and descriptors: SfM needs at least 2")
        ledger = resume_or_restart(workspace, "match", options_record(options), db.clear_matches,
                                   "the stored matches are deleted and every pair is matched again")
        pairs = select_pairs(usable, options.pairs, top_k=options.top_k, sequential=options.sequential,
                             exhaustive_threshold=options.exhaustive_threshold, seed=options.seed,
                             load_descriptors=db.read_descriptors)  # fmt: skip
        done = db.pairs_with_geometry()
        todo = [(int(a), int(b)) for a, b in pairs if (int(a), int(b)) not in done]
        skipped = len(pairs) - len(todo)
        logger.info("%d images, %d pairs selected, %d already verified (resumed), %d to match",
                    len(usable), len(pairs), skipped, len(todo))  # fmt: skip
        camera_of = {i: r.camera_id for i, r in images.items()}
        times = _process(db, todo, camera_of, db.read_cameras(), options, executor)
        _, _, inliers = db.verified_pairs(options.min_num_inliers)
    ledger.finish("match", "")
    return MatchResult(
        num_images=len(usable), num_pairs_considered=len(pairs), num_pairs_skipped_existing=skipped,
        num_pairs_processed=len(todo), num_verified=len(inliers),
        median_inliers=float(np.median(inliers)) if len(inliers) else 0.0,
        time_match_s=times[0], time_verify_s=times[1], time_total_s=time.perf_counter() - start,
    )  # fmt: skip


def _process(db: Database, todo: list[tuple[int, int]], camera_of, cameras, options: MatchOptions,
             executor=None):
    """Run the pairs (in a pool when it pays), write results in batches; (t_match, t_verify)."""
    workers = options.num_workers or len(os.sched_getaffinity(0))
    remote = executor is not None and hasattr(executor, "imap")
    t_match = t_verify = 0.0
    batch: list = []

    def flush() -> None:
        with db.transaction():
            db.write_matches_many((a, b, m) for a, b, m, _ in batch)
            db.write_two_view_geometries_many((a, b, to_colmap_pixels(g)) for a, b, _, g in batch)
        batch.clear()

    pool = None
    failed_write = False
    try:
        if remote and todo:
            size = max(1, min(BATCH_REMOTE, len(todo) // (4 * executor.num_workers())))
            batches = executor.imap(_work_batch, _remote_batches(db, todo, camera_of, cameras, options, size))
            results = (r for batch_results in batches for r in batch_results)
        elif workers > 1 and len(todo) >= 2 * workers:
            # an executor, not multiprocessing.Pool: a worker that dies or fails to start raises
            # BrokenProcessPool here instead of being respawned forever
            pool = ProcessPoolExecutor(
                workers, pool_context(), _init_worker,
                (str(db.path), camera_of, cameras, options),
            )  # fmt: skip
            chunk = max(1, min(16, len(todo) // (8 * workers)))
            results = pool.map(_work, todo, chunksize=chunk)
        else:
            results = map(_PairProcessor(_db_loader(db), camera_of, cameras, options), todo)
        for id1, id2, matches, geometry, tm, tv in tqdm(
            results, total=len(todo), desc="match", unit="pair"
        ):
            batch.append((id1, id2, matches, geometry))
            t_match, t_verify = t_match + tm, t_verify + tv
            if len(batch) >= BATCH_PAIRS:
                failed_write = True
                flush()
                failed_write = False
    finally:
        if batch and not failed_write:
            flush()  # keep what was finished, also when interrupted
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    return t_match, t_verify
