"""Rerun logging: every stage of a run is visible in one recording.

A :class:`Recorder` wraps one ``rerun.RecordingStream`` that is saved to a file in the
workspace and never needs a viewer or a network (``spawn=True`` also opens a viewer when one is
installed).  ``graphsfm reconstruct`` writes ``WORK/recording.rrd``; a single stage command
writes ``WORK/recording-<stage>.rrd``.  All files of a workspace share one recording id (derived
from the workspace path), so ``rerun WORK/*.rrd`` shows them as one recording.

The ``stage`` sequence timeline has a fixed value per stage (:data:`STAGES`), so data logged by
separate commands lines up.  Entity paths (the ``sfm.viz`` package docstring lists them):
``images/<name>``, ``graph/images``, ``graph/clusters``, ``clusters/C<k>/...``, ``merge/...``,
``world/...``; ``graphsfm extend`` adds ``extend/E<k>`` (the new clusters' models in the
model's frame) and ``graph/clusters/extend`` (their merge tree onto the model).
A disabled recorder (``Recorder.disabled()``) accepts every call and does nothing.
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

STAGES = {"extract": 1, "match": 2, "cluster": 3, "map": 4, "merge": 5, "refine": 6, "extend": 7}


def cluster_color(k: int) -> tuple[int, int, int]:
    """A distinct, stable colour per cluster id (golden-ratio hue steps)."""
    import colorsys

    r, g, b = colorsys.hsv_to_rgb((k * 0.618033988749895) % 1.0, 0.75, 0.95)
    return int(255 * r), int(255 * g), int(255 * b)


class Recorder:
    """One Rerun recording saved to ``path`` (``None``: disabled, every call is a no-op).

    The stream opens in a background thread; the first call that needs it waits for it and
    raises what opening it raised (e.g. the ``rerun`` import failing)."""

    def __init__(self, path: Path | None, workspace: Path | None = None, spawn: bool = False) -> None:
        self.path = Path(path) if path is not None else None
        self._rec = None
        self._error: BaseException | None = None
        self._opening: threading.Thread | None = None
        if self.path is None:
            return
        # Opening the stream imports the Rerun SDK, which takes a while: a thread does it while
        # the caller goes on (extraction and matching log nothing); the first use waits for it.
        self._opening = threading.Thread(target=self._open, args=(workspace, spawn), daemon=True)
        self._opening.start()

    def _open(self, workspace: Path | None, spawn: bool) -> None:
        try:
            import rerun as rr

            key = str(Path(workspace or self.path.parent).resolve())
            recording_id = str(uuid.uuid5(uuid.NAMESPACE_URL, "graphsfm:" + key))
            rec = rr.RecordingStream("graphsfm", recording_id=recording_id)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(str(self.path))
            self._rec = rec
        except BaseException as exc:  # noqa: BLE001 - raised again by the first use
            self._error = exc
            return
        if spawn:
            try:
                self._rec.spawn(connect=False)  # also stream to a viewer if one is installed
            except Exception as exc:  # noqa: BLE001 - a missing viewer must not stop a run
                log.warning("could not start the Rerun viewer (%s); recording to %s only", exc, self.path)

    def _stream(self):
        """The recording stream once it is open (None when disabled or closed)."""
        if self._opening is not None:
            self._opening.join()
            self._opening = None
            if self._error is not None:
                raise self._error
        return self._rec

    @classmethod
    def disabled(cls) -> Recorder:
        return cls(None)

    @property
    def enabled(self) -> bool:
        return self._stream() is not None

    def stage(self, name: str) -> None:
        """Move the ``stage`` timeline to the stage's fixed position."""
        if (rec := self._stream()) is not None:
            rec.set_time("stage", sequence=STAGES[name])

    def set_time(self, timeline: str, sequence: int) -> None:
        if (rec := self._stream()) is not None:
            rec.set_time(timeline, sequence=int(sequence))

    def log(self, entity: str, *archetypes, static: bool = False) -> None:
        if (rec := self._stream()) is not None:
            rec.log(entity, *archetypes, static=static)

    def close(self) -> None:
        if (rec := self._stream()) is not None:
            rec.flush()
            rec.disconnect()
            self._rec = None

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ graph views
    def log_image_graph(self, names: Sequence[str], edges_i: np.ndarray, edges_j: np.ndarray,
                        weights: np.ndarray, cluster_of: Sequence[int] | None = None) -> None:
        """``graph/images``: one node per image (coloured by cluster when given), one edge per
        verified pair (its weight, the number of inliers, is in the node-less edge list order)."""
        if not self.enabled:
            return
        import rerun as rr

        colors = None if cluster_of is None else [cluster_color(k) if k >= 0 else (128, 128, 128) for k in cluster_of]
        self.log("graph/images", rr.GraphNodes(list(names), labels=list(names), colors=colors, show_labels=False),
                 rr.GraphEdges([(names[a], names[b]) for a, b in zip(edges_i, edges_j)], graph_type="undirected"))
        self.log("graph/images/weights", rr.AnyValues(inliers=np.asarray(weights, dtype=np.float64)))

    def log_cluster_graph(self, sizes: Sequence[int], tree_edges: Sequence[tuple[int, int]],
                          anchor: int | None = None, entity: str = "graph/clusters") -> None:
        """``graph/clusters``: one node per cluster labelled with its size, the tree's edges
        (MaxST after clustering, MinST after merging); the anchor, if any, is drawn larger."""
        if not self.enabled:
            return
        import rerun as rr

        ids = [f"C{k}" for k in range(len(sizes))]
        labels = [f"C{k} ({s})" + (" anchor" if k == anchor else "") for k, s in enumerate(sizes)]
        radii = [12.0 if k == anchor else 6.0 for k in range(len(sizes))]
        self.log(entity, rr.GraphNodes(ids, labels=labels, colors=[cluster_color(k) for k in range(len(sizes))], radii=radii),
                 rr.GraphEdges([(f"C{a}", f"C{b}") for a, b in tree_edges], graph_type="undirected"))


