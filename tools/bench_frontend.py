"""Our front-end (extract + match) against pycolmap's on the same image folder, in one run.

    python tools/bench_frontend.py --images DIR [--intrinsics FILE] [--out DIR] [--gt TABLE] [--map]

graphsfm: ``run_extract`` then ``run_match`` with the defaults except exhaustive pairs, into
``OUT/graphsfm/database.db``. COLMAP: ``pycolmap.extract_features`` then
``pycolmap.match_exhaustive`` with pycolmap's defaults (SIFT on the CPU, camera mode AUTO and
model SIMPLE_RADIAL with focal 1.2 * max(W, H) or the EXIF prior, 8192 features, L1_ROOT, ratio
0.8, cross check, RANSAC 4 px, 15 inliers) except ``num_threads`` = the cores we may use (our
default uses them all too), into ``OUT/colmap/database.db``. With ``--intrinsics`` holding one
``*`` line (or one set of values for all lines) COLMAP gets a single PINHOLE camera with these
values (shifted by +0.5 px to its pixel convention); other intrinsics files are given to us only.
Both workspaces are deleted and remade at the start (default OUT: a new temporary folder).

Printed: a Markdown table (time of extract, match and both; mean keypoints per image; verified
pairs = config >= 2 and >= 15 inliers; median inliers per verified pair), the ratio of our total
time to COLMAP's, and the pairs only one side verifies. ``--gt``: both databases' median
symmetric epipolar distance against the GT (``tools/check_matches.py``; ``--k1`` as there).
``--map``: ``pycolmap.incremental_mapping`` on each database (ours first): registered images,
points, mean reprojection error, time.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
import time
import zlib  # noqa: F401 - before pycolmap (pycolmap first breaks later zlib use)
from dataclasses import dataclass, field
from pathlib import Path

import cv2  # noqa: F401 - same reason
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_page import add_page_arguments, peer_version, publish, run_context
from check_matches import check_matches

from sfm.io.database import Database
from sfm.features.options import ExtractOptions
from sfm.stages.extract import run_extract
from sfm.evaluation.ground_truth import read_gt_table
from sfm.features.cameras import read_intrinsics
from sfm.matching.options import MatchOptions
from sfm.stages.match import run_match

MIN_INLIERS = 15


@dataclass
class FrontendRun:
    """Times and database figures of one front-end."""

    name: str
    workspace: Path
    t_extract: float = 0.0
    t_match: float = 0.0
    notes: list[str] = field(default_factory=list)
    figures: dict[str, float] = field(default_factory=dict)
    verified: dict[tuple[str, str], int] = field(default_factory=dict)

    @property
    def t_total(self) -> float:
        return self.t_extract + self.t_match


def fresh(folder: Path) -> Path:
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    return folder


def run_ours(images: Path, workspace: Path, intrinsics: Path | None) -> FrontendRun:
    run = FrontendRun("graphsfm", fresh(workspace))
    t0 = time.perf_counter()
    run_extract(images, workspace, ExtractOptions(intrinsics=intrinsics))
    run.t_extract = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = run_match(workspace, MatchOptions(pairs="exhaustive"))
    run.t_match = time.perf_counter() - t0
    run.notes.append(
        f"graphsfm match, summed over workers: descriptor matching {result.time_match_s:.1f} s, "
        f"verification {result.time_verify_s:.1f} s"
    )
    return run


def colmap_camera(intrinsics: Path | None) -> tuple[str, str] | None:
    """(model, params) of one PINHOLE camera for COLMAP when the file has one set of values."""
    if intrinsics is None:
        return None
    table = read_intrinsics(intrinsics)
    values = {k.values for k in table.by_name.values()} | (
        {table.default.values} if table.default else set()
    )
    if len(values) != 1:
        return None
    _, _, fx, fy, cx, cy = values.pop()
    return "PINHOLE", f"{fx!r},{fy!r},{cx + 0.5!r},{cy + 0.5!r}"


def run_colmap(images: Path, workspace: Path, intrinsics: Path | None, threads: int) -> FrontendRun:
    import pycolmap

    pycolmap.logging.minloglevel = 2  # warnings and errors only
    run = FrontendRun("COLMAP (pycolmap)", fresh(workspace))
    db = str(workspace / "database.db")
    reader = pycolmap.ImageReaderOptions()
    mode = pycolmap.CameraMode.AUTO
    camera = colmap_camera(intrinsics)
    if camera is not None:
        reader.camera_model, reader.camera_params = camera
        mode = pycolmap.CameraMode.SINGLE
        run.notes.append(f"COLMAP camera: single {camera[0]} {camera[1]}")
    elif intrinsics is not None:
        run.notes.append("COLMAP camera: defaults (the intrinsics file has several cameras)")
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    t0 = time.perf_counter()
    pycolmap.extract_features(
        db,
        str(images),
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    run.t_extract = time.perf_counter() - t0
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    run.t_match = time.perf_counter() - t0
    return run


def measure(run: FrontendRun, gt_table: Path | None, k1: float = 0.0) -> None:
    """Database figures of ``run`` (and GT epipolar figures when ``gt_table`` is given)."""
    with Database(run.workspace / "database.db", readonly=True) as db:
        names = {i: r.name for i, r in db.read_images().items()}
        kp = db.read_all_keypoints()
        id1, id2, inliers = db.verified_pairs(MIN_INLIERS)
        run.verified = {
            tuple(sorted((names[a], names[b]))): int(n) for a, b, n in zip(id1, id2, inliers)
        }
        run.figures.update(
            images=len(names),
            cameras=db.num_cameras(),
            keypoints=float(np.mean([len(k) for k in kp.values()])) if kp else 0.0,
            pairs_matched=len(db.pairs_with_geometry() | db.pairs_with_matches()),
            verified=len(inliers),
            median_inliers=float(np.median(inliers)) if len(inliers) else 0.0,
        )
        if gt_table is not None:
            check = check_matches(db, read_gt_table(gt_table), MIN_INLIERS, k1=k1)
            run.figures.update(
                epi_median=check.median_px,
                epi_p90=check.p90_of_pair_medians_px,
                epi_checked=check.num_checked,
            )


def map_with_colmap(run: FrontendRun, images: Path, threads: int) -> None:
    """``pycolmap.incremental_mapping`` on the run's database; registered images, points, time."""
    import pycolmap

    out = fresh(run.workspace / "colmap_sparse")
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(
        str(run.workspace / "database.db"), str(images), str(out), options
    )
    run.figures["t_map"] = time.perf_counter() - t0
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    run.figures["models"] = len(models)
    run.figures["registered"] = best.num_reg_images() if best is not None else 0
    run.figures["points"] = best.num_points3D() if best is not None else 0
    run.figures["reproj"] = (
        best.compute_mean_reprojection_error() if best is not None else float("nan")
    )


