"""Matching: which pairs to match, descriptor matching, and two-view geometric verification.

The verified pairs are the image graph's edges and their inlier counts its weights (paper
section 3.1.1: "the weight of edges is the number of matches after geometric filtering").  The
``match`` stage (``sfm.stages.match``) selects the pairs, runs batches of them on an executor and
writes raw matches and two-view geometries into the database; this room is the work of one
pair and the choice of pairs, arrays in and arrays out.

Design:

- Pairs: every pair below ``exhaustive_threshold`` images (200); above it, retrieval: each
  image's ``top_k`` (30) most similar images by VLAD over a vocabulary learned from the
  dataset's own descriptors; optionally each image with the next N in name order (video,
  drone strips).  A pair is ``(id1, id2)`` with ``id1 < id2``.
- Descriptor matching: nearest neighbour on unit-normalised descriptors, Lowe's ratio test
  (0.8, COLMAP's) and a mutual check; approximate through an inverted file per image (the
  default where features are many: a descriptor meets only those of its cell) or exact
  (blocked BLAS, ``--matcher brute``).
- Verification, COLMAP's rules with OpenCV's USAC MAGSAC: the essential matrix when both
  cameras have a focal prior (relative pose refined on the inliers), the fundamental matrix
  otherwise, both at COLMAP's 4 px; a homography with more than 0.8 of the E or F inliers marks
  the pair planar or panoramic; fewer than ``min_num_inliers`` (15) inliers make it
  degenerate, stored so that a rerun knows it was tried.  RANSAC's iterations are sized to
  find the weakest edge that COLMAP's global mapper (GLOMAP) trusts, 30 inliers and a quarter
  of the matches; a weaker model met on the way is kept.
- Randomness comes from the seed and the pair's image names, and a pair is matched from the
  image whose name sorts first, so any number of workers, any order of pairs and any image ids
  (an extension's images come after the old ones) give the same matches.  F and H are held in OpenCV's pixel convention and converted when the
  stage writes them (``sfm.matching.verification.to_colmap_pixels``).

Modules, in reading order:

- ``sfm.matching.options``: ``MatchOptions``, the ``match`` stage's options.
- ``sfm.matching.pairs``: exhaustive, retrieval (VLAD) and sequential pairs.
- ``sfm.matching.inverted_file``: one image's inverted file, the approximate nearest neighbours.
- ``sfm.matching.descriptors``: nearest neighbours, ratio test and mutual check.
- ``sfm.matching.verification``: E, F and H by USAC, inliers, COLMAP's config codes.
- ``sfm.matching.pair_matcher``: ``PairMatcher`` and ``match_batch``, the ``match`` stage's task.

Paper: section 3.1.1 (the image graph's edges and weights); Figure 1's matching and epipolar
filtering.
"""
