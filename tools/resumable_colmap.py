"""pycolmap's incremental mapper as a run that can stop and resume, for runs longer than a sitting.

COLMAP's incremental mapper on the 2,000-image synthetic aerial scene runs for hours here, longer
than one working session, and a stopped run used to be lost.  :func:`run_incremental` runs it in
segments: COLMAP writes a snapshot of the model every ``SNAPSHOT_EVERY`` registered images
(its own ``snapshot_path`` option), a segment that reaches its time budget stops the mapper
(COLMAP's ``max_runtime_seconds``) and keeps its model as one more snapshot, and the next call
resumes from the newest complete snapshot (``input_path``: COLMAP continues that model; its
global-BA schedule restarts from the snapshot's image count).  Work after the newest snapshot of
a segment that was killed is lost, not counted.

Snapshots are taken while the model grows, so none holds COLMAP's final iterative global
refinement (re-triangulation and global BAs until little changes), and COLMAP skips that
refinement when a continued model registers no new image.  A resumed segment that registers
nothing therefore runs it itself (:func:`final_refinement`, the same calls COLMAP makes), within
the segment's credited time; otherwise a run killed in its final refinement would resume to an
unrefined model in no time.

The time credited to COLMAP is the time of the segments up to the snapshot each one resumed
from: ``segments.json`` records each segment's wall-clock start and the seconds credited before
it, and a snapshot's time is read off its files' modification time.  Each resume also re-reads
the database (a few seconds at 2,000 images), which is counted: resuming can only make COLMAP
look slower, and the result says how many segments it took.  ``progress.txt`` gets one line
"credited-seconds registrations" per registered image, across segments.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

SNAPSHOT_EVERY = 50  # registered images between snapshots (about a second each at 2,000 images)
KEEP_SNAPSHOTS = 2  # the newest complete ones; older ones are deleted as new ones appear
MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin")


def snapshot_time(folder: Path) -> float:
    """Wall-clock time a snapshot was finished: the newest modification time of its files."""
    return max(p.stat().st_mtime for p in folder.iterdir())


def snapshots(root: Path) -> list[Path]:
    """Snapshot folders holding every model file, oldest first."""
    if not root.is_dir():
        return []
    found = [d for d in root.iterdir() if d.is_dir() and all((d / f).is_file() for f in MODEL_FILES)]
    return sorted(found, key=snapshot_time)


def credited_seconds(segments: list[dict], when: float) -> float:
    """Mapper seconds credited at wall-clock time ``when``: the time credited before the
    segment running then, plus how long that segment had run."""
    started = [s for s in segments if s["wall_start"] <= when]
    if not started:
        raise ValueError(f"no segment had started at {when}")
    seg = max(started, key=lambda s: s["wall_start"])
    return seg["offset"] + (when - seg["wall_start"])


def _resume_point(work: Path, segments: list[dict]):
    """(snapshot, its model, credited seconds) of the newest snapshot that loads, or None."""
    import pycolmap

    for snap in reversed(snapshots(work / "snapshots")):
        try:
            model = pycolmap.Reconstruction(str(snap))
        except Exception:  # noqa: BLE001 - half written when its segment was killed
            continue
        try:
            return snap, model, credited_seconds(segments, snapshot_time(snap))
        except ValueError:
            continue
    return None


def final_refinement(database: Path, model, options) -> None:
    """COLMAP's final step of a model, in place: its iterative global refinement with the
    pipeline's options, then the removal of frames with implausible intrinsics."""
    import pycolmap

    cache_options = pycolmap.DatabaseCacheOptions()
    cache_options.min_num_matches = options.min_num_matches
    cache_options.ignore_watermarks = options.ignore_watermarks
    db = pycolmap.Database.open(str(database))
    try:
        cache = pycolmap.DatabaseCache.create(db, cache_options)
    finally:
        db.close()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(model)
    mapper.iterative_global_refinement(options.ba_global_max_refinements, options.ba_global_max_refinement_change,
                                       options.get_mapper(), options.get_global_bundle_adjustment(),
                                       options.get_triangulation())
    mapper.filter_frames(options.get_mapper())
    mapper.end_reconstruction(False)