def table(runs: list[FrontendRun]) -> str:
    ours, peer = runs
    rows = [
        ("images / cameras", lambda r: f"{r.figures['images']:.0f} / {r.figures['cameras']:.0f}"),
        ("time extract (s)", lambda r: f"{r.t_extract:.2f}"),
        ("time match (s)", lambda r: f"{r.t_match:.2f}"),
        ("time total (s)", lambda r: f"{r.t_total:.2f}"),
        ("keypoints per image (mean)", lambda r: f"{r.figures['keypoints']:.0f}"),
        ("pairs matched", lambda r: f"{r.figures['pairs_matched']:.0f}"),
        (
            f"verified pairs (config >= 2, >= {MIN_INLIERS} inliers)",
            lambda r: f"{r.figures['verified']:.0f}",
        ),
        ("median inliers per verified pair", lambda r: f"{r.figures['median_inliers']:.0f}"),
    ]
    if "epi_median" in ours.figures:
        rows += [
            (
                "GT epipolar distance, median of inliers (px)",
                lambda r: f"{r.figures['epi_median']:.3f}",
            ),
            (
                "GT epipolar distance, p90 of pair medians (px)",
                lambda r: f"{r.figures['epi_p90']:.3f}",
            ),
        ]
    if "registered" in ours.figures:
        rows += [
            (
                "incremental_mapping: registered (largest model)",
                lambda r: f"{r.figures['registered']:.0f}",
            ),
            (
                "incremental_mapping: models / points",
                lambda r: f"{r.figures['models']:.0f} / {r.figures['points']:.0f}",
            ),
            (
                "incremental_mapping: mean reproj. error (px)",
                lambda r: f"{r.figures['reproj']:.3f}",
            ),
            ("incremental_mapping: time (s)", lambda r: f"{r.figures['t_map']:.2f}"),
        ]
    lines = [f"| | {ours.name} | {peer.name} |", "|---|---|---|"]
    lines += [f"| {label} | {f(ours)} | {f(peer)} |" for label, f in rows]
    return "\n".join(lines)


