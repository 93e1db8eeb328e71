"""Synthetic scenes with exact ground truth, for tests, benchmarks and the demo, at any size.

Two kinds.  Correspondence-level scenes (``orbit``: a ring of cameras around an object;
``street``: a camera moving forward between two facades; ``aerial``: a nadir grid over hills)
have no images: cameras, points and noisy keypoints are generated and matching is simulated,
straight into a COLMAP-schema database, so ``cluster``, ``map`` and ``merge`` can be exercised
on thousands of images without a front end.  Rendered scenes are real images: ``rendered``, a facade of
textured planes photographed from an arc (PNG), for end-to-end tests of ``extract`` and ``match``
without downloads; ``survey``, a drone survey of a town on gentle hills (JPEG with EXIF focal
length and GPS), nadir and oblique, at any size, rendered photo by photo in worker processes
and resumable, for benchmarks of the whole pipeline on large aerial captures.

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
- ``sfm.synthetic.survey``: the rendered drone survey: flight plan, terrain, buildings, ray
  casting, band-limited texture, EXIF and ground truth.

Paper: none; the scenes stand in for the kinds of data section 4 evaluates (object-centred,
street and large aerial captures).
"""
