"""Shared fixtures: where the real datasets live, and a skip when they are absent."""

from __future__ import annotations

import zlib  # noqa: F401 - before pycolmap: importing it first breaks later zlib use (PNG writes)
from pathlib import Path

import cv2  # noqa: F401 - same reason

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data`` beside the checkout; tests that need it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real datasets not found at {SHARED_DATA} (../shared/data beside the checkout)")
    return SHARED_DATA


@pytest.fixture
def db_path(tmp_path: Path) -> Path:
    """A database file path in the test's temporary directory (test_database*.py)."""
    return tmp_path / "database.db"
