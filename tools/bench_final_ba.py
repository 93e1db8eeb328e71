"""The final bundle adjustment whole against the consensus of K track parts, on one mapped model.

    python tools/bench_final_ba.py --out DIR [--images 1000] [--parts 1 2 4 8] [--workers 2]

Above its memory budget (``--ba-max-observations``; by default what half of the machine's memory
holds) the merge's final BA is the consensus of BAs over K random track parts
(``backend.partitioned_ba``), an approximation of the one BA.  This measures what it costs in
accuracy, time and memory.  ``graphsfm synth --scene aerial --outlier-ratio 0.2 --seed 0`` makes
``DIR/data/<n>`` once; ``cluster`` and ``map`` (``--workers`` local workers) run once into
``DIR/mapped/<n>``; then, for each K, ``graphsfm merge`` runs on a copy of that mapped workspace
in a child process with ``--ba-max-observations`` set so that the final BA splits into K parts
(K = 1: ``0``, no limit, the one BA), and its model is compared with the ground truth.  Peak
memory is the largest RSS of the merge's process tree, sampled every 0.2 s.  Each K's row is
cached in ``DIR/runs/<n>/parts<K>.json`` (``--force`` reruns).  Prints the table and refreshes
its section of ``tools/BENCHMARKS.md``.  Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scaling import make_aerial, run_child  # noqa: E402
from benchmarks_page import add_page_arguments, markdown_table, publish, run_context  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
COLUMNS = ["images", "parts", "budget", "observations", "final_ba_s", "merge_s", "peak_rss_gb", "registered",
           "med_rot_deg", "p90_rot_deg", "auc@1", "auc@5", "rms_after_px", "code", "date", "machine"]
# The budget a K-part run is given: the one BA's observations over K with this slack, since the
# model that reaches a later final BA may hold a few more observations than the first one did.
SLACK = 1.02


def graphsfm(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "sfm", "-q", *args], check=True, cwd=ROOT)


def mapped_workspace(out: Path, n: int, workers: int) -> Path:
    """``DIR/mapped/<n>``: the synthetic block's database, clustered and mapped (made once)."""
    data, mapped = out / "data" / str(n), out / "mapped" / str(n)
    if not (data / "database.db").exists():
        make_aerial(data, n)
    if not (mapped / "mapped.done").exists():
        shutil.rmtree(mapped, ignore_errors=True)
        mapped.mkdir(parents=True)
        shutil.copy(data / "database.db", mapped / "database.db")
        graphsfm("cluster", "--workspace", str(mapped), "--no-recording")
        graphsfm("map", "--workspace", str(mapped), "--workers", str(workers), "--no-recording")
        (mapped / "mapped.done").touch()
    return mapped


def merge_run(out: Path, n: int, mapped: Path, parts: int, budget: int) -> dict:
    """``graphsfm merge --ba-max-observations budget`` on a copy of ``mapped``: the row."""
    import numpy as np

    from bench_mapping import row
    from sfm.evaluation.ground_truth import read_gt_table
    from sfm.evaluation.metrics import evaluate
    from sfm.io.colmap_model import read_model

    work = out / "runs" / str(n) / f"parts{parts}"
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(mapped, work, ignore=shutil.ignore_patterns("sparse", "mapped.done"))
    print(f"{n} images, final BA in {parts} part(s) (--ba-max-observations {budget}) ...", flush=True)
    argv = [sys.executable, "-m", "sfm", "-q", "merge", "--workspace", str(work), "--no-recording",
            "--ba-max-observations", str(budget)]
    code, seconds, peak = run_child(argv)
    if code != 0:
        raise SystemExit(f"merge with {parts} part(s) failed with exit code {code}")
    report = json.loads((work / "report.json").read_text())
    model = report["models"][0]  # the largest
    final_ba = model.get("final_ba") or {}
    gt = read_gt_table(out / "data" / str(n) / "gt" / "cameras_gt_opencv.txt")
    model_dir = Path(model["path"])
    r = row(f"parts{parts}", model_dir, seconds, gt)
    errors = list(evaluate(read_model(model_dir), gt).rotation_errors_deg.values())
    (work / "database.db").unlink()
    return {"images": n, "parts": final_ba.get("parts", parts), "budget": budget if budget else "none",
            "observations": final_ba.get("observations"), "final_ba_s": report["times_s"].get("final_ba"),
            "merge_s": round(seconds, 1), "peak_rss_gb": round(peak / 1024**3, 2),
            "registered": f"{r['registered']}/{n}", "med_rot_deg": r.get("med_rot_deg"),
            "p90_rot_deg": round(float(np.percentile(errors, 90)), 4), "auc@1": r.get("auc@1"),
            "auc@5": r.get("auc@5"), "rms_after_px": final_ba.get("rms_after_px"), **run_context()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder for data, the mapped model and the runs")
    parser.add_argument("--images", type=int, default=1000, help="images of the synthetic aerial block")
    parser.add_argument("--parts", type=int, nargs="+", default=[1, 2, 4, 8], help="K: track parts of the final BA")
    parser.add_argument("--workers", type=int, default=2, help="local workers of the map stage")
    parser.add_argument("--force", action="store_true", help="rerun cached rows")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    out, n = args.out.resolve(), args.images
    os.chdir(ROOT)  # the children run this checkout's code (``python -m sfm`` from here)
    mapped = mapped_workspace(out, n, args.workers)
    rows: dict[int, dict] = {}
    for k in sorted(set(args.parts)):
        cache = out / "runs" / str(n) / f"parts{k}.json"
        if cache.exists() and not args.force:
            rows[k] = json.loads(cache.read_text())
            continue
        if k == 1:
            budget = 0
        else:  # the one BA's size decides the budget that splits it into k parts
            whole_cache = out / "runs" / str(n) / "parts1.json"
            if 1 not in rows:
                rows[1] = json.loads(whole_cache.read_text()) if whole_cache.exists() and not args.force \
                    else merge_run(out, n, mapped, 1, 0)
            whole = rows[1]
            budget = math.ceil(SLACK * whole["observations"] / k)
        rows[k] = merge_run(out, n, mapped, k, budget)
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_text(json.dumps(rows[k]))
    for k, r in rows.items():  # the one BA's row is cached when it was run to size the others
        cache = out / "runs" / str(n) / f"parts{k}.json"
        if not cache.exists():
            cache.write_text(json.dumps(r))
    table = markdown_table([rows[k] for k in sorted(rows)], COLUMNS)
    text = (f"{table}\n\nSynthetic aerial, 20% outlier matches, one mapped "
            "model; `parts` 1 is the one BA, K the consensus of K BAs over random track parts ("
            "`--ba-max-observations` = `budget`). `merge_s`: the whole merge stage; `rms_after_px`: of the pooled cameras with the points "
            "re-estimated; `p90_rot_deg`: 90th percentile of the rotation errors after Sim3 alignment.")
    print(text)
    publish(args, f"final_ba_{n}", f"The final BA whole against the consensus of K track parts ({n} aerial images)",
            text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
