"""Keypoint selection and descriptor storage (sfm.sift), on hand-made keypoint lists."""

from __future__ import annotations

import numpy as np

from sfm.sift import strongest_locations


def test_strongest_locations_counts_locations_not_orientations():
    # (x, y, size) locations: A has three orientations, B two, C and D one each
    locations = np.array([
        [1, 1, 2], [5, 5, 2], [1, 1, 2], [9, 9, 3], [1, 1, 2], [5, 5, 2], [7, 7, 1],
    ], dtype=float)  # fmt: skip
    response = np.array([0.9, 0.8, 0.9, 0.5, 0.9, 0.8, 0.1])
    #                      A    B    A    C    A    B    D
    keep = strongest_locations(locations, response, max_locations=3, max_orientations=2)
    # A (two of its three, in input order on ties), B (both), C; D is the fourth location
    assert keep.tolist() == [0, 2, 1, 5, 3]
    assert strongest_locations(locations, response, 1, 1).tolist() == [0]
    assert strongest_locations(locations, response, 10, 4).tolist() == [0, 2, 4, 1, 5, 3, 6]
    assert strongest_locations(np.zeros((0, 3)), np.zeros(0), 5).tolist() == []
