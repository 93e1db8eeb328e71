"""How many extraction workers fit in memory (the ``extract`` stage's pool size)."""

from __future__ import annotations

import logging

from backend.memory import available_memory
from sfm.execution.process_pool import usable_cores

logger = logging.getLogger(__name__)


def workers_for_memory(max_image_size: int) -> int:
    """One worker per core, but no more than memory allows: OpenCV's SIFT holds its whole
    Gaussian and DoG pyramids of the 2x-upsampled image, 6 + 5 float32 images per octave at 4
    times the input's pixels, and a third more over the smaller octaves: about 230 bytes per
    input pixel of an image shrunk to ``max_image_size`` (taken as 4:3), plus the decoded
    full-size image."""
    cores = usable_cores()
    available = available_memory()
    if available is None:
        return cores
    per_worker = 230 * 0.75 * max_image_size**2 + 300e6
    fits = max(1, int(0.8 * available // per_worker))
    if fits < cores:
        logger.info("extract: %d workers instead of %d, to fit in %.1f GB of memory", fits, cores,
                    available / 1e9)  # fmt: skip
    return min(cores, fits)
