"""sfm.merge.alignment.merged_poses: the merged cluster C_final of Alg. 2 before its refinement."""

from __future__ import annotations

import numpy as np

from backend.sim3 import Sim3
from graph.merge_plan import MergePlan
from sfm.core.model import Camera, Image, Reconstruction
from sfm.merge.alignment import merged_poses
from sfm.merge.cluster_graph import LocalModel


def _model(params: list[float], observed: dict[str, int], shift: float) -> Reconstruction:
    """A model whose camera 1 has ``params``; image ``name`` observes ``observed[name]`` points
    and sits at x = ``shift`` in the model's frame."""
    recon = Reconstruction()
    recon.cameras[1] = Camera(1, "SIMPLE_RADIAL", 640, 480, np.array(params))
    for k, (name, n) in enumerate(sorted(observed.items())):
        ids = np.full(10, -1, dtype=np.int64)
        ids[:n] = np.arange(n) + 100 * k
        recon.images[k + 1] = Image(k + 1, name, 1, np.eye(3), np.array([-shift, 0.0, 0.0]),
                                    keypoints=np.zeros((10, 2)), point3D_ids=ids)
    return recon


def _plan() -> MergePlan:
    return MergePlan(anchor=0, clusters=(0, 1), total_size=4, parent={0: None, 1: 0}, layer={0: 1, 1: 1},
                     num_layers=1, path={0: (0,), 1: (1, 0)}, edges=((0, 1, 1.0),), merge_order=((1, 0),))


def test_a_shared_camera_pools_every_model_estimate_weighted_by_its_observations():
    anchor = _model([500.0, 320.0, 240.0, 0.01], {"a": 8, "b": 4}, shift=0.0)    # 12 observations
    other = _model([520.0, 322.0, 238.0, -0.02], {"b": 2, "c": 2}, shift=1.0)    # 4 observations
    sims = {0: Sim3(), 1: Sim3(scale=2.0, translation=np.array([0.0, 5.0, 0.0]))}
    poses, params = merged_poses([LocalModel("C0/0", anchor), LocalModel("C1/0", other)], _plan(), sims)
    expected = (12 * np.array([500.0, 320.0, 240.0, 0.01]) + 4 * np.array([520.0, 322.0, 238.0, -0.02])) / 16
    np.testing.assert_allclose(params[1], expected, rtol=0, atol=1e-12)
    # An image in both models keeps the anchor's pose; the other model's own image is moved by its Sim3.
    assert sorted(poses) == ["a", "b", "c"]
    np.testing.assert_allclose(poses["b"][1], [0.0, 0.0, 0.0], atol=1e-12)
    centre_c = -poses["c"][0].T @ poses["c"][1]
    np.testing.assert_allclose(centre_c, [2.0, 5.0, 0.0], atol=1e-12)


def test_a_camera_no_model_observes_keeps_the_parameters_nearest_the_anchor():
    anchor = _model([500.0, 320.0, 240.0, 0.0], {"a": 0}, shift=0.0)
    other = _model([900.0, 320.0, 240.0, 0.0], {"c": 0}, shift=1.0)
    _, params = merged_poses([LocalModel("C0/0", anchor), LocalModel("C1/0", other)], _plan(), {0: Sim3(), 1: Sim3()})
    np.testing.assert_allclose(params[1], [500.0, 320.0, 240.0, 0.0])


NOMINAL = {1: np.array([768.0, 319.5, 239.5, 0.0])}  # the database's camera: no distortion, the image centre


def _merge_two(anchor_params, other_params, nominal=NOMINAL) -> np.ndarray:
    """Camera 1's merged parameters from an anchor with 12 observations in its images and a
    second model with 4."""
    models = [LocalModel("C0/0", _model(anchor_params, {"a": 8, "b": 4}, shift=0.0)),
              LocalModel("C1/0", _model(other_params, {"b": 2, "c": 2}, shift=1.0))]
    _, params = merged_poses(models, _plan(), {0: Sim3(), 1: Sim3()}, nominal)
    return params[1]


def test_the_principal_point_is_pooled_over_the_models_that_refined_it_only():
    """The anchor held it (12 observations), the other model refined it to (302, 247) (4
    observations).  Focal length and distortion pool over both; the principal point is the
    refining model's alone, not a mean pulled three quarters of the way back to the centre.  With
    both holding it, it stays nominal; without ``nominal`` every model counts."""
    anchor, other = [500.0, 319.5, 239.5, 0.01], [520.0, 302.0, 247.0, -0.02]
    np.testing.assert_allclose(_merge_two(anchor, other),
                               [(12 * 500.0 + 4 * 520.0) / 16, 302.0, 247.0, (12 * 0.01 - 4 * 0.02) / 16], rtol=0, atol=1e-12)
    np.testing.assert_allclose(_merge_two(anchor, other, nominal=None)[1:3],
                               [(12 * 319.5 + 4 * 302.0) / 16, (12 * 239.5 + 4 * 247.0) / 16])
    np.testing.assert_array_equal(_merge_two(anchor, [520.0, 319.5, 239.5, -0.02])[1:3], [319.5, 239.5])


def test_the_distortion_is_pooled_over_the_models_that_refined_it_only():
    """The anchor held k at its nominal 0 (12 observations), the other model refined it to
    -0.02 (4 observations).  The merged distortion is the refining model's, not a quarter of it;
    the focal length still pools over both.  With both holding it, it stays nominal."""
    anchor = [500.0, 319.5, 239.5, 0.0]
    np.testing.assert_allclose(_merge_two(anchor, [520.0, 319.5, 239.5, -0.02]),
                               [(12 * 500.0 + 4 * 520.0) / 16, 319.5, 239.5, -0.02], rtol=0, atol=1e-12)
    assert _merge_two(anchor, [520.0, 319.5, 239.5, 0.0])[3] == 0.0