def log_model(recorder: Recorder, prefix: str, recon) -> None:
    """``<prefix>/points`` (coloured) and ``<prefix>/cams/<name>`` (Transform3D + Pinhole) of a
    :class:`sfm.core.model.Reconstruction`."""
    if not recorder.enabled:
        return
    import rerun as rr

    if recon.points3D:
        xyz = np.array([p.xyz for p in recon.points3D.values()])
        rgb = np.array([p.color for p in recon.points3D.values()])
        recorder.log(f"{prefix}/points", rr.Points3D(xyz, colors=rgb))
    for image in recon.images.values():
        cam = recon.cameras[image.camera_id]
        log_camera(recorder, f"{prefix}/cams/{image.name}", image.cam_from_world_rotation,
                   image.cam_from_world_translation, cam.K, cam.width, cam.height)


def log_camera(recorder: Recorder, entity: str, rotation: np.ndarray, translation: np.ndarray,
               K: np.ndarray, width: int, height: int) -> None:
    """A camera given ``cam_from_world`` as Transform3D (world_from_cam) + Pinhole."""
    if not recorder.enabled:
        return
    import rerun as rr

    from backend.geometry import rotation_to_quaternion

    world_from_cam = rotation.T
    q = rotation_to_quaternion(world_from_cam)
    recorder.log(entity, rr.Transform3D(translation=-world_from_cam @ translation, quaternion=[q[1], q[2], q[3], q[0]]),
                 rr.Pinhole(image_from_camera=K, resolution=[width, height]))


def entity_paths(rrd_path: Path) -> set[str]:
    """Entity paths logged in an ``.rrd`` file (for tests and checks)."""
    from rerun.chunk import RrdReader

    return {str(chunk.entity_path) for chunk in RrdReader(str(rrd_path)).stream()}
