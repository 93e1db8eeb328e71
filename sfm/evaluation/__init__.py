"""Evaluation: the accuracy of a reconstruction's cameras against ground-truth poses.

``graphsfm evaluate MODEL --gt TABLE``, the demo, the tests and the benchmark scripts all score
a model the same way, with this room.  Ground truth is a GT table (one line per image:
``IMAGE_NAME WIDTH HEIGHT FX FY CX CY QW QX QY QZ TX TY TZ``, OpenCV pixels, ``cam_from_world``)
or a reference COLMAP model; images are matched by name.

Design (the project's one rule for pose accuracy):

- Registration: the share of GT images the model registered.
- Absolute errors, after a robust similarity ``gt_from_est``: RANSAC over 3-point Umeyama fits
  on the camera centres picks the inliers, scale and translation, and the rotation is the
  geodesic median of the inliers' orientation offsets (the centres alone leave a roll free
  when they are nearly collinear).  Per image: the rotation error in degrees and the centre
  error divided by the scene's extent (the largest distance between two GT centres).
- Relative-pose AUC, which needs no alignment: for every GT pair, the error is the larger of
  the relative rotation error and the angle between the relative translation directions, in
  degrees; a pair with an unregistered image has an infinite error.  ``AUC@X`` is the area under
  the recall-versus-error curve up to X degrees, divided by X (trapezoids), over all GT pairs
  (as SuperGlue, LightGlue and hloc report it), at 1, 5 and 10 degrees by default.
- Angles come from ``atan2`` forms, never ``arccos``, so equal poses give errors at rounding
  level; the N(N-1)/2 pairs are streamed in blocks, so thousands of images fit in memory.

Modules, in reading order:

- ``sfm.evaluation.ground_truth``: ``GTPose``, GT tables and GT taken from a model.
- ``sfm.evaluation.alignment``: the robust Sim3 alignment of centres, scene extent, collinearity.
- ``sfm.evaluation.metrics``: ``evaluate``, relative-pose errors, ``auc``, ``EvaluationResult``.
- ``sfm.evaluation.options``: ``EvaluateOptions`` of ``graphsfm evaluate``.

Paper: none of its equations; its experiments (section 4) report registered cameras, points,
reprojection errors and times, which ``report.json`` holds.  Pose accuracy against ground truth
is this project's check, for scenes with known cameras.
"""
