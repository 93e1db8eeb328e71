"""COLMAP's pixel convention at the file boundary.

Inside graphsfm pixel centres are at integer coordinates (OpenCV); COLMAP's files and database
put the image corner at (0, 0).  Keypoints and principal points are shifted by +0.5 when
written and -0.5 when read, here and nowhere else.
"""

from __future__ import annotations

import numpy as np

from backend.camera_models import model_spec

#: What COLMAP's pixel coordinates add to graphsfm's.
COLMAP_OFFSET = 0.5


def params_to_colmap(model: str, params: np.ndarray) -> np.ndarray:
    """Internal (pixel centres at integers) -> COLMAP (corner at 0, 0): principal point + 0.5."""
    out = np.array(params, dtype=np.float64, copy=True)
    out[list(model_spec(model).pp_idx)] += COLMAP_OFFSET
    return out


def params_from_colmap(model: str, params: np.ndarray) -> np.ndarray:
    """COLMAP (corner at 0, 0) -> internal (pixel centres at integers): principal point - 0.5."""
    out = np.array(params, dtype=np.float64, copy=True)
    out[list(model_spec(model).pp_idx)] -= COLMAP_OFFSET
    return out
