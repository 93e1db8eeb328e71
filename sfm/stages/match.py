"""The ``match`` stage (paper section 3.1.1: the image graph's edges): pairs, descriptor matching,
verification.

:func:`run_match` reads images, cameras, keypoints and descriptors from ``WORK/database.db``,
selects pairs (``sfm.matching.pairs``), matches and verifies them in batches on an executor
(``sfm.matching.pair_matcher``, ``sfm.execution``) and writes raw matches and two-view
geometries back, one transaction per batch of results, so a killed run loses at most one batch.
Pairs that already have a two-view geometry row are skipped: rerunning resumes.  Local workers
read the features from the database themselves; remote ones get them with their batch.  The
pairs run in an order that keeps each worker's images in its feature cache
(``sfm.matching.pair_matcher.cache_order``); any order and any number of workers give the same
results (seeds per pair).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sfm.core import progress
from sfm.core.geodesy import enu_from_wgs84
from sfm.errors import InputError
from sfm.execution.local import LocalExecutor
from sfm.io.database import Database
from sfm.io.database_schema import COORDINATES_WGS84
from sfm.io.ledger import options_record, resume_or_restart
from sfm.io.report import update_report
from sfm.matching.options import MatchOptions
from sfm.matching.pair_matcher import PairBatch, cache_order, close_matchers, images_in_cache, match_batch
from sfm.matching.pairs import extension_pairs, select_pairs
from sfm.matching.verification import to_colmap_pixels
from sfm.io.database_schema import TwoViewConfig
from sfm.io.workspace import image_dir_of
from sfm.viz.frontend import log_image_graph, log_match_pair, pair_sample
from sfm.viz.recorder import Recorder
from sfm.viz.tour import match_text

logger = logging.getLogger(__name__)

BATCH_PAIRS = 100  # results written per transaction
LOCAL_BATCH = 16  # pairs per task when workers read the database themselves
REMOTE_BATCH = 64  # pairs per task when their features travel with them


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


def _batches(db: Database, todo: list[tuple[int, int]], camera_of, cameras, names, options: MatchOptions,
             size: int, remote: bool) -> Iterator[PairBatch]:
    """Consecutive pairs (``cache_order`` gives them few images) with the cameras they need;
    for remote workers, with their images' features."""
    for start in range(0, len(todo), size):
        pairs = todo[start:start + size]
        ids = sorted({i for p in pairs for i in p})
        cams = {camera_of[i] for i in ids}
        batch = PairBatch(pairs, {i: camera_of[i] for i in ids}, {c: cameras[c] for c in cams}, options,
                          {i: names[i] for i in ids})
        if remote:
            batch.features = {i: (db.read_keypoints(i), db.read_descriptors(i)) for i in ids}
        else:
            batch.database = str(db.path)
        yield batch


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


def _gps_positions(db: Database, image_ids: list[int]):
    """(N, 3) east-north-up metres of the images' WGS84 position priors (origin: their mean),
    NaN rows for images without one."""
    priors = db.read_pose_priors()
    lla = np.full((len(image_ids), 3), np.nan)
    for row, i in enumerate(image_ids):
        p = priors.get(i)
        if p is not None and p.coordinate_system == COORDINATES_WGS84:
            lla[row] = p.position
    known = np.all(np.isfinite(lla), axis=1)
    if not known.any():
        logger.warning("pairs spatial: no image has a GPS position; retrieval pairs only")
        return lla
    logger.info("pairs spatial: %d of %d images have a GPS position", known.sum(), len(image_ids))
    lla[known] = enu_from_wgs84(lla[known], lla[known].mean(axis=0))
    return lla


