"""Entity path parts of the recording."""

from __future__ import annotations


def entity_part(name: str) -> str:
    """An image or model name (which may hold ``/``, spaces, dots) as one entity path part."""
    import rerun as rr

    return rr.escape_entity_path_part(name)
