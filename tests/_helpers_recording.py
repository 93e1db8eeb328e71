"""Reading a recording back in tests: the text documents a run logged."""

from __future__ import annotations

from pathlib import Path

from rerun.chunk import RrdReader


def recording_texts(path: Path) -> dict[str, str]:
    """The last ``TextDocument`` text of every entity of the ``.rrd`` at ``path``, by entity path."""
    texts = {}
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        if "TextDocument:text" in batch.schema.names:
            texts[str(chunk.entity_path)] = batch.column("TextDocument:text").to_pylist()[-1][0]
    return texts
