"""Options of ``graphsfm export``."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option


@dataclass(frozen=True)
class ExportOptions(Options):
    """Options of ``graphsfm export``."""

    to: str = option("bin", "Output format: a COLMAP model folder (txt, bin) or a coloured PLY point cloud.",
                     choices=("txt", "bin", "ply"))
