"""Pose accuracy on the real photo sets with ground truth: graphsfm against COLMAP's mappers, one run.

    python tools/bench_accuracy.py [--data ../shared/data] [--sets lund_door temple_ring ...]
                                   [--out DIR] [--recording] [--no-colmap-frontend] [--no-per-image]
                                   [--every N [N ...]] [--downscale F [F ...]] [--crop F [F ...]]

For every set (default: every folder of ``--data`` with ``images/`` and a pose table
``gt/cameras_gt_opencv.txt``), on the same images and evaluated the same way
(:func:`sfm.evaluation.metrics.evaluate`: the largest model, Sim3-aligned rotation error, the
alignment-free relative-pose AUC):

- ``graphsfm``: ``sfm.reconstruct(images, ...)`` with the defaults (the Rerun recording off
  unless ``--recording``), from nothing; its time is the whole run.
- ``graphsfm, N clusters``: ``reconstruct`` on a copy of that run's database with
  ``--max-cluster-size`` the largest size that gives at least 3 clusters (cluster, map, merge);
  its time is those stages.
- ``colmap incremental`` and ``colmap global`` on graphsfm's database (the same matches):
  ``pycolmap.incremental_mapping`` and ``pycolmap.global_mapping`` with their defaults; their
  time is the mapper's.
- ``graphsfm, one camera per image`` and COLMAP's two mappers on that run's database, in a table
  of their own (``--no-per-image`` skips it): the conditions of internet photos, where nothing
  says two images share a lens, so every image's focal length and distortion are estimated on
  their own (from the 1.2 x longer side guess when the image has no EXIF focal length).
- ``colmap extract+match, incremental`` and ``..., global``: pycolmap's own front end
  (``extract_features`` + ``match_exhaustive``, its defaults on the CPU, as
  ``tools/bench_frontend.py``) and both mappers on that database; the time is front end + mapper.

Per set the table has registered images (of the GT's), the median rotation error, AUC@1/5/10,
time, and a verdict: graphsfm's AUC@1 and AUC@5 against COLMAP's best mapper (the highest value
over COLMAP's rows, per threshold), and the forced-cluster run against the same (within 0.01).
Images graphsfm did not register and models it did not merge are listed with the step that
failed (``unregistered`` and ``warnings`` of ``report.json``).

``--every 2 3`` also runs the main table's methods on sparser versions of each set: every 2nd
and every 3rd image along the camera path (:func:`path_order`), from each possible first image
(2 + 3 tables), with the GT poses of those images (``<out>/sparser/<set>_every<N>_from<K>``);
only for the sets whose every N-th image still makes ``--every-min-images`` images (10).
Fewer, wider-spaced views of the same scene: the condition of a narrow-field object ring
photographed in fewer steps, which the shared sets do not hold.

``--downscale 2`` also runs the main table's methods on each set at half resolution (each
image box-filtered by 2 in both directions, its EXIF kept; ``<out>/transformed/<set>_1of2``), and
``--every`` on those too: fewer and coarser features on the same views, the condition of weakly
textured or low-resolution photos.

``--crop 2`` also runs them on each set's images cropped to their central half in both
directions, without EXIF (``<out>/transformed/<set>_crop1of2``), and ``--every`` on those: the
same focal length in pixels over a narrower field of view, with the focal length's 1.2 x
longer side guess twice as far from it as on the whole images: the condition of a narrow-field
object ring photographed with a long lens and no EXIF.

A set whose ``gt/`` also holds projection matrices (``*P_matrices.txt``, read by
:func:`sfm.evaluation.ground_truth.read_projection_matrices`) gets a second table: the same
models evaluated against them, the same verdict.  Where the pose table was itself made by one of
the programs compared (lund_door's is a COLMAP model), that is a check by a ground truth that
program did not make.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import sys
import tempfile
import time
import zlib  # noqa: F401 - before pycolmap (pycolmap first breaks later zlib use)
from pathlib import Path

import cv2  # noqa: F401 - same reason
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_frontend import fresh, run_colmap as run_colmap_frontend  # noqa: E402
from bench_mapping import run_colmap as run_colmap_mapper  # noqa: E402
from benchmarks_page import add_page_arguments, markdown_table, peer_version, publish, run_context  # noqa: E402

from sfm.api import reconstruct  # noqa: E402
from sfm.clustering.options import ClusterOptions  # noqa: E402
from sfm.evaluation.ground_truth import read_gt_table, read_projection_matrices  # noqa: E402
from sfm.evaluation.metrics import evaluate  # noqa: E402
from sfm.io.colmap_model import read_model  # noqa: E402
from sfm.stages.cluster import run_cluster  # noqa: E402

GT_TABLE = Path("gt") / "cameras_gt_opencv.txt"
MIN_CLUSTERS = 3
TOLERANCE_CLUSTERS = 0.01  # the forced-cluster run may trail COLMAP's best by this much


def gt_sets(data: Path) -> list[str]:
    """Folders of ``data`` with an ``images/`` folder and a GT pose table."""
    return sorted(d.name for d in data.iterdir() if (d / "images").is_dir() and (d / GT_TABLE).exists())


def add_set_arguments(parser) -> None:
    """``--data``, ``--sets`` and ``--out`` on a script's parser (this script's, and the scripts
    that measure something else on the same sets)."""
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data",
                        help="folder of the photo sets (default: %(default)s)")
    parser.add_argument("--sets", nargs="+", help="set names (default: every set of --data with pose GT)")
    parser.add_argument("--out", type=Path, help="output folder (default: a new temporary folder)")


def path_order(centers: np.ndarray) -> np.ndarray:
    """Indices of camera centres (N, 3) in the order of the path that took them: a chain that
    starts at the centre farthest from their mean and goes on to the nearest centre not yet
    visited (an orbit or a strip is walked end to end; the file order need not follow it)."""
    centers = np.asarray(centers, float)
    left = np.ones(len(centers), dtype=bool)
    order = [int(np.argmax(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))] if len(centers) else []
    if order:
        left[order[0]] = False
    while left.any():
        dist = np.linalg.norm(centers - centers[order[-1]], axis=1)
        dist[~left] = np.inf
        order.append(int(np.argmin(dist)))
        left[order[-1]] = False
    return np.array(order, dtype=np.int64)


def sparser_set(data: Path, name: str, every: int, start: int, root: Path) -> str:
    """A set of every ``every``-th image of ``data/name`` along its camera path
    (:func:`path_order` of the GT centres), from the one at position ``start`` (0-based),
    written as ``root/<name>_every<every>_from<start + 1>`` (links to the images, the GT
    table's lines of those images); its name under ``root``."""
    gt = read_gt_table(data / name / GT_TABLE)
    names = sorted(gt)
    kept = {names[i] for i in path_order(np.stack([gt[n].center for n in names]))[start::every]}
    sub = f"{name}_every{every}_from{start + 1}"
    fresh(root / sub)
    (root / sub / "images").mkdir(parents=True)
    (root / sub / GT_TABLE.parent).mkdir(parents=True)
    for image in sorted(kept):
        (root / sub / "images" / image).parent.mkdir(parents=True, exist_ok=True)
        (root / sub / "images" / image).symlink_to((data / name / "images" / image).resolve())
    lines = (data / name / GT_TABLE).read_text(encoding="utf-8").splitlines(keepends=True)
    (root / sub / GT_TABLE).write_text("".join(
        line for line in lines if not line.strip() or line.startswith("#") or line.split()[0] in kept), encoding="utf-8")
    return sub


def transformed_set(data: Path, name: str, sub: str, root: Path, transform, keep_exif: bool) -> str:
    """``data/name`` with every image replaced by ``transform(image)`` (a Pillow image; the same
    file format, the EXIF kept only with ``keep_exif``) and the same GT table (the poses do not
    depend on it), written as ``root/sub``; ``sub``."""
    from PIL import Image

    fresh(root / sub)
    (root / sub / GT_TABLE.parent).mkdir(parents=True)
    shutil.copy(data / name / GT_TABLE, root / sub / GT_TABLE)
    source = data / name / "images"
    for path in sorted(p for p in source.rglob("*") if p.is_file()):
        target = root / sub / "images" / path.relative_to(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        with Image.open(path) as im:
            exif = im.info.get("exif") if keep_exif else None
            extra = {"quality": 95} if im.format == "JPEG" else {}
            transform(im).save(target, format=im.format, **({"exif": exif} if exif else {}), **extra)
    return sub


def downscaled_set(data: Path, name: str, factor: int, root: Path) -> str:
    """``data/name`` with every image reduced by ``factor`` in both directions (Pillow's box
    filter, the EXIF kept: a 35 mm equivalent focal length still holds), written as
    ``root/<name>_1of<factor>`` (:func:`transformed_set`); its name under ``root``."""
    return transformed_set(data, name, f"{name}_1of{factor}", root, lambda im: im.reduce(factor), keep_exif=True)


def cropped_set(data: Path, name: str, factor: int, root: Path) -> str:
    """``data/name`` with every image cropped to its central ``1/factor`` in both directions: the
    same focal length in pixels over a field of view ``factor`` times narrower, as a longer lens
    would see.  The EXIF is dropped (its 35 mm equivalent would describe the uncropped view), so
    the focal length starts from the 1.2 x longer side guess, ``factor`` times shorter than the
    set's own guess: a long lens without EXIF.  Written as ``root/<name>_crop1of<factor>``
    (:func:`transformed_set`); its name under ``root``."""
    def crop(im):
        w, h = im.size
        left, top = (w - w // factor) // 2, (h - h // factor) // 2
        return im.crop((left, top, left + w // factor, top + h // factor))

    return transformed_set(data, name, f"{name}_crop1of{factor}", root, crop, keep_exif=False)


def evaluate_row(method: str, model_dir: Path | None, seconds: float, gt: dict) -> dict:
    """One table row: registered (of the GT images), median rotation error, AUC@1/5/10, time."""
    row = {"method": method, "registered": f"0/{len(gt)}", "med_rot_deg": "", "auc@1": 0.0, "auc@5": 0.0,
           "auc@10": 0.0, "time_s": round(seconds, 1)}
    if model_dir is None or not (model_dir / "images.bin").exists() and not (model_dir / "images.txt").exists():
        return row
    res = evaluate(read_model(model_dir), gt)
    row.update({"registered": f"{res.num_registered}/{len(gt)}",
                "med_rot_deg": round(res.median_rotation_error_deg, 4) if math.isfinite(res.median_rotation_error_deg) else "",
                "auc@1": round(res.auc[1.0], 3), "auc@5": round(res.auc[5.0], 3), "auc@10": round(res.auc[10.0], 3)})
    return row


def graphsfm_default(images: Path, workspace: Path, recording: bool) -> tuple[Path, float, dict]:
    fresh(workspace)
    t0 = time.perf_counter()
    _, report = reconstruct(images, workspace, recording=recording)
    return workspace / "sparse" / "0", time.perf_counter() - t0, report


def stamp(rows: list[dict], context: dict) -> None:
    """Each row's date, machine and code (pycolmap's version for COLMAP's rows)."""
    for r in rows:
        r.update({"date": context["date"], "machine": context["machine"],
                  "code": peer_version() if r["method"].startswith("colmap") else context["code"]})


def graphsfm_per_image(images: Path, workspace: Path) -> tuple[Path, float, dict]:
    """``reconstruct`` from nothing with ``camera_mode="per-image"``, the recording off."""
    fresh(workspace)
    t0 = time.perf_counter()
    _, report = reconstruct(images, workspace, recording=False, camera_mode="per-image")
    return workspace / "sparse" / "0", time.perf_counter() - t0, report


def per_image_rows(images: Path, where: Path, gt: dict, context: dict) -> tuple[list[dict], list[str]]:
    """graphsfm with one camera per image and COLMAP's mappers on its database: rows and verdict."""
    model, seconds, report = graphsfm_per_image(images, where / "graphsfm_per_image")
    rows = [evaluate_row("graphsfm, one camera per image", model, seconds, gt)]
    notes = [f"graphsfm, one camera per image: {line}" for line in failures(report)]
    for kind in ("incremental", "global"):
        model, seconds = run_colmap_mapper(where / "graphsfm_per_image" / "database.db", where / f"colmap_per_image_{kind}",
                                           kind)
        rows.append(evaluate_row(f"colmap {kind} (that database)", model, seconds, gt))
    stamp(rows, context)
    return rows, verdict(rows, len(gt)) + notes


def graphsfm_clusters(database: Path, workspace: Path, num_images: int) -> tuple[Path, float, dict, int]:
    """``reconstruct`` from a copy of ``database`` with the largest ``max_cluster_size`` that gives
    at least ``MIN_CLUSTERS`` clusters (found by the ``cluster`` stage alone, from N - 1 down:
    the size bounds the expanded clusters, overlap included); (model, seconds, report,
    max_cluster_size)."""
    size = max(2, num_images - 1)
    while size > 2:
        fresh(workspace)
        shutil.copy(database, workspace / "database.db")
        if run_cluster(workspace, ClusterOptions(max_cluster_size=size)).num_clusters >= MIN_CLUSTERS:
            break
        size -= 1
    fresh(workspace)
    shutil.copy(database, workspace / "database.db")
    t0 = time.perf_counter()
    _, report = reconstruct(None, workspace, recording=False, max_cluster_size=size)
    return workspace / "sparse" / "0", time.perf_counter() - t0, report, size


def colmap_frontend(images: Path, workspace: Path, threads: int) -> tuple[Path, float]:
    """pycolmap's extraction and exhaustive matching with its defaults; (database, seconds)."""
    run = run_colmap_frontend(images, workspace, None, threads)
    return workspace / "database.db", run.t_total


def failures(report: dict) -> list[str]:
    """One line per image in no final model (with ``report.json``'s reason) and per warning of
    the run (a cluster that failed, models that did not merge)."""
    lines = [f"{u['name']}: {u['reason']}" for u in report.get("unregistered", [])]
    return lines + list(report.get("warnings", []))


def verdict(rows: list[dict], gt_count: int) -> list[str]:
    """graphsfm against COLMAP's best mapper (highest AUC over COLMAP's rows, per threshold)."""
    colmap = [r for r in rows if r["method"].startswith("colmap")]
    if not colmap:
        return []
    out = []
    for k in ("auc@1", "auc@5"):
        best = max(colmap, key=lambda r: r[k])
        out.append(f"COLMAP's best {k}: {best[k]} ({best['method']})")
    for r in rows:
        if r["method"].startswith("colmap"):
            continue
        tolerance = TOLERANCE_CLUSTERS if "clusters" in r["method"] else 0.0
        ok = r["registered"] == f"{gt_count}/{gt_count}" and all(
            r[k] >= max(c[k] for c in colmap) - tolerance - 1e-12 for k in ("auc@1", "auc@5"))
        out.append(f"{r['method']}: {'meets' if ok else 'DOES NOT MEET'} all images and AUC@1, AUC@5 >= COLMAP's best"
                   + (f" - {tolerance}" if tolerance else ""))
    return out


def bench_set(data: Path, name: str, out: Path, threads: int, recording: bool, colmap_frontend_too: bool,
              context: dict) -> tuple[list[dict], list[str]]:
    images, gt = data / name / "images", read_gt_table(data / name / GT_TABLE)
    where = out / name
    rows, notes, models = [], [], []

    def add(method: str, model: Path | None, seconds: float) -> None:
        rows.append(evaluate_row(method, model, seconds, gt))
        models.append((method, model))

    model, seconds, report = graphsfm_default(images, where / "graphsfm", recording)
    add("graphsfm", model, seconds)
    notes += [f"graphsfm: {line}" for line in failures(report)]
    database = where / "graphsfm" / "database.db"
    model, seconds, report, size = graphsfm_clusters(database, where / "graphsfm_clusters", len(gt))
    add(f"graphsfm, {report.get('num_clusters')} clusters (--max-cluster-size {size})", model, seconds)
    notes += [f"graphsfm, clusters: {line}" for line in failures(report)]
    for kind in ("incremental", "global"):
        model, seconds = run_colmap_mapper(database, where / f"colmap_{kind}", kind)
        add(f"colmap {kind} (graphsfm's database)", model, seconds)
    if colmap_frontend_too:
        colmap_db, front_s = colmap_frontend(images, where / "colmap_frontend", threads)
        for kind in ("incremental", "global"):
            model, seconds = run_colmap_mapper(colmap_db, where / f"colmap_frontend_{kind}", kind)
            add(f"colmap extract+match, {kind}", model, front_s + seconds)
    stamp(rows, context)
    return rows, verdict(rows, len(gt)) + notes, second_opinions(data / name, gt, models)


def second_opinions(folder: Path, gt: dict, models: list[tuple[str, Path | None]]) -> list[tuple[str, list[dict], list[str]]]:
    """For each projection-matrix file in ``folder/gt`` (``*P_matrices.txt``): its name, the
    models evaluated against it (no times: the same runs as the main table) and the verdict."""
    out = []
    sizes = {name: (pose.width, pose.height) for name, pose in gt.items()}
    for path in sorted((folder / "gt").glob("*P_matrices.txt")):
        other = read_projection_matrices(path, sizes)
        rows = [{k: v for k, v in evaluate_row(method, model, 0.0, other).items() if k != "time_s"}
                for method, model in models]
        out.append((path.name, rows, verdict(rows, len(other))))
    return out


def variant_section(heading: str, rows: list[dict], notes: list[str], where: Path) -> str:
    """The page's section of a variant of a set (sparser, downscaled): printed, and its rows
    and notes kept in ``where/rows.json``."""
    text = f"#### {heading}\n\n{markdown_table(rows)}\n\n" + "\n".join(f"- {n}" for n in notes)
    print(text + "\n", flush=True)
    (where / "rows.json").write_text(json.dumps({"rows": rows, "notes": notes}, indent=1))
    return text


def ordinal(n: int) -> str:
    """The English ordinal suffix of ``n`` (2 -> "nd", 11 -> "th")."""
    return "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_set_arguments(parser)
    parser.add_argument("--recording", action="store_true", help="graphsfm's default run writes its Rerun recording")
    parser.add_argument("--no-colmap-frontend", action="store_true",
                        help="skip pycolmap's own extraction and matching (its mappers on graphsfm's database only)")
    parser.add_argument("--no-per-image", action="store_true",
                        help="skip the runs with one camera per image")
    parser.add_argument("--every", type=int, nargs="+", default=[], metavar="N",
                        help="also every N-th image along each set's camera path, from each of the first N "
                        "(main table's methods only)")
    parser.add_argument("--every-min-images", type=int, default=10, metavar="M",
                        help="--every skips a set whose every N-th image is fewer than M images (default: %(default)s)")
    parser.add_argument("--downscale", type=int, nargs="+", default=[], metavar="F",
                        help="also each set with its images reduced F times in both directions, and --every on "
                        "those (main table's methods only)")
    parser.add_argument("--crop", type=int, nargs="+", default=[], metavar="F",
                        help="also each set with its images cropped to their central 1/F in both directions and "
                        "no EXIF (a long lens), and --every on those (main table's methods only)")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    if any(n < 2 for n in args.every):
        parser.error("--every takes integers of at least 2")
    if any(f < 2 for f in args.downscale):
        parser.error("--downscale takes integers of at least 2")
    if any(f < 2 for f in args.crop):
        parser.error("--crop takes integers of at least 2")
    logging.basicConfig(level=logging.WARNING, format="%(levelname).1s %(name)s: %(message)s")
    import os

    sets = args.sets or gt_sets(args.data)
    out = args.out or Path(tempfile.mkdtemp(prefix="graphsfm_bench_accuracy_"))
    threads = len(os.sched_getaffinity(0))
    context = run_context()
    sections = []
    for name in sets:
        rows, notes, others = bench_set(args.data, name, out, threads, args.recording, not args.no_colmap_frontend,
                                        context)
        text = f"### {name}\n\n{markdown_table(rows)}\n\n" + "\n".join(f"- {n}" for n in notes)
        for source, other_rows, other_notes in others:
            text += (f"\n\n#### {name} against `gt/{source}`\n\n{markdown_table(other_rows)}\n\n"
                     + "\n".join(f"- {n}" for n in other_notes))
        per_image: tuple[list[dict], list[str]] = ([], [])
        if not args.no_per_image:
            gt = read_gt_table(args.data / name / GT_TABLE)
            per_image = per_image_rows(args.data / name / "images", out / name, gt, context)
            text += (f"\n\n#### {name}, one camera per image\n\n{markdown_table(per_image[0])}\n\n"
                     + "\n".join(f"- {n}" for n in per_image[1]))
        print(text + "\n", flush=True)
        sections.append(text)
        (out / name / "rows.json").write_text(json.dumps({"rows": rows, "notes": notes, "other_gt": others,
                                                          "per_image": per_image}, indent=1))
        variants = [(args.data, name, name)]
        for factor, make, label in ([(f, downscaled_set, f"{name} at 1/{f} resolution") for f in args.downscale]
                                    + [(f, cropped_set, f"{name} cropped to its central 1/{f}") for f in args.crop]):
            sub = make(args.data, name, factor, out / "transformed")
            rows, notes, _ = bench_set(out / "transformed", sub, out / "transformed_runs", threads, args.recording,
                                       not args.no_colmap_frontend, context)
            sections.append(variant_section(label, rows, notes, out / "transformed_runs" / sub))
            variants.append((out / "transformed", sub, label))
        num_images = len(read_gt_table(args.data / name / GT_TABLE))
        for root, source, label in variants:
            for every, start in [(n, k) for n in args.every if num_images // n >= args.every_min_images for k in range(n)]:
                sub = sparser_set(root, source, every, start, out / "sparser")
                rows, notes, _ = bench_set(out / "sparser", sub, out / "sparser_runs", threads, args.recording,
                                           not args.no_colmap_frontend, context)
                count = len(range(start, num_images, every))
                heading = (f"{label}, every {every}{ordinal(every)} image along the camera path from the "
                           f"{start + 1}{ordinal(start + 1)} ({count} images)")
                sections.append(variant_section(heading, rows, notes, out / "sparser_runs" / sub))
    intro = ("graphsfm (defaults; and with forced clusters) and pycolmap's mappers on the same images, "
             "evaluated by `sfm.evaluation.metrics.evaluate` (largest model; rotation error after Sim3 "
             "alignment; relative-pose AUC). Times: graphsfm's default row the whole run (extract to final "
             "model), the cluster row cluster + map + merge on the same database, the COLMAP rows on "
             "graphsfm's database the mapper alone, the `extract+match` rows pycolmap's front end + mapper. "
             "The tables 'one camera per image' repeat graphsfm's run with `--camera-mode per-image` "
             "(internet photos' conditions: each image's intrinsics estimated on their own) and COLMAP's "
             "mappers on its database; the acceptance verdicts are the main tables'. The tables 'every N-th image "
             "along the camera path' (`--every`) run the main table's methods on a sparser version of the set, "
             "the tables 'at 1/F resolution' (`--downscale`) on the set's images reduced F times, the tables "
             "'cropped to its central 1/F' (`--crop`) on their central parts without EXIF, a long lens whose focal "
             "length starts from a guess F times too short (and `--every` on both).")
    publish(args, "accuracy", "Pose accuracy on the photo sets with ground truth", intro + "\n\n" + "\n\n".join(sections))
    return 0


if __name__ == "__main__":
    sys.exit(main())
