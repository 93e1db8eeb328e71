"""Georegistration of the final models (``WORK/sparse/N``) on the images' EXIF GPS.

The ``map`` stage (one cluster) and the ``merge`` stage call :func:`georegister_models` on their
final models before writing them: each model with at least three registered images carrying
GPS (the database's WGS84 ``pose_priors``, written by ``extract``) is moved into a local
east-north-up frame in metres (``sfm.evaluation.georegistration``).  Its folder then holds
``georegistration.json`` (the ENU origin and the fit), and ``WORK/report.json`` holds the
largest model's under ``georegistration``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from sfm.core.model import Reconstruction
from sfm.evaluation.georegistration import georegister
from sfm.io.database import Database
from sfm.io.database_schema import COORDINATES_WGS84
from sfm.mapper.options import MapperOptions

log = logging.getLogger(__name__)


def gps_by_name(db_path: Path) -> dict[str, np.ndarray]:
    """Image name -> WGS84 ``(lat, lon, alt)`` of the database's position priors."""
    with Database(db_path, readonly=True) as db:
        names = {i: r.name for i, r in db.read_images().items()}
        priors = db.read_pose_priors()
    return {names[i]: p.position for i, p in priors.items()
            if i in names and p.coordinate_system == COORDINATES_WGS84 and np.all(np.isfinite(p.position))}


def georegister_models(models: list[Reconstruction], db_path: Path, options: MapperOptions) -> list[dict | None]:
    """Georegister each model in place where its GPS allows (module docstring); per model the
    registration's JSON, or None."""
    if not options.georegister or not models:
        return [None] * len(models)
    gps = gps_by_name(db_path)
    if not gps:
        return [None] * len(models)
    out = []
    for m, model in enumerate(models):
        reg, why = georegister(model, gps, options.gps_max_error, options.seed)
        if reg is None:
            log.warning("model %d is not georegistered: %s", m, why)
        out.append(None if reg is None else reg.to_json())
    return out
