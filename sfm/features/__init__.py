"""Features: SIFT keypoints and RootSIFT descriptors of each image, and the camera each image gets.

The first step of the pipeline (paper Figure 1: "we first extract and match features"), run
by the ``extract`` stage (``sfm.stages.extract``), which reads the images and writes the
database.  This room is arrays in, arrays out: a decoded grey image becomes keypoints and
descriptors, image headers and an intrinsics file become cameras.

Design:

- Detector: OpenCV SIFT (``cv2.SIFT_create``) with COLMAP's peak and edge thresholds and the
  precise upscale of the first octave (no quarter-pixel bias).  Images whose longer side
  exceeds ``max_image_size`` (3200) are shrunk first; keypoints are mapped back to full
  resolution.  At most ``max_num_features`` (8192) keypoint locations per image, each with up
  to two orientations, the largest-scale ones: COLMAP's meaning of the option and its rule.
- Keypoints are float32 rows ``(x, y, scale, orientation)``, COLMAP's 4-column layout, with
  pixel centres at integers; the scale later weighs each observation in bundle adjustment.
  Descriptors are RootSIFT (COLMAP's default), quantised to bytes as COLMAP does.
- Cameras are COLMAP camera models: ``SIMPLE_RADIAL (f, cx, cy, k)`` with the EXIF focal prior
  (35 mm equivalent, else focal length and sensor resolution), else ``1.2 * max(W, H)``
  (COLMAP's default); images share a camera by size, EXIF make, model and focal
  (``camera_mode``).  Intrinsics given in an ``--intrinsics`` file
  (``IMAGE_NAME W H FX FY CX CY`` lines, ``*`` for every image) make ``PINHOLE`` cameras, held
  fixed unless ``refine_given_intrinsics``.

Modules, in reading order:

- ``sfm.features.options``: ``ExtractOptions``, the ``extract`` stage's options.
- ``sfm.features.extraction``: ``extract_features``: one image's keypoints and descriptors, and
  the conventions above in full.
- ``sfm.features.sift``: which SIFT keypoints are kept, descriptor bytes, keypoint scales.
- ``sfm.features.cameras``: the intrinsics file, EXIF priors and camera grouping.
- ``sfm.features.worker_memory``: how many extraction workers fit in memory (SIFT's pyramids).

Paper: Figure 1's feature extraction; section 4.1 (the paper uses VLFeat's SIFT; graphsfm uses
OpenCV's with COLMAP's settings).
"""
