"""Run COLMAP's incremental mapper (pycolmap) on a graphsfm database and evaluate it.

Proof that our ``database.db`` is valid for COLMAP, and the peer column of later benchmarks.
With no ``--workspace`` it first makes a synthetic orbit scene (100 images, 20% outlier matches):

    python tools/colmap_on_database.py                       # synth orbit 100 + COLMAP
    python tools/colmap_on_database.py --workspace W         # an existing workspace

Prints one table row: images, registered, points, mean track length, mean reprojection error,
time, and the GT metrics when ``W/gt/cameras_gt_opencv.txt`` exists.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
import zlib  # noqa: F401 - import before pycolmap (pycolmap first breaks later zlib use)
from pathlib import Path

import cv2  # noqa: F401 - same reason

from sfm.io.colmap_model import read_model
from sfm.evaluation.metrics import evaluate
from sfm.evaluation.ground_truth import read_gt_table
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def run_colmap_incremental(workspace: Path, num_threads: int = -1, quiet: bool = True) -> tuple[Path | None, float]:
    """``pycolmap.incremental_mapping`` on ``workspace/database.db``; returns the largest model's
    folder (``workspace/colmap/<k>``) and the wall time."""
    import pycolmap

    if quiet:  # COLMAP logs every step (and a warning per missing image file) through glog
        pycolmap.logging.minloglevel = 2

    out = workspace / "colmap"
    out.mkdir(exist_ok=True)
    images = workspace / "images"
    images.mkdir(exist_ok=True)  # COLMAP wants the folder, not the files
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(str(workspace / "database.db"), str(images), str(out), options)
    elapsed = time.perf_counter() - t0
    if not models:
        return None, elapsed
    best = max(models, key=lambda k: models[k].num_reg_images())
    return out / str(best), elapsed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workspace", type=Path, help="workspace with database.db (default: a new synthetic orbit scene)")
    parser.add_argument("--images", type=int, default=100, help="images of the synthetic scene (default 100)")
    parser.add_argument("--scene", default="orbit", choices=["orbit", "street", "aerial"])
    parser.add_argument("--outlier-ratio", type=float, default=0.2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--min-registered", type=int, default=None, help="exit 1 when COLMAP registers fewer images")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname).1s %(name)s: %(message)s")

    workspace = args.workspace
    if workspace is None:
        workspace = Path(tempfile.mkdtemp(prefix="graphsfm_colmap_"))
        run_synth(workspace, SynthOptions(scene=args.scene, num_images=args.images, outlier_ratio=args.outlier_ratio, seed=args.seed))
    model_dir, elapsed = run_colmap_incremental(workspace)
    row = {"workspace": str(workspace), "peer": "pycolmap.incremental_mapping", "time_s": round(elapsed, 2)}
    if model_dir is None:
        row["registered"] = 0
    else:
        recon = read_model(model_dir)
        row.update(recon.summary())
        gt_table = workspace / "gt" / "cameras_gt_opencv.txt"
        if gt_table.exists():
            res = evaluate(recon, read_gt_table(gt_table)).to_dict()
            row.update({k: res[k] for k in ("num_gt_images", "median_rotation_error_deg", "auc@1", "auc@5", "auc@10")})
    print("| " + " | ".join(row) + " |")
    print("|" + "---|" * len(row))
    print("| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row.values()) + " |")
    print(json.dumps(row), file=sys.stderr)
    if args.min_registered is not None and row["registered"] < args.min_registered:
        print(f"COLMAP registered {row['registered']} < {args.min_registered}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