def run_match(workspace: Path, options: MatchOptions = MatchOptions(), executor=None,
              recorder: Recorder | None = None) -> MatchResult:
    """Match and verify the selected pairs of ``workspace/database.db`` (see module docstring).

    ``executor``: where the pairs are matched (``sfm.execution``; default: a local pool of one
    process per core); only this process writes the database.  ``recorder``: the image graph,
    the inlier matches of a sample of pairs and the stage's text go to it."""
    start = time.perf_counter()
    progress.stage("match")
    executor = executor or LocalExecutor()
    recorder = recorder or Recorder.disabled()
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
        pairs = select_pairs(usable, options.pairs, **_pair_arguments(db, usable, options))
        done = db.pairs_with_geometry()
        todo = [(int(a), int(b)) for a, b in pairs if (int(a), int(b)) not in done]
        skipped = len(pairs) - len(todo)
        logger.info("%d images, %d pairs selected, %d already verified (resumed), %d to match",
                    len(usable), len(pairs), skipped, len(todo))  # fmt: skip
        camera_of = {i: r.camera_id for i, r in images.items()}
        times = _process(db, todo, camera_of, db.read_cameras(), names, options, executor)
        _, _, inliers = db.verified_pairs(options.min_num_inliers)
        if recorder.enabled:
            log_match(recorder, db, options, len(pairs), workspace)
    ledger.finish("match", "")
    update_report(workspace, {}, {"match": time.perf_counter() - start})
    logger.info("match: %d pairs matched now, %d verified in all (median %d inliers), %.1f s", len(todo),
                len(inliers), int(np.median(inliers)) if len(inliers) else 0, time.perf_counter() - start)
    return MatchResult(
        num_images=len(usable), num_pairs_considered=len(pairs), num_pairs_skipped_existing=skipped,
        num_pairs_processed=len(todo), num_verified=len(inliers),
        median_inliers=float(np.median(inliers)) if len(inliers) else 0.0,
        time_match_s=times[0], time_verify_s=times[1], time_total_s=time.perf_counter() - start,
    )  # fmt: skip


def _pair_arguments(db: Database, image_ids: list[int], options: MatchOptions) -> dict:
    """The pair selection's keyword arguments from the options (GPS positions read only for
    ``--pairs spatial``)."""
    positions = _gps_positions(db, image_ids) if options.pairs == "spatial" else None
    return {"top_k": options.top_k, "sequential": options.sequential,
            "exhaustive_threshold": options.exhaustive_threshold, "seed": options.seed,
            "load_descriptors": db.read_descriptors, "positions": positions,
            "spatial_neighbors": options.spatial_neighbors, "spatial_max_distance": options.spatial_max_distance}


def match_extension(workspace: Path, new_names: list[str], options: MatchOptions = MatchOptions(),
                    executor=None) -> MatchResult:
    """Match and verify the pairs of images added to a finished model (``graphsfm extend``):
    the pairs with at least one of ``new_names`` (``sfm.matching.pairs.extension_pairs``), so
    the work grows with the new images.  Pairs already verified are skipped (resuming), and the
    stored matches of the old images are never dropped, whatever the options."""
    start = time.perf_counter()
    executor = executor or LocalExecutor()
    db_path = Path(workspace) / "database.db"
    with Database(db_path) as db:
        images = db.read_images()
        names = {i: r.name for i, r in images.items()}
        wanted = set(new_names)
        ordered = sorted(images, key=lambda i: names[i])
        usable = _usable_images(db, ordered, names)
        new = [i for i in usable if names[i] in wanted]
        old = [i for i in usable if names[i] not in wanted]
        pairs = extension_pairs(new, old, options.pairs, **_pair_arguments(db, new + old, options))
        done = db.pairs_with_geometry()
        todo = [(int(a), int(b)) for a, b in pairs if (int(a), int(b)) not in done]
        logger.info("extension: %d new and %d old images, %d pairs selected, %d already verified (resumed), %d to match",
                    len(new), len(old), len(pairs), len(pairs) - len(todo), len(todo))  # fmt: skip
        camera_of = {i: r.camera_id for i, r in images.items()}
        times = _process(db, todo, camera_of, db.read_cameras(), names, options, executor)
        _, _, inliers = db.verified_pairs(options.min_num_inliers)
    return MatchResult(
        num_images=len(usable), num_pairs_considered=len(pairs), num_pairs_skipped_existing=len(pairs) - len(todo),
        num_pairs_processed=len(todo), num_verified=len(inliers),
        median_inliers=float(np.median(inliers)) if len(inliers) else 0.0,
        time_match_s=times[0], time_verify_s=times[1], time_total_s=time.perf_counter() - start,
    )  # fmt: skip


