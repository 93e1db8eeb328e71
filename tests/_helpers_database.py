"""Raw-SQL and rotation helpers shared by test_database.py and test_database_pycolmap.py."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def _raw(path: Path, sql: str, params: tuple = ()) -> list[tuple]:
    con = sqlite3.connect(path)
    try:
        return con.execute(sql, params).fetchall()
    finally:
        con.close()


def _quat_wxyz(rotation: Rotation) -> np.ndarray:
    x, y, z, w = rotation.as_quat()
    return np.array([w, x, y, z])
