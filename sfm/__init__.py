"""graphsfm's application: images in, cameras and a 3D point cloud out (GraphSfM, paper Figure 1).

``sfm.reconstruct(images, workspace, **options)`` runs every stage, ``sfm.extend(workspace,
images, **options)`` adds new photos to a finished model; ``sfm.run_extract``,
``run_match``, ``run_cluster``, ``run_map`` and ``run_merge`` run one each (``sfm.api``).  The
command line (``sfm.cli``) is the same functions behind flags, and the program ``graphsfm``
(``sfm.__main__``) runs it in a supervised child process.

The rooms, one concept each, in layers, lowest first.  A module imports only from its own room
or from a lower layer (``tests/test_layering.py`` checks it, and that nothing anywhere imports
in a cycle):

    0. sfm.errors, sfm.core
    1. sfm.io
    2. sfm.viz, sfm.execution
    3. sfm.features, sfm.matching, sfm.clustering, sfm.evaluation, sfm.synthetic
    4. sfm.mapper
    5. sfm.merge
    6. sfm.stages, sfm.console
    7. sfm.api, sfm.cli
    8. sfm.__main__

- ``core``: the data model (cameras, images, points with tracks), rigid geometry, the options
  machinery every stage's options use.
- ``io``: COLMAP's model files and database, the workspace's JSON files and run ledger, image
  files (finding, EXIF, decoding).
- ``viz``: the Rerun recording.  ``execution``: where parallel tasks run (process pool, Dask).
- ``features`` (SIFT), ``matching`` (pairs, descriptors, two-view verification),
  ``clustering`` (Alg. 1 on the image graph), ``evaluation`` (accuracy against ground truth),
  ``synthetic`` (scenes with exact ground truth).
- ``mapper``: incremental SfM of one cluster (section 3.2).  ``merge``: the cluster graph, the
  merge plan and the refinement of the merged model (section 3.2, Alg. 2).
- ``stages``: one module per stage (``extract``, ``match``, ``cluster``, ``map``, ``merge``,
  ``reconstruct``, ``extend``, ``synth``, ``demo``), the only code that writes the workspace.
  ``console``: what a command shows on the terminal and keeps in ``WORK/log.txt``.
- ``graph`` and ``backend`` (top-level packages beside ``sfm``) are array libraries: the graph
  algorithms (NCut, MaxST expansion, MinST, minimum-height tree) and the numerical optimisation
  (GTSAM bundle adjustment, Sim3 estimation).  They never import ``sfm`` nor each other.

Conventions, everywhere:

- Poses are ``cam_from_world``: ``x_cam = R @ X + t`` (COLMAP's images.txt); the camera centre
  is ``-R.T @ t``.  GTSAM's ``Pose3`` is ``world_from_cam`` and is converted only in
  ``backend.bundle_adjustment``.  A similarity named ``b_from_a`` maps points of frame ``a``
  into frame ``b``: ``X_b = s R X_a + t``.  Variables name their frames.
- Pixels: pixel centres at integer coordinates (OpenCV).  COLMAP's files and database put the
  image corner at (0, 0): keypoints and principal points are shifted by 0.5 when written and
  read (``sfm.io``), nowhere else.
- Cameras are COLMAP camera models (``backend.camera_models``): ``SIMPLE_RADIAL`` with an
  EXIF focal prior (else 1.2 x the longer side) by default, or the ``camera_model`` asked for
  (SIMPLE_PINHOLE, PINHOLE, RADIAL, OPENCV), ``PINHOLE`` held fixed for intrinsics the user gives.
- GPS: EXIF positions are the database's WGS84 pose priors; a final model with three or more
  is georegistered into a local east-north-up frame in metres (origin in
  ``sparse/N/georegistration.json`` and ``report.json``).
- Images are named by their path relative to the image folder; integer ids are the database's.
- Randomness comes only from a ``seed`` option: the same input and seed give the same files,
  with any number of workers.

Options: each stage's options are one frozen dataclass in its room's ``options.py``
(``ExtractOptions``, ``MatchOptions``, ``ClusterOptions``, ``MapperOptions``, ``MergeOptions``;
``ExecutionOptions`` and ``RecordingOptions`` say where tasks run and whether a recording is
written).  Keyword options of the Python API and the command line's flags are their field names
(dashes for underscores); values are checked when the dataclass is built (``sfm.core.options``).

Errors a user sees are one line with an exit code (``sfm.errors``): 0 a model was written, 1 an
internal error (details in ``WORK/log.txt``), 2 bad arguments or no usable input, 3 the input
was read but no model could be made.
"""

from __future__ import annotations


def _version() -> str:
    """The installed distribution's version (pyproject.toml's, the one source); a checkout that
    is not installed reads it from the pyproject.toml beside the package."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("graphsfm")
    except PackageNotFoundError:
        import re
        from pathlib import Path

        pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
        found = re.search(r'^version\s*=\s*"([^"]+)"', pyproject.read_text(), re.M) if pyproject.is_file() else None
        return found.group(1) if found else "unknown"


__version__ = _version()

_API = ("reconstruct", "extend", "make_options", "run_extract", "run_match", "run_cluster", "run_map", "run_merge",
        "export", "info", "align",
        "ExtractOptions", "MatchOptions", "ClusterOptions", "MapperOptions", "MergeOptions", "ExecutionOptions",
        "RecordingOptions", "ExportOptions", "AlignOptions", "ExtendOptions", "Reconstruction", "read_model")


def __getattr__(name: str):
    if name in _API:
        from sfm import api

        return getattr(api, name)
    raise AttributeError(f"module 'sfm' has no attribute {name!r}")
