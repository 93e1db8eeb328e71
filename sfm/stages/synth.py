"""``graphsfm synth``: a scene with exact ground truth, written as a new workspace.

A correspondence-level scene (``sfm.synthetic.scenes``: orbit, street, aerial) becomes
``WORK/database.db`` (keypoints, raw matches, verified two-view geometries simulated as
``sfm.synthetic.matching`` describes), ``WORK/gt/cameras_gt_opencv.txt`` and ``WORK/gt/model``;
the rendered scene (``sfm.synthetic.rendered``) becomes ``WORK/images/*.png`` and the GT table.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from sfm.errors import InputError
from sfm.io.colmap_model import write_model
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import RenderOptions, SynthOptions
from sfm.synthetic.rendered import write_rendered_scene
from sfm.synthetic.scenes import gt_reconstruction, make_scene, write_gt_table

log = logging.getLogger(__name__)


def run_synth(workspace: Path, opts: SynthOptions) -> dict:
    """``graphsfm synth``: scene + database + GT table + GT model in ``workspace`` (or, for the
    rendered scene, images + GT table); returns a summary."""
    workspace = Path(workspace)
    if opts.scene == "rendered":
        if (workspace / "images").exists():
            raise InputError(f"{workspace / 'images'} exists; synth writes a new workspace (remove it first)")
        return write_rendered_scene(workspace, RenderOptions(num_images=opts.num_images, seed=opts.seed))
    db_path = workspace / "database.db"
    if db_path.exists():
        raise InputError(f"{db_path} exists; synth writes a new workspace (remove it first)")
    (workspace / "gt" / "model").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = make_scene(opts)
    pairs = simulate_matching(scene, opts)
    t1 = time.perf_counter()
    tmp_db = workspace / "database.db.partial"
    tmp_db.unlink(missing_ok=True)
    write_database(scene, pairs, tmp_db)
    tmp_db.replace(db_path)
    write_gt_table(scene, workspace / "gt" / "cameras_gt_opencv.txt")
    write_model(gt_reconstruction(scene), workspace / "gt" / "model")
    t2 = time.perf_counter()
    verified = [p for p in pairs if len(p.inlier_matches)]
    track_len = np.bincount(scene.obs_point)
    summary = {
        "scene": opts.scene,
        "images": len(scene.names),
        "points": len(scene.points),
        "observations": int(len(scene.obs_point)),
        "mean_track_length": round(float(track_len.mean()), 3),
        "pairs_with_matches": len(pairs),
        "verified_pairs": len(verified),
        "median_inliers": int(np.median([len(p.inlier_matches) for p in verified])) if verified else 0,
        "time_scene_s": round(t1 - t0, 2),
        "time_write_s": round(t2 - t1, 2),
        "database": str(db_path),
        "gt_table": str(workspace / "gt" / "cameras_gt_opencv.txt"),
        "gt_model": str(workspace / "gt" / "model"),
    }
    log.info("synth: %s", summary)
    return summary
