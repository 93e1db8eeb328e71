"""Rerun logging: every stage of a run is visible in one recording, with a guided tour.

A :class:`Recorder` wraps one ``rerun.RecordingStream`` that is saved to a file in the
workspace and never needs a viewer or a network (``spawn=True`` also opens a viewer when one is
installed).  ``graphsfm reconstruct`` writes ``WORK/recording.rrd``; a single stage command
writes ``WORK/recording-<stage>.rrd``.  All files of a workspace share one recording id (derived
from the workspace path), so ``rerun WORK/*.rrd`` shows them as one recording.

Timelines: ``stage`` has a fixed value per stage (:data:`STAGES`), so data logged by separate
commands lines up; ``registration`` counts the registered images of a growing local model (map);
``merge_layer`` the layers of the minimum height tree (merge).  ``graphsfm extend`` logs at
its own stage: ``graph/extend`` and ``extend/<model>`` (the new local models in the model's frame).  What each stage logs, entity by
entity, is in the README ("The recording"); the stage modules of ``sfm.viz`` log it.  Each stage
also logs a markdown text (:meth:`Recorder.tour`): ``tour/<n>_<stage>`` on its own and ``tour``,
the whole tour so far, which the default layout (``sfm.viz.blueprint``) shows beside the views.

A disabled recorder (``Recorder.disabled()``) accepts every call and does nothing.
"""

from __future__ import annotations

import logging
import threading
import uuid
from pathlib import Path

from sfm.viz.entities import entity_part  # noqa: F401 - re-exported
from sfm.viz.options import RecordingOptions
from sfm.viz.palette import cluster_color  # noqa: F401 - re-exported: the colour of a cluster
from sfm.viz.thumbnails import Thumbnail, thumbnail_from_file

log = logging.getLogger(__name__)

STAGES = {"extract": 1, "match": 2, "cluster": 3, "map": 4, "merge": 5, "refine": 6, "final": 7, "extend": 8}


class Recorder:
    """One Rerun recording saved to ``path`` (``None``: disabled, every call is a no-op).

    The stream opens in a background thread; the first call that needs it waits for it and
    raises what opening it raised (e.g. the ``rerun`` import failing).  The recorder also keeps
    what later views need and what the default layout shows: the images' thumbnails (made by the
    extract stage, or read from ``image_dir``), the tour's texts, the cluster labels and pairs
    that were logged."""

    def __init__(self, path: Path | None, workspace: Path | None = None, spawn: bool = False,
                 options: RecordingOptions | None = None) -> None:
        self.path = Path(path) if path is not None else None
        self.options = options or RecordingOptions()
        self.image_dir: Path | None = None
        self.thumbnails: dict[str, Thumbnail] = {}
        self.texts: dict[str, str] = {}
        self.views: dict[str, list[str]] = {"images": [], "pairs": [], "clusters": [], "world": []}
        self._rec = None
        self._stage = 0
        self._error: BaseException | None = None
        self._opening: threading.Thread | None = None
        if self.path is None:
            return
        # Opening the stream imports the Rerun SDK, which takes a while: a thread does it while
        # the caller goes on (extraction and matching log nothing); the first use waits for it.
        self._opening = threading.Thread(target=self._open, args=(workspace, spawn), daemon=True)
        self._opening.start()
        threading.Thread(target=_preload, daemon=True).start()

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

    @property
    def requested(self) -> bool:
        """Whether a recording was asked for, without waiting for the stream to open."""
        return self.path is not None and self._error is None

    # ------------------------------------------------------------------ time and logging
    def stage(self, name: str) -> None:
        """Move the ``stage`` timeline to the stage's fixed position; the stage-local timelines
        (``registration``, ``merge_layer``) are left unset until a stage sets them."""
        if (rec := self._stream()) is not None:
            rec.reset_time()
            rec.set_time("stage", sequence=STAGES[name])
            self._stage = STAGES[name]

    def set_time(self, timeline: str, sequence: int) -> None:
        if (rec := self._stream()) is not None:
            rec.set_time(timeline, sequence=int(sequence))

    def clear_time(self, timeline: str) -> None:
        """Log the next data without a time on ``timeline``."""
        if (rec := self._stream()) is not None:
            rec.disable_timeline(timeline)

    def log(self, entity: str, *archetypes, static: bool = False) -> None:
        if (rec := self._stream()) is not None:
            rec.log(entity, *archetypes, static=static)

    def send_columns(self, entity: str, timeline: str, sequence, columns) -> None:
        """Many rows of one entity in one call (``rerun.send_columns``): row k at ``sequence[k]``
        on ``timeline``, all at the current stage."""
        if (rec := self._stream()) is not None:
            import rerun as rr

            sequence = [int(x) for x in sequence]
            indexes = [rr.TimeColumn(timeline, sequence=sequence),
                       rr.TimeColumn("stage", sequence=[self._stage] * len(sequence))]
            rec.send_columns(entity, indexes=indexes, columns=columns)

    # ------------------------------------------------------------------ the tour
    def tour(self, stage: str, markdown: str) -> None:
        """The stage's text of the guided tour, at the stage's time: as ``tour/<n>_<stage>``
        and appended to ``tour``, the tour so far."""
        if not self.enabled:
            return
        import rerun as rr

        self.stage(stage)
        self.texts[stage] = markdown.strip()
        ordered = [self.texts[s] for s in sorted(self.texts, key=STAGES.__getitem__)]
        self.log(f"tour/{STAGES[stage]}_{stage}", rr.TextDocument(self.texts[stage], media_type=rr.MediaType.MARKDOWN))
        self.log("tour", rr.TextDocument("\n\n---\n\n".join(ordered), media_type=rr.MediaType.MARKDOWN))

    # ------------------------------------------------------------------ images
    def thumbnail(self, name: str) -> Thumbnail | None:
        """The thumbnail of image ``name``: kept from the extract stage, or read from
        ``image_dir`` (None when there is no image folder or the file cannot be read)."""
        if name not in self.thumbnails and self.image_dir is not None:
            thumb = thumbnail_from_file(self.image_dir / name, self.options.thumbnail_size)
            if thumb is not None:
                self.thumbnails[name] = thumb
        return self.thumbnails.get(name)

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Send the default layout (``sfm.viz.blueprint``) for what was logged, then flush."""
        if (rec := self._stream()) is not None:
            from sfm.viz.blueprint import default_blueprint

            try:
                rec.send_blueprint(default_blueprint(self), make_active=True, make_default=True)
            except Exception as exc:  # noqa: BLE001 - a layout is not worth failing a run for
                log.warning("no default layout in the recording: %s", exc)
            rec.flush()
            rec.disconnect()
            self._rec = None

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _preload() -> None:
    """Import what the graph views' layout needs (``sfm.viz.graphs``: networkx, SciPy's
    optimiser, about a second) while the run's first stages go on."""
    try:
        import networkx  # noqa: F401
        import scipy.optimize  # noqa: F401
    except ImportError:  # pragma: no cover - dependencies of graphsfm
        pass


def entity_paths(rrd_path: Path) -> set[str]:
    """Entity paths logged in an ``.rrd`` file (for tests and checks)."""
    from rerun.chunk import RrdReader

    return {str(chunk.entity_path) for chunk in RrdReader(str(rrd_path)).stream()}
