"""Keypoint selection and descriptor storage (sfm.features.sift), on hand-made keypoint lists."""

from __future__ import annotations

import numpy as np

from sfm.features.sift import keypoint_scales, localization_sigma, top_locations


def test_top_locations_counts_locations_not_orientations():
    # (x, y, size) locations: A has three orientations, B two, C and D one each
    locations = np.array([
        [1, 1, 2], [5, 5, 2], [1, 1, 2], [9, 9, 3], [1, 1, 2], [5, 5, 2], [7, 7, 1],
    ], dtype=float)  # fmt: skip
    response = np.array([0.9, 0.8, 0.9, 0.5, 0.9, 0.8, 0.1])
    #                      A    B    A    C    A    B    D
    keep = top_locations(locations, response, max_locations=3, max_orientations=2)
    # A (two of its three, in input order on ties), B (both), C; D is the fourth location
    assert keep.tolist() == [0, 2, 1, 5, 3]
    assert top_locations(locations, response, 1, 1).tolist() == [0]
    assert top_locations(locations, response, 10, 4).tolist() == [0, 2, 4, 1, 5, 3, 6]
    assert top_locations(np.zeros((0, 3)), np.zeros(0), 5).tolist() == []


def test_keypoint_scales_from_each_layout():
    xy = np.array([[10.0, 20.0], [30.0, 40.0]])
    assert keypoint_scales(xy) is None
    four = np.column_stack([xy, [0.8, 3.2], [0.5, 1.0]])  # x, y, scale, orientation
    np.testing.assert_array_equal(keypoint_scales(four), [0.8, 3.2])
    # COLMAP's affine shape: A = s R(theta), so sqrt|det A| = s whatever the angle
    s, th = np.array([1.5, 4.0]), np.array([0.3, -2.0])
    affine = np.column_stack([xy, s * np.cos(th), -s * np.sin(th), s * np.sin(th), s * np.cos(th)])
    np.testing.assert_allclose(keypoint_scales(affine), s, rtol=1e-12)


def test_localization_sigma_grows_with_scale_from_the_finest_level():
    scales = np.array([0.5, 0.8, 1.6, 3.2, 12.8, 0.0, -1.0, np.nan, np.inf])
    np.testing.assert_allclose(localization_sigma(scales), [1, 1, 2, 4, 16, 1, 1, 1, 1])
