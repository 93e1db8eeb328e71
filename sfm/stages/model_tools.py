"""What to do with a model once made: export it, summarise it, align it (``graphsfm export``,
``info``, ``align``; ``sfm.export``, ``sfm.info``, ``sfm.align``).

- :func:`export`: a COLMAP folder (txt, bin), a PLY (colours and normals), undistorted images and
  a PINHOLE model (``sfm.io.undistort``), or nerfstudio's ``transforms.json``
  (``sfm.io.nerfstudio``); the format from the output's extension when not given; an existing
  output is an :class:`InputError` unless ``overwrite``.
- :func:`info`: COLMAP's model_analyzer (``sfm.evaluation.model_info``).
- :func:`align`: COLMAP's model_aligner: onto GPS (a database's pose priors or an image folder's
  EXIF) into a local east-north-up frame in metres, or onto a table of reference centres, with
  the robust Sim3 of ``sfm.evaluation.georegistration``.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np

from sfm.core.model import Reconstruction
from sfm.core.options import OptionError, options_from, unknown_names
from sfm.errors import InputError
from sfm.evaluation.georegistration import georegister, model_centers_and_up, register_to_reference
from sfm.evaluation.model_info import model_info
from sfm.evaluation.options import AlignOptions
from sfm.io.colmap_model import read_model, write_model, write_ply
from sfm.io.image_files import BadImageError, probe_image
from sfm.io.nerfstudio import write_nerfstudio
from sfm.io.options import ExportOptions, format_from_path
from sfm.io.undistort import export_undistorted
from sfm.io.workspace import read_georegistration, write_georegistration
from sfm.stages.georegister import gps_by_name


def _options(cls, values: dict):
    """``cls`` from keyword options; a name it does not have is an :class:`OptionError`."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(values) - known
    if unknown:
        raise OptionError(sorted(unknown)[0], f"unknown option {unknown_names(unknown, known)}")
    return options_from(cls, values)


def _model(path: str | Path) -> Reconstruction:
    """The model at ``path``; a missing or unreadable one is an :class:`InputError`."""
    model = Path(path)
    if not model.exists():
        raise InputError(f"model not found: {model}")
    try:
        return read_model(model)
    except (FileNotFoundError, ValueError) as exc:
        raise InputError(str(exc)) from exc


def _free(out: Path, overwrite: bool) -> None:
    if out.exists() and not overwrite:
        raise InputError(f"{out} exists; choose another output or pass --overwrite to replace it")


def export(model: str | Path, out: str | Path, images: str | Path | None = None,
           options: ExportOptions | None = None, **values) -> dict:
    """Write the model at ``model`` as ``options.to`` (``ExportOptions``; default: from ``out``'s
    extension): a COLMAP folder (txt, bin), a PLY, undistorted images and a PINHOLE model
    (``images``: the model's image folder, required), or nerfstudio's ``transforms.json``
    (frames pointing into ``images`` when given).  An existing ``out`` is an :class:`InputError`
    unless ``overwrite``.  Returns what was written."""
    options = options or _options(ExportOptions, values)
    out = Path(out)
    to = options.to or format_from_path(out)
    if to == "undistorted" and images is None:
        raise InputError("--to undistorted needs --images DIR, the folder of the model's images")
    _free(out, options.overwrite)
    recon = _model(model)
    summary: dict = {"to": to, "out": str(out)}
    if to == "ply":
        out.parent.mkdir(parents=True, exist_ok=True)
        write_ply(recon, out)
        summary["points"] = len(recon.points3D)
    elif to == "nerfstudio":
        path = out if out.suffix.lower() == ".json" else out / "transforms.json"
        summary.update(write_nerfstudio(recon, path, Path(images) if images is not None else None))
    elif to == "undistorted":
        for stale in (out / "images", out / "sparse"):
            shutil.rmtree(stale, ignore_errors=True)
        summary.update(export_undistorted(recon, Path(images), out))
    else:
        write_model(recon, out, fmt=to)
        write_georegistration(out, read_georegistration(Path(model)))
        summary.update({"images": len(recon.registered_image_ids), "points": len(recon.points3D)})
    return summary


def info(model: str | Path) -> dict:
    """A summary of the model at ``model`` (``sfm.evaluation.model_info``; COLMAP's model_analyzer)."""
    return model_info(_model(model), read_georegistration(Path(model)))


def _reference_table(path: Path) -> dict[str, list[float]]:
    """``IMAGE_NAME X Y Z`` lines (COLMAP's model_aligner reference); ``#`` lines skipped."""
    if not path.is_file():
        raise InputError(f"reference table not found: {path}")
    table = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        try:
            values = [float(v) for v in tokens[1:]]
        except ValueError:
            values = []
        if len(values) != 3:
            raise InputError(f"{path}:{lineno}: expected 'IMAGE_NAME X Y Z'")
        table[tokens[0]] = values
    return table


def _gps_source(source: Path, names: list[str]) -> dict:
    """Image name -> (lat, lon, alt): a database's pose priors, or an image folder's EXIF."""
    if source.is_file():
        return gps_by_name(source)
    if not source.is_dir():
        raise InputError(f"GPS source not found: {source} (a database.db or the image folder)")
    gps = {}
    for name in names:
        try:
            found = probe_image(source / name).gps if (source / name).is_file() else None
        except BadImageError:
            found = None
        if found is not None:
            gps[name] = np.array(found)
    return gps


def align(model: str | Path, out: str | Path, gps: str | Path | None = None, ref: str | Path | None = None,
          options: AlignOptions | None = None, **values) -> dict:
    """Move the model at ``model`` onto GPS (``gps``: a database.db or the image folder; into a
    local east-north-up frame in metres, ``georegistration.json`` beside it) or onto a table of
    reference centres (``ref``: ``IMAGE_NAME X Y Z`` lines) with the robust Sim3 of
    ``sfm.evaluation.georegistration``, and write it to ``out`` (COLMAP binary)."""
    options = options or _options(AlignOptions, values)
    if (gps is None) == (ref is None):
        raise InputError("align needs one of --gps SOURCE or --ref TABLE")
    out = Path(out)
    _free(out, options.overwrite)
    recon = _model(model)
    names = sorted(recon.images[i].name for i in recon.registered_image_ids)
    if gps is not None:
        reg, why = georegister(recon, _gps_source(Path(gps), names), options.max_error, options.seed)
    else:
        table = _reference_table(Path(ref))
        known = [n for n in names if n in table]
        centers, up = model_centers_and_up(recon, known)
        reference = np.array([table[n] for n in known], np.float64).reshape(-1, 3)
        reg, why = register_to_reference(centers, up, reference, options.max_error, options.seed)
        if reg is not None:
            recon.transform(reg.target_from_model)
    if reg is None:
        raise InputError(f"cannot align {model}: {why}")
    write_model(recon, out)
    write_georegistration(out, reg.to_json() if reg.origin is not None else None)
    return {"out": str(out), **reg.to_json()}
