"""The inverted-file matcher (sfm.matching.inverted_file): its index is what its docstring says,
it is the exact matcher when every descriptor is listed in every cell, and on real photos it
keeps the verified inliers of the exact matcher."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import SHARED_DATA
from sfm.features.extraction import extract_features
from sfm.features.options import ExtractOptions
from sfm.io.database_schema import CameraRecord
from sfm.matching.descriptors import match_descriptors, normalize_descriptors, resolve_matcher
from sfm.matching.inverted_file import CELL_MARGIN, InvertedFile, match_inverted, number_of_cells
from sfm.matching.verification import verify_pair
from test_matching import synthetic_descriptor_pair


def unit_rows(seed: int, n: int) -> np.ndarray:
    d, _, _ = synthetic_descriptor_pair(seed, n_true=n // 2, n_distract=n - n // 2)
    return normalize_descriptors(d)


def test_each_descriptor_is_listed_in_every_cell_within_the_margin_of_its_nearest():
    unit = unit_rows(0, 3000)
    index = InvertedFile.build(unit, seed=3)
    assert len(index.centroids) == number_of_cells(3000) == 64  # 3000 / 64 rounds to 2^6
    np.testing.assert_allclose(np.linalg.norm(index.centroids, axis=1), 1.0, atol=1e-5)
    similarity = unit @ index.centroids.T
    expected = similarity >= similarity.max(axis=1, keepdims=True) - CELL_MARGIN
    listed = np.zeros_like(expected)
    for c in range(len(index.centroids)):
        members = index.members[index.bounds[c]:index.bounds[c + 1]]
        assert np.all(np.diff(members) > 0)  # each row once per cell, in order
        listed[members, c] = True
    np.testing.assert_array_equal(listed, expected)
    assert np.all(listed[np.arange(len(unit)), similarity.argmax(axis=1)])  # its own cell always


def test_the_index_depends_on_the_seed_and_the_descriptors_only():
    unit = unit_rows(1, 2000)
    a, b = InvertedFile.build(unit, seed=5), InvertedFile.build(unit.copy(), seed=5)
    np.testing.assert_array_equal(a.centroids, b.centroids)
    np.testing.assert_array_equal(a.members, b.members)
    assert not np.array_equal(a.centroids, InvertedFile.build(unit, seed=6).centroids)


@pytest.mark.parametrize("cross_check", [True, False])
def test_with_every_descriptor_in_every_cell_it_is_the_exact_matcher(cross_check):
    """A margin of 2 (the full range of cosine similarities) lists every row in every cell: the
    search is then exhaustive and must give the exact matcher's matches, mutual check included."""
    d1, d2, _ = synthetic_descriptor_pair(2, n_true=600, n_distract=900)
    u1, u2 = normalize_descriptors(d1), normalize_descriptors(d2)
    exact = match_descriptors(u1, u2, cross_check=cross_check, matcher="brute", normalized=True)
    got = match_inverted(InvertedFile.build(u1, margin=2.0), InvertedFile.build(u2, margin=2.0),
                         cross_check=cross_check)
    np.testing.assert_array_equal(got, exact)


def test_auto_takes_the_inverted_file_only_where_features_are_many():
    assert resolve_matcher("auto", 1000, 1000) == "brute"
    assert resolve_matcher("auto", 4000, 4000) == "ivf"
    assert resolve_matcher("brute", 9000, 9000) == "brute"
    with pytest.raises(ValueError, match="matcher"):
        resolve_matcher("exact", 10, 10)


def test_on_real_photos_it_keeps_the_exact_matchers_verified_inliers():
    """lund_door, three pairs from neighbours to a wide baseline, at full features: the inlier
    counts after verification stay within 2% of the exact matcher's, and the approximate
    search compares a small share of the descriptor pairs."""
    data = SHARED_DATA / "lund_door"
    if not (data / "images").is_dir():
        pytest.skip(f"lund_door not found at {data} (../shared/data beside the checkout)")
    names = sorted(p.name for p in (data / "images").iterdir())
    gt = {line.split()[0]: [float(v) for v in line.split()[3:7]]
          for line in (data / "gt" / "cameras_gt_opencv.txt").read_text().splitlines() if not line.startswith("#")}
    options = ExtractOptions(max_image_size=1600)
    features = {}
    for name in (names[0], names[1], names[3]):
        gray = cv2.imread(str(data / "images" / name), cv2.IMREAD_GRAYSCALE)
        features[name] = extract_features(gray, options)
    fx, fy, cx, cy = gt[names[0]]
    camera = CameraRecord(1, "PINHOLE", 1296, 1936, np.array([fx, fy, cx + 0.5, cy + 0.5]), True)  # COLMAP pixels
    for a, b in ((names[0], names[1]), (names[1], names[3]), (names[0], names[3])):
        (kp1, d1), (kp2, d2) = features[a], features[b]
        u1, u2 = normalize_descriptors(d1), normalize_descriptors(d2)
        i1, i2 = InvertedFile.build(u1), InvertedFile.build(u2)
        assert len(i2.members) < 0.25 * len(i2.centroids) * len(u2)  # a cell lists a small share
        exact = verify_pair(kp1, kp2, match_descriptors(u1, u2, normalized=True, matcher="brute"), camera, camera)
        approx = verify_pair(kp1, kp2, match_inverted(i1, i2), camera, camera)
        assert len(exact.inlier_matches) > 300
        assert len(approx.inlier_matches) >= 0.98 * len(exact.inlier_matches), (a, b)
