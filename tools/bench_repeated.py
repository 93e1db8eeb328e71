"""Repeated structures: graphsfm and pycolmap's mappers on scenes where buildings repeat.

    python tools/bench_repeated.py --out DIR [--scenes street-twins] [--workers 2]

Each scene is made once in ``DIR/data/<scene>`` with exact ground truth:

- ``street-twins``: ``graphsfm synth --scene street --num-images 200 --twins 2 --seed 0``, a
  street walked along whose facades repeat twice (``sfm.synthetic.scenes.street_twins``: one
  stretch again further along the same facade, one again across the street, turned to face it);
  their features match as if each were one building, so a pair of images that see the two
  copies is verified with the twin's apparent geometry.

On a copy of each database: graphsfm from the database (cluster, map with ``--workers``
local workers, merge) with the default cluster size and with ``--max-cluster-size 50``, and
pycolmap's global and incremental mappers.  Every output model is compared with the ground
truth on its own (Sim3 alignment, rotation error): ``wrong`` counts the images more than 5
degrees off in any model, the failure the repeated-structures work must avoid (a model glued
wrong); ``models`` and ``registered`` (in the largest) say how much a method split.  AUC and
median rotation error are the largest model's.  Prints the table and refreshes its section of
``tools/BENCHMARKS.md``.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import time
import zlib  # noqa: F401 - before pycolmap (pycolmap first breaks later zlib use)
from pathlib import Path

import cv2  # noqa: F401 - same reason
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_page import add_page_arguments, markdown_table, peer_version, publish, run_context  # noqa: E402

SCENES = {"street-twins": dict(scene="street", num_images=200, twins=2, seed=0)}
WRONG_DEG = 5.0


def make_scene(out: Path, name: str) -> Path:
    from sfm.stages.synth import run_synth
    from sfm.synthetic.options import SynthOptions

    data = out / "data" / name
    if not (data / "database.db").exists():
        shutil.rmtree(data, ignore_errors=True)
        run_synth(data, SynthOptions(**SCENES[name]))
    return data


def judge(models: list[Path], gt, method: str, seconds: float, code: str) -> dict:
    """The row of one method's output models against the ground truth."""
    from sfm.evaluation.metrics import evaluate
    from sfm.io.colmap_model import read_model

    recons = sorted((read_model(m) for m in models), key=lambda r: -len(r.images))
    row = {"method": method, "time_s": round(seconds, 1), "models": len(recons), "registered": 0, "wrong": 0}
    for k, recon in enumerate(recons):
        if len(recon.images) < 3:
            continue
        res = evaluate(recon, gt)
        row["wrong"] += int(np.sum(np.array(list(res.rotation_errors_deg.values())) > WRONG_DEG))
        if k == 0:
            row.update({"registered": len(recon.images), "med_rot_deg": round(res.median_rotation_error_deg, 4),
                        "auc@1": round(res.auc[1], 3), "auc@5": round(res.auc[5], 3)})
    return {**row, "code": code}


def run_graphsfm(data: Path, work: Path, max_cluster_size: int | None, workers: int) -> tuple[list[Path], float]:
    from sfm.clustering.options import ClusterOptions
    from sfm.execution.local import LocalExecutor
    from sfm.mapper.options import MapperOptions
    from sfm.merge.options import MergeOptions
    from sfm.stages.cluster import run_cluster
    from sfm.stages.map import run_map
    from sfm.stages.merge import run_merge

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    shutil.copy(data / "database.db", work / "database.db")
    t0 = time.perf_counter()
    options = ClusterOptions() if max_cluster_size is None else ClusterOptions(max_cluster_size=max_cluster_size)
    run_cluster(work, options)
    result = run_map(work, MapperOptions(), executor=LocalExecutor(workers))
    if not result.direct:
        run_merge(work, MapperOptions(), MergeOptions())
    seconds = time.perf_counter() - t0
    return sorted(p for p in (work / "sparse").iterdir() if p.is_dir()), seconds


def run_colmap(data: Path, work: Path, kind: str) -> tuple[list[Path], float]:
    import pycolmap

    pycolmap.logging.minloglevel = 2
    shutil.rmtree(work, ignore_errors=True)
    (work / "images").mkdir(parents=True)
    shutil.copy(data / "database.db", work / "database.db")
    t0 = time.perf_counter()
    mapper = {"incremental": pycolmap.incremental_mapping, "global": pycolmap.global_mapping}[kind]
    models = mapper(str(work / "database.db"), str(work / "images"), str(work / "sparse"))
    return [work / "sparse" / str(k) for k in models], time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder for the scenes and the runs")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--workers", type=int, default=2, help="local workers of graphsfm's map stage")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from sfm.evaluation.ground_truth import read_gt_table

    context = run_context()
    rows = []
    for name in args.scenes:
        data = make_scene(args.out, name)
        gt = read_gt_table(data / "gt" / "cameras_gt_opencv.txt")
        runs = args.out / "runs" / name
        for label, size in (("graphsfm", None), ("graphsfm --max-cluster-size 50", 50)):
            models, seconds = run_graphsfm(data, runs / label.replace(" ", "_"), size, args.workers)
            rows.append({"scene": name, **judge(models, gt, label, seconds, context["code"])})
            print(rows[-1], flush=True)
        for kind in ("global", "incremental"):
            models, seconds = run_colmap(data, runs / f"colmap-{kind}", kind)
            rows.append({"scene": name, **judge(models, gt, f"colmap-{kind}", seconds, peer_version())})
            print(rows[-1], flush=True)
    keys = ["scene", "method", "time_s", "models", "registered", "wrong", "med_rot_deg", "auc@1", "auc@5", "code"]
    text = (markdown_table(rows, keys) + f"\n\n`wrong`: images more than {WRONG_DEG:g} degrees off after Sim3 "
            "alignment, in any output model; `registered`, `med_rot_deg` and AUC: the largest model. Measured "
            f"{context['date']} on {context['machine']}.")
    print(text)
    publish(args, "repeated", "Repeated structures: scenes whose buildings repeat", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
