"""Whether a run writes its Rerun recording, whether a viewer opens, and how much it holds."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option


@dataclass(frozen=True)
class RecordingOptions(Options):
    """The Rerun recording of a run (``--recording/--no-recording``, ``--spawn``) and its size:
    the images' thumbnails, the pairs whose matches are drawn, the points of each growth step."""

    recording: bool = option(True, "Write the Rerun recording of every stage into the workspace.")
    spawn: bool = option(False, "Also open a Rerun viewer, when one is installed.")
    thumbnail_size: int = option(320, "Longer side, in pixels, of the images in the recording (JPEG).",
                                 min=32, max=4096)
    record_pairs: int = option(16, "Verified pairs whose inlier matches the recording draws between their "
                               "two images, spread from the most to the fewest inliers; 0 draws every pair.",
                               min=0)
    record_points: int = option(2000, "Points the recording shows of each growing local model at each "
                                "registration (a fixed sample of its tracks); final models are recorded whole.",
                                min=1)
