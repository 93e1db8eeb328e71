"""Rerun views of the map stage: each cluster's model growing image by image.

The cluster's :class:`sfm.mapper.growth.Growth` (made wherever the cluster ran) is logged here,
in the main process, on the ``registration`` timeline (the number of registered images):
``clusters/<C>/model<m>/cams/<name>`` (pose at every step, frustum and image from the step that
registered it), ``clusters/<C>/model<m>/points`` (the sample of points, in their colours) and
``clusters/<C>/model<m>/ba_rms_px`` (the last bundle adjustment's RMS reprojection error),
``clusters/<C>/model<m>/calibration`` (what its final bundle adjustments refined of each camera,
and why), ``clusters/<C>/model<m>/joins`` (the earlier models that joined it as a whole, and
on what evidence), ``clusters/<C>/model<m>/unjoined`` (those that did not, and which step fell
short); a model attempt too small to keep is ``clusters/<C>/dropped<a>``, one that
joined a later model ``clusters/<C>/joined<a>``, one taken apart because a later model
rejected the focal length it grew at ``clusters/<C>/taken_apart<a>`` (``/taken_apart`` says
why).  ``clusters/<C>/unregistered`` says why each image in no model was left out;
``clusters/<C>/error`` why a cluster failed.
"""

from __future__ import annotations

import numpy as np

from sfm.viz.models import frustum_depth, log_frustum, log_model, world_centres, world_quaternions
from sfm.viz.recorder import Recorder, entity_part


def model_prefix(label: str, rank: int, attempt: int, absorbed: bool = False, taken_apart: bool = False) -> str:
    if absorbed:
        return f"clusters/{label}/joined{attempt}"
    if taken_apart:
        return f"clusters/{label}/taken_apart{attempt}"
    return f"clusters/{label}/model{rank}" if rank >= 0 else f"clusters/{label}/dropped{attempt}"


def log_growth(recorder: Recorder, growth) -> int:
    """Log a cluster's :class:`sfm.mapper.growth.Growth` (module docstring), each entity's steps
    in one call; returns how many of its images no model holds."""
    if not recorder.enabled:
        return sum(1 for _ in _left_out(growth))
    import rerun as rr

    recorder.stage("map")
    label = growth.label
    for attempt, model in enumerate(growth.models):
        if not model.steps:
            continue
        prefix = model_prefix(label, model.rank, attempt, model.absorbed, bool(model.taken_apart))
        times = [step.num_registered for step in model.steps]
        poses: dict[int, list] = {}  # image -> [(time, R, t)]
        for step in model.steps:
            for i, R, t in zip(step.posed.tolist(), step.rotations, step.translations):
                poses.setdefault(i, []).append((step.num_registered, R, t))
        for i, rows in poses.items():
            rotations = np.array([R for _, R, _ in rows], dtype=np.float64)
            translations = np.array([t for _, _, t in rows], dtype=np.float64)
            recorder.send_columns(f"{prefix}/cams/{entity_part(growth.names[i])}", "registration", [r[0] for r in rows],
                                  rr.Transform3D.columns(translation=world_centres(rotations, translations),
                                                         quaternion=world_quaternions(rotations)))
        first = model.steps[min(len(model.steps), 3) - 1]  # frustums sized by the young model
        first_centres = world_centres(first.rotations.astype(np.float64), first.translations.astype(np.float64))
        depth = frustum_depth(first.points, first_centres)
        for step in model.steps:
            recorder.set_time("registration", step.num_registered)
            for i in step.new:
                width, height = growth.sizes[i]
                log_frustum(recorder, f"{prefix}/cams/{entity_part(growth.names[i])}", growth.names[i], growth.K[i],
                            int(width), int(height), depth)
        lengths = [len(step.points) for step in model.steps]
        points = np.concatenate([step.points for step in model.steps]).reshape(-1, 3)
        colors = np.concatenate([step.colors for step in model.steps]).reshape(-1, 3)
        recorder.send_columns(f"{prefix}/points", "registration", times,
                              rr.Points3D.columns(positions=points, colors=colors).partition(lengths))
        rms = [(k, step.ba_rms_px) for k, step in zip(times, model.steps) if np.isfinite(step.ba_rms_px)]
        if rms:
            recorder.send_columns(f"{prefix}/ba_rms_px", "registration", [k for k, _ in rms],
                                  rr.Scalars.columns(scalars=[x for _, x in rms]))
        if model.calibration:
            recorder.log(f"{prefix}/calibration", rr.TextDocument(calibration_text(model.calibration),
                                                                  media_type=rr.MediaType.MARKDOWN))
        if model.taken_apart:
            recorder.log(f"{prefix}/taken_apart", rr.TextDocument(model.taken_apart, media_type=rr.MediaType.MARKDOWN))
        if model.joins:
            recorder.log(f"{prefix}/joins", rr.TextDocument("\n".join(f"- {line}" for line in model.joins),
                                                            media_type=rr.MediaType.MARKDOWN))
        if model.unjoined:
            lines = [f"- the finished model of {growth.models[k].size} images: {why}" for k, why in model.unjoined.items()]
            recorder.log(f"{prefix}/unjoined", rr.TextDocument("Earlier models that did not join this one as a "
                                                               "whole, and why:\n\n" + "\n".join(lines),
                                                               media_type=rr.MediaType.MARKDOWN))
    recorder.clear_time("registration")
    left_out = list(_left_out(growth))
    lines = [f"| {name} | {reason} |" for name, reason in left_out]
    text = (f"**{label}**: every one of its {len(growth.names)} images is in a model." if not lines else
            f"**{label}**: {len(lines)} of its {len(growth.names)} images are in no model.\n\n"
            "| image | why (the largest model's view) |\n|---|---|\n" + "\n".join(lines))
    recorder.log(f"clusters/{label}/unregistered", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN))
    if label not in recorder.views["clusters"]:
        recorder.views["clusters"].append(label)
    return len(left_out)


def calibration_text(lines: list[str]) -> str:
    """Markdown of a model's self-calibration decisions (``sfm.mapper.self_calibration.SelfCalibration.report``)."""
    return ("What the final bundle adjustments refined of each camera (`sfm.mapper.distortion`, "
            "`sfm.mapper.principal_point`):\n\n" + "\n".join(f"- {line}" for line in lines))


def _left_out(growth):
    """``(name, reason)`` of the images in no kept model, the reason :meth:`Growth.left_out` gives."""
    kept = set()
    for model in growth.models:
        if model.rank >= 0:
            kept |= {growth.names[i] for i in model.registered.tolist()}
    reasons = growth.left_out()
    for name in growth.names:
        if name not in kept:
            yield name, reasons[name]


def log_local_model(recorder: Recorder, label: str, m: int, model, growth_logged: bool = False) -> None:
    """A local model as written (``clusters/<C>/model<m>``), for clusters whose growth was not
    recorded (finished by an earlier run)."""
    if not recorder.enabled or growth_logged:
        return
    recorder.stage("map")
    log_model(recorder, model_prefix(label, m, m), model, max_points=recorder.options.record_points)
    if label not in recorder.views["clusters"]:
        recorder.views["clusters"].append(label)


def log_cluster_error(recorder: Recorder, label: str, names: list[str], error: str) -> None:
    """``clusters/<C>/error``: why a cluster failed (its images are left out of the run)."""
    if not recorder.enabled:
        return
    import rerun as rr

    recorder.stage("map")
    recorder.log(f"clusters/{label}/error", rr.TextDocument(
        f"**{label} failed** ({len(names)} images, left out of this run; the next run tries it again):\n\n"
        f"`{error}`", media_type=rr.MediaType.MARKDOWN))
