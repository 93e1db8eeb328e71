"""Whether a run writes its Rerun recording, and whether a viewer opens."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option


@dataclass(frozen=True)
class RecordingOptions(Options):
    """The Rerun recording of a run (``--recording/--no-recording``, ``--spawn``)."""

    recording: bool = option(True, "Write the Rerun recording of every stage into the workspace.")
    spawn: bool = option(False, "Also open a Rerun viewer, when one is installed.")
