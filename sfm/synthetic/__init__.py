"""Synthetic scenes with exact ground truth, for tests, benchmarks and the demo, at any size.

Two kinds.  Correspondence-level scenes (``orbit``: a ring of cameras around an object;
``street``: a camera moving forward between two facades; ``aerial``: a nadir grid over hills)
have no images: cameras, points and noisy keypoints are generated and matching is simulated,
straight into a COLMAP-schema database, so ``cluster``, ``map`` and ``merge`` can be exercised
on thousands of images without a front end.  The rendered scene is real images (PNG): a facade of textured
planes photographed from an arc, for end-to-end tests of ``extract`` and ``match`` without
downloads.

Design:

- A point is seen by the cameras whose frustum holds it, within a maximum distance and a
  maximum angle to its surface normal, so track lengths and overlaps behave like a capture's.
- Matching fails as a real front end does: raw matches are the true ones plus a share of
  random wrong ones; verification keeps a random share of the true ones and lets a few
  outliers through, near the epipolar line as RANSAC survivors are.
- Everything is seeded: the same options give the same database and images.  Ground truth is
  written as a GT table (``gt/cameras_gt_opencv.txt``, the format ``sfm.evaluation`` reads) and
  as a COLMAP model.

Modules, in reading order:

- ``sfm.synthetic.options``: ``SynthOptions``, ``RenderOptions``, ``DemoOptions``.
- ``sfm.synthetic.scenes``: the correspondence-level scenes and their ground truth.
- ``sfm.synthetic.matching``: simulated matching and verification, written into a database.
- ``sfm.synthetic.rendered``: the rendered facade and its ground truth.

Paper: none; the scenes stand in for the kinds of data section 4 evaluates (object-centred,
street and large aerial captures).
"""
