"""Incremental SfM of one cluster: its images' matches in, one or more local models out.

The local reconstruction of paper section 3.2 ("due to the robustness to outliers, we choose
incremental SfM"; a cluster's bounded size keeps its drift small), following COLMAP's
incremental mapper, as the paper's own implementation does (section 4.1).  The ``map`` stage
(``sfm.stages.map``) builds one self-contained payload per cluster and runs
``reconstruct_incremental`` on it in a worker; ``sfm.merge`` reuses the same state and bundle
adjuster to refine the merged model.

Design, the loop (``sfm.mapper.incremental``):

1. Tracks: the verified inlier matches are joined into tracks over (image, keypoint) nodes; a
   component that would hold two keypoints of one image is rebuilt so that the wrong match
   loses against the many right ones it contradicts.
2. Initial pair: among the pairs with most inliers (``init_min_num_inliers``, 100), one that is
   not homography-dominated and whose median triangulation angle reaches
   ``init_min_tri_angle`` (16 degrees, halved up to three times when none does), reconstructed
   from its essential matrix.
3. Next image: the unregistered image that sees most triangulated points, well spread, is
   registered by PnP RANSAC (``abs_pose_min_num_inliers`` 30, ``abs_pose_min_inlier_ratio``
   0.25, ``abs_pose_max_error`` 12 px) and refined on its inliers; when PnP registers nothing,
   the structure-less fallback registers from 2D-2D matches (COLMAP 4's default behaviour).
   The first image of a camera new to the model also estimates that camera: focal length
   searched when it is a guess, refined with the pose, kept where the view determines it.
4. Triangulation of the tracks it newly sees: batched multi-view DLT with angle
   (``min_tri_angle`` 1.5 degrees), depth and reprojection (``max_reproj_error`` 4 px) checks.
   A two-view track (two keypoints with one verified match each in the whole database: no
   third image confirms it) is triangulated only in the initial pair
   (``ignore_two_view_tracks``, COLMAP's default).
5. Local BA around the new image (``local_ba_num_images`` 6; it refines the intrinsics of a
   camera only when all of that camera's registered images are free in it); a global BA, re-triangulation
   and filtering whenever the model has grown by ``global_ba_ratio`` (1.2), and after every
   image while the model is young.  A camera whose refined intrinsics leave the range a lens can
   have takes its images out of the model, and so does an image left with fewer than the three
   points that fix a pose (COLMAP's filter, which drops an image with none); such an image may
   register again.
6. When no image registers any more: final BAs to a tighter tolerance, then an earlier model of
   the cluster that shares no image with this one, but whose points its images see or the other
   way round, joins it as a whole, registered by one similarity from all the rays between the
   two (on PnP's terms), and the model grows on; otherwise a new model from the remaining
   images: several models are a result, not an error.  A model whose final BAs moved a guessed
   focal length (no EXIF) more than 3 times away, or more than the focal search's resolution
   (17%) while they find the camera beyond any lens (COLMAP's bogus camera: a principal point
   outside the image, a distortion parameter above 1), is grown again from the refined value (at
   most twice): it was grown at a focal length it rejects.  Every later model of that camera
   starts from the refined value too, and an earlier one that grew from the rejected value is
   taken apart, its images free again: joined as a whole, its poses and points made at that
   focal length would bend the model.  The final BAs pose the cameras with the points three
   images or more see (a point two images see cannot expose a wrong match; it is re-estimated
   afterwards, unless an image needs it).  They refine what the photos determine of each camera
   (``intrinsics_refinement`` "auto", the default): its distortion only when its difference from
   the nominal values is significant at 3 sigma and within a lens's range, no parameter above 1
   (held otherwise: a nadir block trades an undetermined distortion for a bent block, and a
   small model grown at a wrong focal length fits it with a distortion no lens has); its
   principal point only when its shift from the nominal value is significant at 3 sigma, its
   correlation with the other intrinsics below 0.9, and the two halves of its images, each
   adjusted alone, agree on it where each half can see the shift (held otherwise, as COLMAP
   always holds it).

Design, the data and the solver: state lives in flat numpy arrays over the track observations (per row:
image, keypoint, pixel, normalised coordinates, inlier flag), so each step is a vectorised
operation, not a loop over points.  Every BA is a GTSAM factor graph (``backend``) with a robust
loss, each observation weighed by its keypoint's detection scale; a global BA while the model
grows optimises a subset of the tracks, and a final BA too large for memory is the consensus of
BAs over random track parts (``ba_max_observations``; by default what half of the machine's
memory holds).  Defaults are COLMAP's documented ones
(OpenSfM's for ``global_ba_ratio``).

Modules, in reading order:

- ``sfm.mapper.payload``: ``MapperInput``, one cluster's self-contained input, and its cameras.
- ``sfm.mapper.options``: ``MapperOptions``, the ``map`` stage's options.
- ``sfm.mapper.incremental``: ``reconstruct_incremental``, the loop above, and the final
  refinement of each model.
- ``sfm.mapper.tracks``: tracks from pairwise matches (conflict-aware union-find).
- ``sfm.mapper.state``: ``MapperState``, the arrays and their geometry steps (triangulate,
  filter, candidates for registration, apply a BA).
- ``sfm.mapper.initialization``: choosing and reconstructing the initial pair.
- ``sfm.mapper.registration``: registering the next image by PnP.
- ``sfm.mapper.structureless``: registering an image that sees too few points for PnP.
- ``sfm.mapper.joining``: registering a finished model as a whole in the current one.
- ``sfm.mapper.triangulation``: batched DLT, triangulation angles, point refinement.
- ``sfm.mapper.bundle_adjuster``: ``BundleAdjuster``, which local, global and final BAs move
  what, and when they stop.
- ``sfm.mapper.self_calibration``: ``SelfCalibration``, what each final BA refines of each
  camera, from the two tests below and the principal point's split-sample step.
- ``sfm.mapper.distortion``: the test that decides whether a final BA refines a camera's
  distortion.
- ``sfm.mapper.principal_point``: the test that decides whether a final BA keeps a camera's
  refined principal point.
- ``sfm.mapper.output``: the model as a ``Reconstruction``, and the growing model for Rerun.

Paper: section 3.2 (local incremental SfM of each cluster, in parallel) and section 4.1
(COLMAP's incremental pipeline for the local clusters).
"""
