"""``graphsfm synth``: a scene with exact ground truth, written as a new workspace.

A correspondence-level scene (``sfm.synthetic.scenes``: orbit, street, aerial) becomes
``WORK/database.db`` (keypoints, raw matches, verified two-view geometries simulated as
``sfm.synthetic.matching`` describes), ``WORK/gt/cameras_gt_opencv.txt`` and ``WORK/gt/model``;
the rendered scene (``sfm.synthetic.rendered``) becomes ``WORK/images/*.png`` and the GT table.

The survey (``sfm.synthetic.survey``) becomes ``WORK/images/survey_NNNNN.jpg``, rendered by a
pool of worker processes that return each photo's bytes for this process to write in index
order (a temporary name, then a rename), ``WORK/gt/survey.json`` (its parameters, written
first) and the GT table (written last).  It resumes: a rerun with the same options finds its
``survey.json`` and renders only the photos not yet there; other options are refused.
"""

from __future__ import annotations

import json
import logging
import os
import time
from functools import partial
from pathlib import Path

import numpy as np

from sfm.core import progress
from sfm.errors import InputError
from sfm.execution.local import LocalExecutor
from sfm.io.colmap_model import write_model
from sfm.io.workspace import read_json, write_json_atomic
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import RenderOptions, SynthOptions
from sfm.synthetic.rendered import write_rendered_scene
from sfm.synthetic.scenes import TWIN_LENGTH_M, gt_reconstruction, make_scene, write_gt_table
from sfm.synthetic.survey import camera_kind, description, gt_table, image_name, photo, survey_plan

log = logging.getLogger(__name__)


def run_synth(workspace: Path, opts: SynthOptions) -> dict:
    """``graphsfm synth``: scene + database + GT table + GT model in ``workspace`` (or, for the
    rendered scene, images + GT table); returns a summary."""
    workspace = Path(workspace)
    if opts.scene == "survey":
        return _write_survey(workspace, opts)
    if opts.scene == "rendered":
        if (workspace / "images").exists():
            raise InputError(f"{workspace / 'images'} exists; synth writes a new workspace (remove it first)")
        return write_rendered_scene(workspace, RenderOptions(num_images=opts.num_images, seed=opts.seed))
    if opts.twins and opts.scene != "street":
        raise InputError(f"twins: only the survey and street scenes have them, not {opts.scene}")
    if opts.twins and (opts.num_images - 1) / (2 * opts.twins) < TWIN_LENGTH_M + 10.0:
        raise InputError(f"twins {opts.twins}: a street of {opts.num_images} images is too short for them "
                         f"(each twin needs {2 * (TWIN_LENGTH_M + 10.0):.0f} images); fewer twins or more images")
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


def _write_survey(workspace: Path, opts: SynthOptions) -> dict:
    """The survey's photos, ``gt/survey.json`` and GT table in ``workspace`` (module docstring)."""
    progress.stage("synth")
    plan = survey_plan(opts)
    try:
        scene = json.loads(json.dumps(description(plan)))  # as it reads back
    except ValueError as exc:  # too many twins for the area
        raise InputError(str(exc)) from None
    image_dir, spec_path = workspace / "images", workspace / "gt" / "survey.json"
    if image_dir.exists():
        if not spec_path.exists():
            raise InputError(f"{image_dir} exists and holds no survey ({spec_path} is missing); synth "
                             "writes a new workspace (remove it first)")
        found = read_json(spec_path)
        if found != scene:
            before = found.get("options", {}) if isinstance(found, dict) else {}
            differ = ", ".join(f"{k} {before.get(k)} (now {v})" for k, v in scene["options"].items()
                               if before.get(k) != v) or "another version of the scene"
            raise InputError(f"{image_dir} holds a survey made with other options ({differ}); rerun with "
                             "those or remove it")
    else:
        write_json_atomic(spec_path, scene)
        image_dir.mkdir(parents=True)
    for stale in image_dir.glob(".survey_*.tmp"):  # photos in flight when a run was stopped
        stale.unlink()
    todo = [i for i in range(plan.num_images) if not (image_dir / image_name(i)).exists()]
    t0 = time.perf_counter()
    executor = LocalExecutor(opts.workers)
    results = executor.map(partial(photo, plan), todo)
    for result in progress.bar(results, total=len(todo), desc="synth survey", unit="photo"):
        name = image_name(todo[result.index])
        tmp = image_dir / f".{name}.tmp"
        tmp.write_bytes(result.value)
        os.replace(tmp, image_dir / name)
    elapsed = time.perf_counter() - t0
    gt_path = workspace / "gt" / "cameras_gt_opencv.txt"
    tmp = gt_path.with_name(f".{gt_path.name}.tmp")
    tmp.write_text(gt_table(plan))
    os.replace(tmp, gt_path)
    kinds = [camera_kind(plan, i) for i in range(plan.num_images)]
    summary = {
        "scene": "survey",
        "images": plan.num_images,
        "rendered": len(todo),
        "already_there": plan.num_images - len(todo),
        "nadir": kinds.count("nadir"),
        "oblique": plan.num_images - kinds.count("nadir"),
        "size": [plan.width, plan.height],
        "focal": plan.focal,
        "gsd_m": round(plan.gsd_m, 4),
        "strips": plan.strips,
        "workers": executor.workers,
        "time_render_s": round(elapsed, 2),
        "seconds_per_photo_per_worker": round(elapsed * min(executor.workers, len(todo)) / len(todo), 3)
        if todo else None,
        "image_dir": str(image_dir),
        "gt_table": str(gt_path),
        "survey_json": str(spec_path),
    }
    log.info("synth: %s", summary)
    return summary
