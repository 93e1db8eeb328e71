"""Our mapping against pycolmap's incremental (and global) mapper on the same database, one run.

    python tools/bench_mapping.py --workspace W [--gt TABLE] [--max-cluster-size S] [--global]

graphsfm runs from ``W/database.db`` to a final model: with ``--max-cluster-size`` the whole
divide-and-conquer path (cluster, map in parallel, merge, final BA), otherwise a single-cluster
``map``.  COLMAP's incremental mapper (and GLOMAP's global mapper with ``--global``) run on the
very same database in the same process, so the time ratio is trustworthy on a noisy machine.
Each result is evaluated against ``--gt`` (default: ``W/gt/cameras_gt_opencv.txt`` if present).
Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import tempfile
import time
import zlib  # noqa: F401 - before pycolmap (pycolmap first breaks later zlib use)
from pathlib import Path

import cv2  # noqa: F401 - same reason

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_page import add_page_arguments, markdown_table, peer_version, publish, run_context  # noqa: E402

from sfm.clustering.options import ClusterOptions
from sfm.stages.cluster import run_cluster
from sfm.io.colmap_model import read_model
from sfm.evaluation.metrics import evaluate
from sfm.evaluation.ground_truth import read_gt_table
from sfm.execution.local import LocalExecutor
from sfm.mapper.options import MapperOptions
from sfm.stages.map import run_map
from sfm.merge.options import MergeOptions
from sfm.stages.merge import run_merge


def run_graphsfm(db: Path, out: Path, max_cluster_size: int | None, workers: int) -> tuple[Path, float, int]:
    """Our pipeline from a copy of the database; returns (model folder, seconds, clusters)."""
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(db, out / "database.db")
    t0 = time.perf_counter()
    clusters = 1
    if max_cluster_size:
        clusters = run_cluster(out, ClusterOptions(max_cluster_size=max_cluster_size)).num_clusters
    result = run_map(out, MapperOptions(), executor=LocalExecutor(workers))
    if not result.direct:
        run_merge(out, MapperOptions(), MergeOptions())
    return out / "sparse" / "0", time.perf_counter() - t0, clusters


def run_colmap(db: Path, out: Path, kind: str) -> tuple[Path | None, float]:
    """pycolmap's ``kind`` mapper ("incremental", "global" or "hierarchical": clusters mapped
    incrementally and merged, COLMAP's divide and conquer) on a copy of ``db`` (``tools/resumable_colmap.py`` runs the incremental
    one in resumable segments for ``bench_scaling``)."""
    import pycolmap

    pycolmap.logging.minloglevel = 2
    out.mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    shutil.copy(db, out / "database.db")
    t0 = time.perf_counter()
    mapper = {"incremental": pycolmap.incremental_mapping, "global": pycolmap.global_mapping,
              "hierarchical": pycolmap.hierarchical_mapping}[kind]  # default options each
    models = mapper(str(out / "database.db"), str(out / "images"), str(out / "sparse"))
    elapsed = time.perf_counter() - t0
    if not models:
        return None, elapsed
    best = max(models, key=lambda k: models[k].num_reg_images())
    return out / "sparse" / str(best), elapsed


def row(method: str, model_dir: Path | None, seconds: float, gt) -> dict:
    out = {"method": method, "time_s": round(seconds, 1)}
    if model_dir is None:
        return {**out, "registered": 0}
    recon = read_model(model_dir)
    out.update({"registered": len(recon.images), "points": len(recon.points3D),
                "track_len": round(recon.mean_track_length, 2), "reproj_px": round(recon.mean_reprojection_error(), 3)})
    if gt is not None:
        res = evaluate(recon, gt)
        out.update({"med_rot_deg": round(res.median_rotation_error_deg, 4), "auc@1": round(res.auc[1], 3),
                    "auc@5": round(res.auc[5], 3), "auc@10": round(res.auc[10], 3)})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workspace", type=Path, required=True, help="workspace holding database.db")
    parser.add_argument("--gt", type=Path, help="GT table (default: WORK/gt/cameras_gt_opencv.txt if present)")
    parser.add_argument("--max-cluster-size", type=int, help="run cluster + map + merge with this S_max")
    parser.add_argument("--workers", type=int, default=0, help="graphsfm cluster workers (0: all cores)")
    parser.add_argument("--global", dest="global_", action="store_true", help="also run pycolmap's global mapper")
    parser.add_argument("--out", type=Path, help="where to put the runs (default: a temporary folder)")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    db = args.workspace / "database.db"
    gt_path = args.gt or (args.workspace / "gt" / "cameras_gt_opencv.txt")
    gt = read_gt_table(gt_path) if gt_path.exists() else None
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_mapping_"))
    rows = []
    model, seconds, clusters = run_graphsfm(db, out / "graphsfm", args.max_cluster_size, args.workers)
    rows.append(row(f"graphsfm ({clusters} clusters)", model, seconds, gt))
    model, seconds = run_colmap(db, out / "colmap_incremental", "incremental")
    rows.append(row("pycolmap incremental", model, seconds, gt))
    if args.global_:
        model, seconds = run_colmap(db, out / "colmap_global", "global")
        rows.append(row("pycolmap global", model, seconds, gt))
    context = run_context()
    for k, r in enumerate(rows):
        r.update({"date": context["date"], "machine": context["machine"],
                  "code": context["code"] if k == 0 else peer_version()})
    ratio = rows[0]["time_s"] / rows[1]["time_s"] if rows[1]["time_s"] else float("nan")
    text = f"{markdown_table(rows)}\n\ngraphsfm time / pycolmap incremental time = {ratio:.2f}"
    print(f"database: {db}  ({len(gt) if gt else '?'} GT images)\n{text}")
    name = args.workspace.resolve().name
    publish(args, f"mapping-{name}" + (f"-s{args.max_cluster_size}" if args.max_cluster_size else ""),
            f"Mapping from one database: {name}" + (f", --max-cluster-size {args.max_cluster_size}"
                                                     if args.max_cluster_size else ""), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
