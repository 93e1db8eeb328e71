"""Options of ``graphsfm export``."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option

EXPORT_FORMATS = ("txt", "bin", "ply", "undistorted", "nerfstudio")


@dataclass(frozen=True)
class ExportOptions(Options):
    """Options of ``graphsfm export``."""

    to: str | None = option(
        None, "Output format: a COLMAP model folder (txt, bin), a PLY point cloud, undistorted images and a PINHOLE "
        "model (needs --images), or nerfstudio's transforms.json; default: from OUT (.ply, .json, else bin).",
        choices=EXPORT_FORMATS)
    overwrite: bool = option(False, "Replace OUT when it exists (otherwise an existing OUT is an error).")


def format_from_path(out) -> str:
    """The export format an output path implies: ``.ply`` a PLY, ``.json`` nerfstudio, else a
    binary COLMAP model folder."""
    suffix = str(out).lower().rsplit(".", 1)[-1] if "." in str(out).rsplit("/", 1)[-1] else ""
    return {"ply": "ply", "json": "nerfstudio"}.get(suffix, "bin")
