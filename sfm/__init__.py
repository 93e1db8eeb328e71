"""graphsfm's application package: data model, I/O, stages, CLI.

``sfm.reconstruct(images, workspace, **options)`` runs every stage; ``sfm.run_extract``,
``run_match``, ``run_cluster``, ``run_map`` and ``run_merge`` run one each (see ``sfm.api``).
Imported lazily so that ``import sfm.core.model`` stays light.
"""

from __future__ import annotations

_API = ("reconstruct", "make_options", "run_extract", "run_match", "run_cluster", "run_map", "run_merge",
        "ExtractOptions", "MatchOptions", "ClusterOptions", "MapperOptions", "MergeOptions", "read_model")


def __getattr__(name: str):
    if name in _API:
        from sfm import api

        return getattr(api, name)
    raise AttributeError(f"module 'sfm' has no attribute {name!r}")
