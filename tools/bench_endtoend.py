"""End to end on an image folder: ``graphsfm reconstruct`` against COLMAP, in one run.

    python tools/bench_endtoend.py --images DIR [--gt TABLE] [--intrinsics FILE]
                                   [--max-cluster-size S] [--no-recording] [--repeat N] [--out DIR]

graphsfm: ``sfm.reconstruct(DIR, OUT/graphsfm, ...)`` with the defaults of ``graphsfm
reconstruct`` (every stage, the Rerun recording included unless ``--no-recording``; with
``--max-cluster-size`` the divide-and-conquer path). COLMAP: pycolmap's ``extract_features`` +
``match_exhaustive`` (as ``tools/bench_frontend.py`` runs them: CPU, its defaults, the same
number of threads) then ``incremental_mapping`` on that database. Both start from nothing in
fresh workspaces. Each side's largest model is evaluated against ``--gt``. Prints a Markdown
table (time per stage and in all, registered images, points, median rotation error, AUC) and
the ratio of the total times.  ``--repeat N`` runs both sides N times, alternating which goes
first (a shared machine drifts by tens of percent within minutes), prints every run's rows and
ratio, and the median ratio.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import zlib  # noqa: F401 - before pycolmap (pycolmap first breaks later zlib use)
from pathlib import Path

import cv2  # noqa: F401 - same reason

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_frontend import fresh, prepare, run_colmap
from bench_mapping import row
from benchmarks_page import add_page_arguments, markdown_table, peer_version, publish, run_context

from sfm.api import reconstruct
from sfm.evaluation.ground_truth import read_gt_table


def run_graphsfm(images: Path, workspace: Path, options: dict, recording: bool) -> dict:
    """Our whole pipeline from the images; the table row with the report's stage times."""
    fresh(workspace)
    t0 = time.perf_counter()
    _, report = reconstruct(images, workspace, recording=recording, **options)
    total = time.perf_counter() - t0
    times = report.get("times_s", {})
    rest = sum(times.get(k, 0.0) for k in ("cluster", "map", "merge", "final_ba"))
    stages = {"extract_s": times.get("extract"), "match_s": times.get("match"), "map_s": rest}
    return {"stages": stages, "total": total, "model": workspace / "sparse" / "0",
            "label": f"graphsfm reconstruct ({report.get('num_clusters', 1)} clusters)"}


def run_peer(images: Path, workspace: Path, intrinsics: Path | None, threads: int) -> dict:
    """pycolmap extract + exhaustive match + incremental mapping from the images."""
    import pycolmap

    t0 = time.perf_counter()
    front = run_colmap(images, workspace, intrinsics, threads)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    sparse = fresh(workspace / "sparse")
    t_map = time.perf_counter()
    models = pycolmap.incremental_mapping(str(workspace / "database.db"), str(images), str(sparse), options)
    t_end = time.perf_counter()
    best = max(models, key=lambda k: models[k].num_reg_images()) if models else None
    stages = {"extract_s": front.t_extract, "match_s": front.t_match, "map_s": t_end - t_map}
    return {"stages": stages, "total": t_end - t0, "model": sparse / str(best) if best is not None else None,
            "label": "pycolmap extract + match_exhaustive + incremental_mapping"}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=Path, required=True, help="image folder")
    parser.add_argument("--gt", type=Path, help="GT table (cam_from_world) to evaluate both models")
    parser.add_argument("--intrinsics", type=Path, help="intrinsics file (graphsfm's --intrinsics; COLMAP "
                        "gets one PINHOLE camera when the file has one set of values)")
    parser.add_argument("--max-cluster-size", type=int, help="graphsfm's --max-cluster-size")
    parser.add_argument("--no-recording", action="store_true", help="graphsfm without the Rerun recording")
    parser.add_argument("--repeat", type=int, default=1, help="run both sides N times, alternating which goes "
                        "first; prints each ratio and the median")
    parser.add_argument("--out", type=Path, help="output folder (default: a new temporary folder)")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    setup = prepare(args.images, args.out, "graphsfm_bench_endtoend_")
    if setup is None:
        return 2
    out, threads = setup
    gt = read_gt_table(args.gt) if args.gt else None
    options = {k: v for k, v in (("intrinsics", args.intrinsics), ("max_cluster_size", args.max_cluster_size))
               if v is not None}
    rows, ratios = [], []
    context = run_context()
    for i in range(args.repeat):
        where = out if args.repeat == 1 else out / f"run{i + 1}"
        ours = lambda: run_graphsfm(args.images, where / "graphsfm", options, not args.no_recording)  # noqa: E731
        peer = lambda: run_peer(args.images, where / "colmap", args.intrinsics, threads)  # noqa: E731
        runs = [ours(), peer()] if i % 2 == 0 else list(reversed([peer(), ours()]))
        ratios.append(runs[0]["total"] / runs[1]["total"])
        for run, ours_side in zip(runs, (True, False)):
            r = row(run["label"], run["model"], run["total"], gt)
            run_column = {"run": i + 1} if args.repeat > 1 else {}
            ratio = {"ratio": round(ratios[-1], 2) if ours_side else ""}
            code = {"code": context["code"] if ours_side else peer_version()}
            rows.append({**run_column, "method": r.pop("method"), **{k: round(v, 1) for k, v in run["stages"].items()},
                         **r, **ratio, "date": context["date"], "machine": context["machine"], **code})
    summary = (f"total time graphsfm / COLMAP: {', '.join(f'{x:.2f}' for x in ratios)}"
               + (f" (median {statistics.median(ratios):.2f})" if len(ratios) > 1 else ""))
    text = f"{markdown_table(rows)}\n\n{summary}"
    print(f"## End to end: {args.images} ({threads} threads each; workspaces in {out})\n\n{text}")
    publish(args, f"endtoend-{args.images.resolve().parent.name}-{args.images.name}",
            f"End to end from the images: {args.images.resolve().parent.name}", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