def _prune(root: Path) -> None:
    for old in snapshots(root)[:-KEEP_SNAPSHOTS]:
        shutil.rmtree(old, ignore_errors=True)


def run_incremental(db: Path, work: Path, budget_s: float | None = None) -> tuple[Path | None, float, bool, int]:
    """Run (or resume) COLMAP's incremental mapper on a copy of ``db`` in ``work``.

    Returns (largest model folder or None, credited seconds, finished, segments so far).
    ``finished`` is False when the segment stopped at ``budget_s`` seconds (call again to
    resume); the model folder is then the snapshot it stopped at."""
    import pycolmap

    pycolmap.logging.minloglevel = 2
    work.mkdir(parents=True, exist_ok=True)
    ledger = work / "segments.json"
    segments = json.loads(ledger.read_text()) if ledger.exists() else []
    resume = _resume_point(work, segments) if segments else None
    if not (work / "database.db").exists() or resume is None:
        shutil.rmtree(work / "snapshots", ignore_errors=True)
        shutil.copy(db, work / "database.db")
        segments = []
        (work / "progress.txt").write_text("")
    (work / "images").mkdir(exist_ok=True)
    (work / "snapshots").mkdir(exist_ok=True)  # COLMAP makes the snapshot folders, not their parent
    options = pycolmap.IncrementalPipelineOptions()
    options.snapshot_path = str(work / "snapshots")
    options.snapshot_frames_freq = SNAPSHOT_EVERY
    offset, count, input_path = 0.0, [2], ""  # the initial pair registers two
    if resume is not None:
        snap, model, offset = resume
        count[0], input_path = model.num_reg_images(), str(snap)
        lines = (work / "progress.txt").read_text().splitlines()
        kept = [ln for ln in lines if float(ln.split()[0]) <= offset]
        (work / "progress.txt").write_text("".join(ln + "\n" for ln in kept))
    if budget_s:
        options.max_runtime_seconds = int(budget_s)  # COLMAP stops there and keeps the model
    sparse = work / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir()
    with (work / "progress.txt").open("a", buffering=1) as log:
        t0 = time.perf_counter()

        def callback() -> None:
            count[0] += 1
            log.write(f"{offset + time.perf_counter() - t0:.1f} {count[0]}\n")
            _prune(work / "snapshots")

        segments.append({"wall_start": time.time(), "offset": offset, "from": input_path})
        ledger.write_text(json.dumps(segments, indent=1))
        start_count = count[0]
        models = pycolmap.incremental_mapping(str(work / "database.db"), str(work / "images"), str(sparse),
                                              options, input_path=input_path, next_image_callback=callback)
        best = max(models, key=lambda k: models[k].num_reg_images()) if models else None
        stopped = bool(budget_s) and time.perf_counter() - t0 >= budget_s
        refined = resume is not None and best is not None and count[0] == start_count and not stopped
        if refined:
            final_refinement(work / "database.db", models[best], options)  # COLMAP skips it here
        segment_s = time.perf_counter() - t0
    if stopped:  # stopped at the budget: its model is the next resume point
        if best is None:
            return None, offset + segment_s, False, len(segments)
        stop = work / "snapshots" / f"{int(time.time() * 1000):013d}"
        stop.mkdir()
        models[best].write(str(stop))
        return stop, credited_seconds(segments, snapshot_time(stop)), False, len(segments)
    if best is None:
        return None, offset + segment_s, True, len(segments)
    if refined or not (sparse / str(best) / "images.bin").exists():  # COLMAP may return a resumed model
        # unwritten, and any copy it wrote of a refined one predates the refinement
        (sparse / str(best)).mkdir(parents=True, exist_ok=True)
        models[best].write(str(sparse / str(best)))
    return sparse / str(best), offset + segment_s, True, len(segments)
