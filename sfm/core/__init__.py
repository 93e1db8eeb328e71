"""The data model and the options machinery that every room of ``sfm`` shares (layer 0).

The room holds the reconstruction as data (cameras, images with their poses and keypoints, 3D
points with their tracks) and the way each stage declares, checks and exposes its options.
Nothing here reads a file or runs an algorithm, and nothing imports another room of ``sfm``:
the geometry the model needs (rotations, COLMAP camera models, similarities) is
``backend``'s, shared with the array libraries.

Design:

- Data classes hold data.  ``Reconstruction`` keeps its three tables consistent (a point's
  track and the images' ``point3D_ids`` always agree) and offers the few operations every stage
  needs: add and remove observations, a subset of the images, a similarity applied to the whole
  model, reprojection errors, a summary.  Algorithms live in their own rooms and read or build a
  ``Reconstruction`` at their edges (``sfm.mapper`` works on flat arrays inside).
- Conventions (the ``sfm`` package docstring states them for every room): poses are
  ``cam_from_world`` (``x_cam = R X + t``, centre ``-R.T t``); keypoints and principal points
  put pixel centres at integer coordinates (OpenCV); a track is a list of
  ``(image_id, keypoint_index)``; ``Image.point3D_ids[k]`` is -1 when keypoint ``k`` observes
  no point; ids are the database's.
- Options: one frozen dataclass per stage, each field declared once with its default, one or
  two sentences of help and the values it allows.  The command line makes its flags from that
  declaration and the Python API its keywords, and the values are checked when the dataclass is
  built, so the three cannot drift apart and a bad value stops a run before any work starts.

Modules, in reading order:

- ``sfm.core.model``: ``Camera``, ``Image``, ``Point3D`` and ``Reconstruction``.
- ``sfm.core.options``: ``Options``, ``option()``, ``OptionError`` and the checks every
  stage's options dataclass uses.

Paper: none directly; the model is what every step of Figure 1 reads and writes.
"""
