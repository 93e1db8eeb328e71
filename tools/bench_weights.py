"""Observation weights on the sets with pose ground truth: what keypoint-scale weights do to
graphsfm's accuracy, and whether the photos' own residuals bear out the weights' noise model.

    python tools/bench_weights.py [--data ../shared/data] [--sets lund_door temple_ring ...]
                                  [--out DIR] [--from ACCURACY_OUT]

graphsfm's bundle adjustments weigh each observation by its keypoint's detection scale (std
``max(1, scale / 0.8)`` px, ``sfm.features.sift.localization_sigma``); COLMAP weighs every
observation alike (1 px).  Per set, from one database (a default ``reconstruct`` of the set's
images, or the one a ``tools/bench_accuracy.py --out`` folder holds: ``--from``):

- ``graphsfm`` (scale weights, the default) and ``graphsfm, --no-scale-weights``, each a
  ``reconstruct`` from a copy of that database, and COLMAP's incremental and global mappers on
  it, evaluated as ``tools/bench_accuracy.py`` does, against the set's pose table and, where its
  ``gt/`` holds them, its projection matrices (a second ground truth: lund_door's pose table is
  itself a COLMAP model, made with COLMAP's 1 px weights);
- the residuals of the default model per keypoint-scale octave (half-octave bins): their spread
  per axis (the median reprojection error over ``sqrt(2 ln 2)``, the median of a 2-D Gaussian
  error's length), and that spread over the bin's median scale.  A ratio constant across the
  bins is the weights' model, an error in proportion to the scale; a ratio that falls says the
  error grows more slowly than the scale on that set.
"""

from __future__ import annotations

import argparse
import itertools
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
from bench_accuracy import GT_TABLE, add_set_arguments, evaluate_row, gt_sets, stamp
from bench_frontend import fresh
from bench_mapping import run_colmap as run_colmap_mapper
from benchmarks_page import add_page_arguments, markdown_table, publish, run_context

from sfm.api import reconstruct
from sfm.evaluation.ground_truth import read_gt_table, read_projection_matrices
from sfm.io.colmap_model import read_model
from sfm.io.database import Database

# The median length of a 2-D error with independent N(0, s^2) axes is s * sqrt(2 ln 2).
MEDIAN_LENGTH_PER_SIGMA = math.sqrt(2.0 * math.log(2.0))
# Bins with fewer observations than this are left out of the residual table.
MIN_BIN_OBSERVATIONS = 200
PAGE_INTRO = """graphsfm with keypoint-scale weights (the default) and with 1 px for every observation
(`--no-scale-weights`, COLMAP's weights), from one database per set, beside COLMAP's mappers on that
database; then the default model's residuals per keypoint-scale octave: a constant `spread/scale` is
the weights' model, a falling one an error growing more slowly than the scale."""


def database_of(data: Path, name: str, where: Path, accuracy_out: Path | None) -> Path:
    """The set's database: copied from ``accuracy_out/<name>/graphsfm`` or made by a default
    ``reconstruct`` of its images (the recording off) in ``where/extract``."""
    if accuracy_out is not None:
        source = accuracy_out / name / "graphsfm" / "database.db"
        if not source.exists():
            raise SystemExit(f"bench_weights: error: {source} does not exist (run tools/bench_accuracy.py --out first)")
        return source
    fresh(where / "extract")
    reconstruct(data / name / "images", where / "extract", recording=False)
    return where / "extract" / "database.db"


def graphsfm_from(database: Path, workspace: Path, **options) -> tuple[Path, float]:
    """``reconstruct`` from a copy of ``database`` with ``options``; (model, seconds)."""
    fresh(workspace)
    shutil.copy(database, workspace / "database.db")
    t0 = time.perf_counter()
    reconstruct(None, workspace, recording=False, **options)
    return workspace / "sparse" / "0", time.perf_counter() - t0


def residuals_by_scale(model_dir: Path, database: Path) -> list[dict]:
    """The residual table (module docstring) of the model in ``model_dir``, the keypoint
    scales read from ``database``."""
    model = read_model(model_dir)
    _, image_ids, keypoints = model.observations()
    _, error = model.reprojection_errors()  # the same order as observations()
    with Database(database, readonly=True) as db:
        table = db.read_all_keypoints(sorted(set(image_ids.tolist())))
    if any(kp.shape[1] < 3 for kp in table.values()):
        return []  # no scales stored
    scale = np.empty(len(error))
    for i, kp in table.items():
        rows = image_ids == i
        scale[rows] = kp[keypoints[rows], 2]
    edges = 0.8 * 2.0 ** np.arange(0.0, 8.5, 0.5)
    rows = []
    for low, high in itertools.pairwise(edges):
        inside = (scale >= low) & (scale < high)
        if inside.sum() < MIN_BIN_OBSERVATIONS:
            continue
        spread = float(np.median(error[inside])) / MEDIAN_LENGTH_PER_SIGMA
        median_scale = float(np.median(scale[inside]))
        rows.append({"scale": f"{low:.1f}-{high:.1f}", "observations": int(inside.sum()),
                     "median_scale": round(median_scale, 2), "spread_px": round(spread, 3),
                     "spread/scale": round(spread / median_scale, 4)})
    return rows


def bench_set(data: Path, name: str, out: Path, accuracy_out: Path | None, context: dict) -> str:
    """The page's section of one set: printed as it is made."""
    gt = read_gt_table(data / name / GT_TABLE)
    where = out / name
    database = database_of(data, name, where, accuracy_out)
    models = []
    for method, options in (("graphsfm", {}), ("graphsfm, --no-scale-weights", {"scale_weights": False})):
        model, seconds = graphsfm_from(database, where / ("graphsfm" if options else "graphsfm_default"), **options)
        models.append((method, model, seconds))
    for kind in ("incremental", "global"):
        model, seconds = run_colmap_mapper(database, where / f"colmap_{kind}", kind)
        models.append((f"colmap {kind} (the same database)", model, seconds))
    rows = [evaluate_row(method, model, seconds, gt) for method, model, seconds in models]
    stamp(rows, context)
    text = f"### {name}\n\n{markdown_table(rows)}\n"
    sizes = {image: (pose.width, pose.height) for image, pose in gt.items()}
    for path in sorted((data / name / "gt").glob("*P_matrices.txt")):
        other = read_projection_matrices(path, sizes)
        second = [{k: v for k, v in evaluate_row(method, model, 0.0, other).items() if k != "time_s"}
                  for method, model, _ in models]
        text += f"\nAgainst `gt/{path.name}`:\n\n{markdown_table(second)}\n"
    residuals = residuals_by_scale(models[0][1], database)
    if residuals:
        text += f"\nResiduals of the default model by keypoint scale:\n\n{markdown_table(residuals)}\n"
    print(text, flush=True)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_set_arguments(parser)
    parser.add_argument("--from", dest="accuracy_out", type=Path,
                        help="a tools/bench_accuracy.py --out folder whose graphsfm databases to map from "
                             "(default: extract and match each set here)")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        parser.error(f"{args.data} is not a folder")
    names = args.sets or gt_sets(args.data)
    missing = [n for n in names if not (args.data / n / GT_TABLE).exists()]
    if missing:
        parser.error(f"no {GT_TABLE} for: {', '.join(missing)}")
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_weights_"))
    context = run_context()
    sections = [bench_set(args.data, name, out, args.accuracy_out, context) for name in names]
    publish(args, "weights", "Observation weights", PAGE_INTRO + "\n\n" + "\n".join(sections))
    return 0


if __name__ == "__main__":
    sys.exit(main())