def pair_differences(ours: FrontendRun, peer: FrontendRun, limit: int = 20) -> list[str]:
    out = []
    for label, a, b in (
        ("verified by COLMAP only", peer, ours),
        ("verified by graphsfm only", ours, peer),
    ):
        only = sorted(set(a.verified) - set(b.verified), key=lambda p: -a.verified[p])
        shown = ", ".join(f"{p[0]}-{p[1]} ({a.verified[p]})" for p in only[:limit])
        more = f", ... {len(only) - limit} more" if len(only) > limit else ""
        out.append(f"{label} ({len(only)}, inliers in brackets): {shown or '-'}{more}")
    common = sorted(set(ours.verified) & set(peer.verified))
    if common:
        ratio = np.median([ours.verified[p] / peer.verified[p] for p in common])
        out.append(
            f"pairs verified by both: {len(common)}; "
            f"median inlier ratio graphsfm/COLMAP {ratio:.2f}"
        )
    return out


def prepare(images: Path, out: Path | None, prefix: str) -> tuple[Path, int] | None:
    """Logging, the image folder check (None: missing, reported), the output folder (a new
    temporary one by default) and the number of threads each side gets."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname).1s %(name)s: %(message)s")
    if not images.is_dir():
        print(f"error: image folder not found: {images}", file=sys.stderr)
        return None
    return out or Path(tempfile.mkdtemp(prefix=prefix)), len(os.sched_getaffinity(0))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--images", type=Path, required=True, help="image folder")
    parser.add_argument(
        "--intrinsics", type=Path, default=None, help="intrinsics file (graphsfm's --intrinsics)"
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="output folder (default: a new temporary folder)"
    )
    parser.add_argument(
        "--gt", type=Path, default=None, help="GT table: add epipolar distances of both databases"
    )
    parser.add_argument(
        "--k1", type=float, default=0.0, help="GT radial distortion (see tools/check_matches.py)"
    )
    parser.add_argument(
        "--map", action="store_true", help="run pycolmap.incremental_mapping on both databases"
    )
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    setup = prepare(args.images, args.out, "graphsfm_bench_frontend_")
    if setup is None:
        return 2
    out, threads = setup

    ours = run_ours(args.images, out / "graphsfm", args.intrinsics)
    peer = run_colmap(args.images, out / "colmap", args.intrinsics, threads)
    runs = [ours, peer]
    for run in runs:
        measure(run, args.gt, args.k1)
    if args.map:
        for run in runs:
            map_with_colmap(run, args.images, threads)

    context = run_context()
    ratio = (
        f"ratio of total time graphsfm / COLMAP: {ours.t_total / peer.t_total:.2f} "
        f"(extract {ours.t_extract / peer.t_extract:.2f}, match {ours.t_match / peer.t_match:.2f})"
    )
    stamp = f"Measured {context['date']} on {context['machine']}; graphsfm at {context['code']}, {peer_version()}."
    text = f"{table(runs)}\n\n{ratio}\n\n{stamp}"
    print(f"## Front-end: {args.images} ({threads} threads each; workspaces in {out})\n\n{text}")
    for line in pair_differences(ours, peer) + ours.notes + peer.notes:
        print(line)
    name = args.images.resolve().parent.name
    publish(args, f"frontend-{name}", f"Extract and match: {name}", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
