"""The Rerun recording: every stage of a run made visible, in one file in the workspace.

A run writes one recording, ``WORK/recording.rrd`` (a single stage command writes
``WORK/recording-<stage>.rrd``; all files of a workspace share one recording id, so
``rerun WORK/*.rrd`` shows them together).  It never needs a viewer or a network;
``--spawn`` also opens a viewer when one is installed, and ``--no-recording`` writes none.
Stages log through a ``Recorder``; a disabled one accepts every call and does nothing, so the
code that logs never asks whether a recording is wanted.

Design:

- Timelines: ``stage`` has a fixed value per stage (extract 1, match 2, cluster 3, map 4,
  merge 5, refine 6), so data logged by separate commands lines up; ``registration`` counts
  the images of a growing local model; ``merge_layer`` is the peeling layer of Alg. 2.
- Entity paths: ``images/<name>`` (thumbnail and keypoints, by the ``extract`` command),
  ``graph/images`` (the verified image graph, nodes coloured by cluster once clustered),
  ``graph/clusters`` (the cluster graph with the MaxST after clustering; with the MinST and the
  anchor after merging, ``graph/clusters/merge...``), ``clusters/C<k>/points`` and
  ``clusters/C<k>/cams/<name>`` (a local model, growing image by image, then as written),
  ``merge/<model>/...`` (each local model moved into its anchor's frame), ``world/points`` and
  ``world/cams/<name>`` (the final model; ``world/model<k>`` for the others).
- Cameras are logged as ``Transform3D`` (``world_from_cam``, converted from the model's
  ``cam_from_world``) with a ``Pinhole``.  Tests read the ``.rrd`` back and check what was logged.

Modules, in reading order:

- ``sfm.viz.recorder``: ``Recorder``, the graph views, ``log_model`` and ``log_camera``.
- ``sfm.viz.frontend``: the views of the front-end stages (thumbnails, the verified graph).
- ``sfm.viz.options``: ``RecordingOptions`` (``--recording``, ``--spawn``).

Paper: the graph views show the objects of Figure 2 (image graph, clusters, MaxST) and
Figure 3 (MinST, anchor, the merge layers).
"""
