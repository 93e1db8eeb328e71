"""The numerical library: geometry, COLMAP camera models, similarities and bundle adjustment.

An array library: it takes and returns numpy arrays and small frozen dataclasses, and never
imports ``sfm`` or ``graph``, so each piece can be tested and reused alone.  ``sfm`` adapts its
data model to these interfaces (a bundle adjustment is a BAL-style problem: per-camera
parameters, poses, points and observation index arrays).

Design:

- Poses are ``cam_from_world`` (``x_cam = R X + t``, OpenCV axes: x right, y down, z
  forward), the camera centre ``C = -R.T t``; GTSAM's ``Pose3`` of a camera is
  ``world_from_cam`` and is converted in ``backend.bundle_adjustment`` only, one function each
  way.  A similarity named ``b_from_a`` maps ``X_b = s R X_a + t``.  The pixel convention is
  the caller's, as long as principal points and observations agree (graphsfm: pixel centres at
  integers).
- Cameras are COLMAP's models (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV), each
  held in bundle adjustment as an exact GTSAM ``Cal3DS2`` (or ``Cal3Bundler``), one calibration
  variable per camera group.
- Bundle adjustment is a GTSAM factor graph: a projection factor per observation under a robust
  loss (Huber by default; an observation's sigma can scale it), Levenberg-Marquardt (or
  Gauss-Newton while every step lowers the cost) with the points eliminated first (the cameras in
  METIS's order of their co-visibility graph on large problems), and the
  gauge fixed by priors on one pose and on the scale, or by the held poses.  Intrinsics are
  refined per group when asked.  Too many observations for memory: the consensus of BAs over
  random track parts; a growing model: a well-spread subset of the tracks.
- Similarity between two local models from their common cameras: the relative scale as a
  median of distance ratios anchored at each RANSAC hypothesis, the rotation and translation
  from a single camera, refit on the inliers; the MSD edge weight normalised by the cameras'
  extent.

Modules, in reading order:

- ``backend.geometry``: rotations and quaternions, angles, projection onto SO(3), look-at poses.
- ``backend.sim3``: ``Sim3`` (``b_from_a``) and Umeyama's least-squares similarity.
- ``backend.camera_models``: COLMAP camera models: layouts, projection, reprojection errors.
- ``backend.similarity``: ``estimate_similarity`` and the MSD between two local models
  (section 3.2.1, Eq. 1-6; section 3.2.2, Eq. 10-11).
- ``backend.ba_problem``: ``BAProblem``, ``BAOptions``, ``BAResult``.
- ``backend.bundle_adjustment``: ``bundle_adjust``, the factor graph.
- ``backend.calibration_step``: what a BA would do to the calibration, and how well the data
  determine it, without running it (the self-calibration tests read it).
- ``backend.gtsam_solver``: robust noise, the optimisers, their ordering, stopping rules and
  why they stopped, and GTSAM's printing kept off the terminal.
- ``backend.track_subset``: which tracks a growing model's global BA needs.
- ``backend.partitioned_ba``: a BA too large for memory, as a consensus of BAs over parts.
- ``backend.memory``: giving freed heap memory back to the system between large steps.
- ``backend.bal``: reading BAL ("Bundle Adjustment in the Large") problems, for benchmarks.

Paper: sections 3.2.1-3.2.2 (the similarity and its weight) and the bundle adjustments of
local SfM (section 3.2) and after merging (Figure 1).
"""
