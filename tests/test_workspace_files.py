"""sfm.io.workspace.numbered_folders and sfm.io.ledger.files_fingerprint: the model folders a
stage reads, and the fingerprint the ledger keeps of them."""

from __future__ import annotations

from sfm.io.ledger import files_fingerprint
from sfm.io.workspace import numbered_folders


def test_numbered_folders_are_the_digit_folders_in_number_order(tmp_path):
    for name in ("10", "2", "0", "extra", "1a"):
        (tmp_path / name).mkdir()
    (tmp_path / "3").write_text("a file, not a model folder")
    assert [d.name for d in numbered_folders(tmp_path)] == ["0", "2", "10"]
    assert numbered_folders(tmp_path / "missing") == []


def test_the_fingerprint_changes_with_a_file_name_or_its_bytes_only(tmp_path):
    (tmp_path / "0").mkdir()
    (tmp_path / "0" / "images.bin").write_bytes(b"abc")
    (tmp_path / "note.txt").write_text("x")
    first = files_fingerprint(tmp_path)
    assert files_fingerprint(tmp_path) == first
    assert files_fingerprint(tmp_path, "*/*") != first  # the pattern picks the files
    (tmp_path / "0" / "images.bin").write_bytes(b"abd")
    assert files_fingerprint(tmp_path) != first
    (tmp_path / "0" / "images.bin").write_bytes(b"abc")
    assert files_fingerprint(tmp_path) == first
    (tmp_path / "0" / "images.bin").rename(tmp_path / "0" / "points.bin")
    assert files_fingerprint(tmp_path) != first
    assert files_fingerprint(tmp_path / "missing") == files_fingerprint(tmp_path / "also_missing")