def _process(db: Database, todo: list[tuple[int, int]], camera_of, cameras, names, options: MatchOptions, executor):
    """Run the pairs in batches on ``executor``, in ``cache_order``, and write the results;
    (t_match, t_verify)."""
    if todo:
        counts = db.keypoint_counts()
        todo = cache_order(todo, images_in_cache(float(np.mean([counts[i] for p in todo for i in p]))))
    workers = executor.num_workers() if executor.remote else executor.workers
    size = max(1, min(REMOTE_BATCH if executor.remote else LOCAL_BATCH, len(todo) // ((4 if executor.remote else 8) * workers)))
    t_match = t_verify = 0.0
    batch: list = []

    def flush() -> None:
        with db.transaction():
            db.write_matches_many((a, b, m) for a, b, m, _ in batch)
            db.write_two_view_geometries_many((a, b, to_colmap_pixels(g)) for a, b, _, g in batch)
        batch.clear()

    failed_write = False
    tasks = _batches(db, todo, camera_of, cameras, names, options, size, executor.remote)
    try:
        results = executor.map(match_batch, tasks, num_items=-(-len(todo) // size))
        pairs = (r for task in results for r in task.value)
        for id1, id2, matches, geometry, tm, tv in progress.bar(pairs, total=len(todo), desc="match", unit="pair"):
            batch.append((id1, id2, matches, geometry))
            t_match, t_verify = t_match + tm, t_verify + tv
            if len(batch) >= BATCH_PAIRS:
                failed_write = True
                flush()
                failed_write = False
    finally:
        if batch and not failed_write:
            flush()  # keep what was finished, also when interrupted
        close_matchers()  # a matcher that ran in this process holds a read connection
    return t_match, t_verify


def log_match(recorder: Recorder, db: Database, options: MatchOptions, num_pairs: int, workspace: Path) -> None:
    """The image graph of paper section 3.1.1 (``graph/images``), the inlier matches of
    ``record_pairs`` pairs spread from the most to the fewest inliers (``matches/...``), and the
    stage's text of the tour."""
    recorder.stage("match")
    recorder.image_dir = recorder.image_dir or image_dir_of(workspace)
    images = db.read_images()
    i, j, w = db.verified_pairs(options.min_num_inliers)
    ids = sorted(images)  # the cluster stage's node order: the same layout
    node = {image_id: k for k, image_id in enumerate(ids)}
    names = [images[k].name for k in ids]
    log_image_graph(recorder, names, np.array([node[int(a)] for a in i], dtype=np.int64),
                    np.array([node[int(b)] for b in j], dtype=np.int64), w)
    drawn = 0
    for k in pair_sample(w, recorder.options.record_pairs).tolist():
        a, b = int(i[k]), int(j[k])
        thumb_a, thumb_b = recorder.thumbnail(images[a].name), recorder.thumbnail(images[b].name)
        geometry = db.read_two_view_geometry(a, b)
        if thumb_a is None or thumb_b is None or geometry is None:
            continue
        m = np.asarray(geometry.inlier_matches, dtype=np.int64)
        kp_a, kp_b = db.read_keypoints(a), db.read_keypoints(b)
        log_match_pair(recorder, images[a].name, images[b].name, thumb_a, thumb_b, kp_a[m[:, 0], :2],
                       kp_b[m[:, 1], :2], TwoViewConfig(int(geometry.config)).name.lower())
        drawn += 1
    recorder.tour("match", match_text(len(images), num_pairs, len(w), w, options.min_num_inliers, options, drawn))
