"""``graphsfm demo``: a rendered scene reconstructed with several clusters and scored.

The rendered facade (``sfm.synthetic.rendered``) is written into ``WORK/scene``, reconstructed
by :func:`sfm.stages.reconstruct.reconstruct` with a cluster bound small enough to cut it into
several clusters that are merged, and the model is evaluated against the scene's exact ground
truth (``sfm.evaluation.metrics``).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from sfm.errors import InputError
from sfm.evaluation.ground_truth import read_gt_table
from sfm.evaluation.metrics import evaluate
from sfm.io.colmap_model import read_model
from sfm.io.report import update_report
from sfm.io.workspace import DATABASE, RECORDING
from sfm.stages.reconstruct import ReconstructOptions, reconstruct
from sfm.synthetic.options import DemoOptions, RenderOptions
from sfm.synthetic.rendered import write_rendered_scene

log = logging.getLogger(__name__)


def run_demo(workspace: Path, demo: DemoOptions, options: ReconstructOptions | None = None,
             command: str | None = None) -> dict:
    """Render, reconstruct and evaluate in ``workspace`` (a new folder); a summary with the
    accuracy.  ``options``: the run's other options (the demo's seed and cluster bound win)."""
    workspace = Path(workspace)
    if (workspace / DATABASE).exists():
        raise InputError(f"{workspace} already holds a run; give a new folder")
    options = options or ReconstructOptions()
    options = dataclasses.replace(
        options, cluster=dataclasses.replace(options.cluster, max_cluster_size=demo.max_cluster_size, seed=demo.seed),
        match=dataclasses.replace(options.match, seed=demo.seed),
        mapper=dataclasses.replace(options.mapper, seed=demo.seed))
    scene = write_rendered_scene(workspace / "scene", RenderOptions(num_images=demo.num_images, seed=demo.seed))
    reconstruct(Path(scene["image_dir"]), workspace, options, command)
    result = evaluate(read_model(workspace / "sparse" / "0"), read_gt_table(Path(scene["gt_table"])))
    accuracy = result.to_dict(per_image=False)  # NaN as null
    report = update_report(workspace, {"accuracy": accuracy})
    log.info("demo: %d of %d images registered, median rotation error %.3g deg, AUC@1/5/10 %.3f/%.3f/%.3f",
             result.num_registered, report["images"], result.median_rotation_error_deg, result.auc[1], result.auc[5],
             result.auc[10])
    return {"images": report["images"], "clusters": report["num_clusters"], "models": report["num_models"],
            "registered": result.num_registered, "median_rotation_error_deg": accuracy["median_rotation_error_deg"],
            "auc@1": result.auc[1], "auc@5": result.auc[5], "auc@10": result.auc[10], "times_s": report["times_s"],
            "model": str((workspace / "sparse" / "0").resolve()), "recording": str((workspace / RECORDING).resolve())}
