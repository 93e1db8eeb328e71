"""Merging the local models into one frame, and the refinement of the merged model.

The second half of paper section 3.2 and Algorithm 2, then the end of Figure 1: the local
models of the clusters, each in its own frame and scale, are stitched along the most accurate
similarity transformations into the frame of one anchor cluster, and the merged model is
re-triangulated and bundle-adjusted once.  The ``merge`` stage (``sfm.stages.merge``) reads
the local models from ``WORK/clusters`` and writes ``WORK/sparse/N`` and ``WORK/merge.json``.

Design:

- Cluster graph (Alg. 2, line 1; section 3.2.1): every pair of local models that share at
  least ``min_common_cameras`` (2) registered images gets a similarity from those cameras
  (``backend.similarity``): the relative scale as a median of camera-distance ratios (Eq. 1-2),
  then rotation and translation by RANSAC with the scale known (Eq. 3-6).
- Edge weights (section 3.2.2): the MSD of Eq. 11, the larger of the two directions' MSE of
  Eq. 10, over the common 3D points (observed through the same keypoint of a common image) and
  the inlier camera centres.  The MinST's weights should be ``-log p_ij`` (Eq. 7-9), but only
  their order decides the tree, and the MSD orders the edges by how well the models agree.
  Edges whose MSD is above ``max_msd`` are dropped (the paper's dotted edges, Figure 3).
- Merge plan (section 3.2.3, Alg. 2, lines 2-12; ``graph.merge_plan``): the Kruskal MinST,
  then the anchor as the root of a minimum height tree, found by peeling leaves layer by layer
  (of two left, the larger cluster).  Every model is moved into the anchor's frame by the
  similarities composed along its tree path; an image registered in several models keeps the
  pose of the model nearest the anchor, a camera the parameters of the model that registered
  most of its images.
- Bridges (a departure; ``sfm.merge.bridging``): when the cluster graph falls into parts, each
  part is aligned in its anchor's frame and registered to another part as one rigid body from
  the rays between them (a part's photos seeing the other's points), on PnP's terms, by the
  estimate that joins models within a cluster (``sfm.mapper.joining``); the bridge becomes an
  edge between the parts' anchors, weighted after every edge from common cameras, and the plan
  is made again.
- Refinement (Figure 1 and the end of section 3's overview: re-triangulation and BA "can be
  executed alternatively until convergence"; its self-calibration decided again on all the
  photos, not kept from the clusters): the merged model starts from the local models'
  own points, moved by the same similarities (Alg. 2's ``C_final`` holds the clusters' points
  as well as their cameras; a track takes the point that the most of its observations saw in
  one model, with the observations that model kept), the other tracks are triangulated with the merged poses, then
  global BA and filtering alternate with re-triangulation until it changes at most COLMAP's
  0.0005 of the observations (at most five BAs).  Starting from the clusters' points, not
  from a triangulation, matters where a cluster's self-calibration differs from the pooled
  one: its poses fit its own calibration, a triangulation with the pooled one rejects the
  rows that join it to the others before any BA could reconcile them, and the parts then
  meet in too few tracks for the BA to close the loop.  The paper finds one round enough;
  clusters joined through thin overlaps need more, because similarity-moved poses make the
  first triangulation reject observations that the first BA brings back.  Then the photos no
  local model holds (a cluster whose local SfM found no initial pair, or images its model could
  not take) are registered in the merged model as incremental SfM registers an image, PnP on
  the points they see, and the model is refined again: the paper leaves them out.
- Departures: the MSD is normalised by the common cameras' extent so weights compare across
  pairs of models of different scales; the relative scale's median is anchored at each RANSAC
  hypothesis (robust to up to half the common cameras being wrong) and the rotation comes from
  the cameras' orientations; parts of the cluster graph are bridged (above), and every part
  still apart becomes its own model (``sparse/0``, ``sparse/1``, ..., largest first), where
  the authors' public code merges only the largest.

Modules, in reading order:

- ``sfm.merge.options``: ``MergeOptions`` (``max_msd``, ``min_common_cameras``).
- ``sfm.merge.cluster_graph``: the cluster graph's edges (similarity and MSD) and the merge plan.
- ``sfm.merge.alignment``: every model in its anchor's frame, and the merged poses and cameras.
- ``sfm.merge.bridging``: parts of the cluster graph joined from the rays between them.
- ``sfm.merge.refinement``: re-triangulation and global BA of the merged poses, and the
  registration of the photos no local model holds.
- ``sfm.merge.extension``: new images' local models merged into a finished model held as the
  anchor (Alg. 2 with the anchor given), and the BA of the new part (``graphsfm extend``).
- ``sfm.merge.options`` also holds ``ExtendOptions`` (``full_ba``).

Paper: section 3.2 (3.2.1 Eq. 1-6, 3.2.2 Eq. 7-11, 3.2.3), Algorithm 2, Figures 1 and 3.
"""
