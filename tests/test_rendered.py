"""The rendered scene: images agree with their ground truth (SIFT matches obey the GT epipolar
geometry to sub-pixel accuracy), so end-to-end tests can trust it."""

from __future__ import annotations

import cv2
import numpy as np

from sfm.evaluation.ground_truth import read_gt_table
from sfm.synthetic.options import RenderOptions
from sfm.synthetic.rendered import write_rendered_scene


def test_rendered_images_match_their_ground_truth(tmp_path):
    summary = write_rendered_scene(tmp_path, RenderOptions(num_images=6, seed=1))
    names = sorted(p.name for p in (tmp_path / "images").glob("*.png"))
    assert len(names) == 6 == summary["images"]
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    assert sorted(gt) == names
    sift = cv2.SIFT_create(nfeatures=4000)
    a, b = gt[names[2]], gt[names[3]]
    feats = []
    for pose in (a, b):
        image = cv2.imread(str(tmp_path / "images" / pose.name), cv2.IMREAD_GRAYSCALE)
        assert image.shape == (pose.height, pose.width)
        feats.append(sift.detectAndCompute(image, None))
    (kp1, d1), (kp2, d2) = feats
    assert len(kp1) > 1000  # rich texture: many keypoints
    matches = [m for m, n in cv2.BFMatcher().knnMatch(d1, d2, k=2) if m.distance < 0.7 * n.distance]
    assert len(matches) > 300
    x1 = np.array([kp1[m.queryIdx].pt for m in matches])
    x2 = np.array([kp2[m.trainIdx].pt for m in matches])
    r = b.rotation @ a.rotation.T
    t = b.translation - r @ a.translation
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ r
    F = np.linalg.inv(b.K).T @ E @ np.linalg.inv(a.K)
    lines = np.column_stack([x1, np.ones(len(x1))]) @ F.T
    dist = np.abs(np.sum(lines[:, :2] * x2, 1) + lines[:, 2]) / np.linalg.norm(lines[:, :2], axis=1)
    assert np.median(dist) < 0.5  # OpenCV keypoints + GT K, R, t agree: pixel conventions match
    assert np.mean(dist < 2.0) > 0.9


def test_rendering_is_deterministic(tmp_path):
    write_rendered_scene(tmp_path / "a", RenderOptions(num_images=2, seed=5, texture_size=256))
    write_rendered_scene(tmp_path / "b", RenderOptions(num_images=2, seed=5, texture_size=256))
    for name in ("view_000.png", "view_001.png"):
        assert np.array_equal(cv2.imread(str(tmp_path / "a" / "images" / name)), cv2.imread(str(tmp_path / "b" / "images" / name)))
