"""The survey scene: its photos show what its ground truth says (the same surface point at the
pixels the GT poses project it to, with the same colour), its EXIF gives the true focal length
and GPS, it renders deterministically and resumes, and twins are the same building."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from backend.geometry import look_at, rotation_angle_deg
from sfm.core.geodesy import enu_from_wgs84
from sfm.errors import InputError
from sfm.evaluation.ground_truth import read_gt_table
from sfm.io.image_files import probe_image
from sfm.stages.synth import run_synth
from sfm.synthetic import survey
from sfm.synthetic.options import SynthOptions

# Small photos, one process; one seed, so the octave tiles are made once.
SMALL = SynthOptions(scene="survey", num_images=10, width=320, height=240, seed=3, workers=1)


def _project(K: np.ndarray, rotation: np.ndarray, translation: np.ndarray, points: np.ndarray) -> np.ndarray:
    cam = points @ rotation.T + translation
    return cam[:, :2] / cam[:, 2:] * K[0, 0] + K[:2, 2]


def _inside(pixels: np.ndarray) -> np.ndarray:
    return (pixels[:, 0] > 0) & (pixels[:, 0] < 319) & (pixels[:, 1] > 0) & (pixels[:, 1] < 239)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    path = tmp_path_factory.mktemp("survey")
    run_synth(path, SMALL)
    return path


def test_flight_plan():
    plan = survey.survey_plan(dataclasses.replace(SMALL, num_images=41))
    kinds = [survey.camera_kind(plan, i) for i in range(41)]
    assert kinds.count("nadir") == 21 and {k for k in kinds if k != "nadir"} == {
        "oblique-north",
        "oblique-east",
        "oblique-south",
        "oblique-west",
    }
    down = np.array([0.0, 0.0, -1.0])
    for i, kind in enumerate(kinds):
        rotation, translation = survey.camera_pose(plan, i)
        axis = rotation[2]  # the optical axis in the world
        tilt = np.degrees(np.arccos(axis @ down))
        assert (tilt < 8) if kind == "nadir" else (abs(tilt - survey.OBLIQUE_TILT_DEG) < 8), (i, kind, tilt)
        assert abs((-rotation.T @ translation)[2] - survey.ALTITUDE_M) < 3
    # Consecutive nadir photos of a strip are one base apart; the next strip runs back.
    centers = np.array([-r.T @ t for r, t in (survey.camera_pose(plan, i) for i in range(0, 41, 2))])
    steps = np.diff(centers[: plan.stations_per_strip, 0])
    assert np.all(np.abs(steps - plan.base_m) < 3)
    back = centers[plan.stations_per_strip : 2 * plan.stations_per_strip, 0]
    assert (
        np.all(np.diff(back) < 0)
        and abs(centers[plan.stations_per_strip, 1] - centers[0, 1] - plan.strip_spacing_m) < 3
    )


def test_gt_table_holds_the_poses_the_renderer_used(workspace):
    plan = survey.survey_plan(SMALL)
    gt = read_gt_table(workspace / "gt" / "cameras_gt_opencv.txt")
    assert (
        sorted(gt)
        == sorted(p.name for p in (workspace / "images").glob("*.jpg"))
        == [survey.image_name(i) for i in range(SMALL.num_images)]
    )
    for i in range(SMALL.num_images):
        pose, (rotation, translation) = gt[survey.image_name(i)], survey.camera_pose(plan, i)
        assert (pose.width, pose.height) == (320, 240)
        np.testing.assert_allclose(pose.K, plan.K, atol=1e-12)
        assert rotation_angle_deg(pose.rotation, rotation) < 1e-6
        np.testing.assert_allclose(pose.translation, translation, atol=1e-9)
    described = json.loads((workspace / "gt" / "survey.json").read_text())
    assert described["nadir_images"] == 5 and described["oblique_images"] == 5


@pytest.mark.parametrize("pair", [(0, 2), (0, 1), (2, 5)])  # nadir-nadir, nadir-oblique, across stations
def test_a_surface_point_is_where_the_gt_projects_it(workspace, pair):
    """Cast the rays of a grid of pixels of photo A, project the points with B's GT pose, cast
    B's rays there: the same point comes back, unless something nearer to B hides it."""
    plan = survey.survey_plan(SMALL)
    gt = read_gt_table(workspace / "gt" / "cameras_gt_opencv.txt")
    a, b = (gt[survey.image_name(i)] for i in pair)
    u, v = np.meshgrid(np.linspace(5, 314, 14), np.linspace(5, 234, 11))
    points = survey.hit_points(plan, a.rotation, a.translation, np.column_stack([u.ravel(), v.ravel()]))
    assert np.isfinite(points).all()
    in_b = _project(b.K, b.rotation, b.translation, points)
    visible = _inside(in_b)
    assert visible.sum() >= 15
    back = survey.hit_points(plan, b.rotation, b.translation, in_b[visible])
    gap = np.linalg.norm(back - points[visible], axis=1)
    nearer = (
        np.linalg.norm(back - b.center, axis=1) < np.linalg.norm(points[visible] - b.center, axis=1) - 1e-3
    )
    assert np.all((gap < 1e-3) | nearer)  # the same point, or an occluder in front of it
    assert np.mean(gap < 1e-3) > 0.6


def _first_hit(plan, rotation: np.ndarray, translation: np.ndarray, pixel) -> np.ndarray:
    """The first surface point on a pixel's ray, found apart from the renderer: the terrain by
    Newton's method, then every face of the buildings the ray passes over, intersected in 3D."""
    center = -rotation.T @ translation
    ray = rotation.T @ np.array(
        [(pixel[0] - plan.K[0, 2]) / plan.focal, (pixel[1] - plan.K[1, 2]) / plan.focal, 1.0]
    )
    depth, _, _ = survey.terrain_depth(
        survey.terrain(plan.seed), center, ray[:, None], np.array([-center[2] / ray[2]]), 30
    )
    best = float(depth[0])
    ground = center + best * ray
    box = [(min(center[k], ground[k]), max(center[k], ground[k])) for k in (0, 1)]
    for building in survey.buildings_near(plan, *box):
        world_r, world_t = survey.world_from_building(building)
        origin, direction = world_r.T @ (center - world_t), world_r.T @ ray  # in the building's frame
        for face in survey.design_faces(building.design):
            along = face.normal @ direction
            if abs(along) < 1e-12:
                continue
            s = face.normal @ (face.vertices[0] - origin) / along
            if not 0 < s < best:
                continue
            hit, verts = origin + s * direction, face.vertices
            turns = [
                np.cross(verts[(k + 1) % len(verts)] - verts[k], hit - verts[k]) @ face.normal
                for k in range(len(verts))
            ]
            if min(turns) >= 0 or max(turns) <= 0:
                best = s
    return center + best * ray


@pytest.mark.parametrize("index", [0, 1])
def test_the_renderer_draws_the_first_surface_each_ray_meets(index):
    """The whole-image pass (terrain interpolated between exact samples, faces rasterised) finds
    the point an independent ray cast finds, at random pixels and at every kind of edge."""
    plan = survey.survey_plan(SMALL)
    rotation, translation = survey.camera_pose(plan, index)
    traced = survey.trace(plan, rotation, translation, np.arange(320), np.arange(240))
    surface = traced.surface
    edges = np.argwhere((surface[:-1, :-1] != surface[1:, :-1]) | (surface[:-1, :-1] != surface[:-1, 1:]))
    rng = np.random.default_rng(index)
    assert len(edges) > 100 and len(np.unique(surface)) > 3  # ground and some buildings' walls and roofs
    rows_cols = np.concatenate(
        [
            edges[rng.choice(len(edges), 100, replace=False)],
            np.column_stack([rng.integers(0, 240, 40), rng.integers(0, 320, 40)]),
        ]
    )
    center = -rotation.T @ translation
    for y, x in rows_cols:
        ray = rotation.T @ np.array([(x - plan.K[0, 2]) / plan.focal, (y - plan.K[1, 2]) / plan.focal, 1.0])
        drawn = center + ray / traced.inverse_depth[y, x]
        assert np.linalg.norm(drawn - _first_hit(plan, rotation, translation, (x, y))) < 2e-3, (x, y)


@pytest.mark.parametrize("pair", [(0, 2), (4, 6)])  # neighbours along a strip and across strips
def test_a_point_has_one_colour_in_the_photos_that_see_it(pair):
    """Texture and shading are functions of the surface point and of the blur its footprint
    brings: where the footprints are alike, so are the colours (no seam, shift or view-dependent
    term)."""
    plan = survey.survey_plan(SMALL)
    a, b = survey.camera_pose(plan, pair[0]), survey.camera_pose(plan, pair[1])
    traced = survey.trace(plan, *a, np.arange(320), np.arange(240))
    colour_a = survey.shade(plan, traced)
    rng = np.random.default_rng(0)
    pixels = np.column_stack([rng.integers(0, 320, 80), rng.integers(0, 240, 80)])
    points = survey.hit_points(plan, *a, pixels)
    in_b = _project(plan.K, *b, points)
    keep = _inside(in_b)
    center_b = -b[0].T @ b[1]
    same, other = [], []
    for (u, v), point, (x, y) in zip(in_b[keep], points[keep], pixels[keep]):
        seen = survey.trace(plan, *b, np.array([u]), np.array([v]))
        ray = b[0].T @ np.array([(u - plan.K[0, 2]) / plan.focal, (v - plan.K[1, 2]) / plan.focal, 1.0])
        if np.linalg.norm(center_b + ray / seen.inverse_depth[0, 0] - point) > 1e-3:
            continue  # hidden from B
        if not 1 / 1.1 < seen.footprint[0, 0] / traced.footprint[y, x] < 1.1:
            continue  # a wall seen head-on in one photo and edge-on in the other: blurred differently
        colour_b = survey.shade(plan, seen)[0, 0]
        same.append(np.abs(colour_b - colour_a[y, x]).max())
        other.append(np.abs(colour_b - colour_a[(y + 40) % 240, (x + 40) % 320]).max())
    assert len(same) >= 20
    assert np.median(same) < 1.0 and np.max(same) < 3.0  # grey levels
    assert np.median(other) > 8.0  # and the texture is not flat


def test_exif_gives_the_focal_length_and_gps(tmp_path, workspace):
    plan = survey.survey_plan(SMALL)
    errors = []
    for i in range(SMALL.num_images):
        info = probe_image(workspace / "images" / survey.image_name(i))
        assert info.focal_source == "exif-focal-plane" and abs(info.focal_px - plan.focal) < 0.01 * plan.focal
        assert (info.make, info.model) == (survey.CAMERA_MAKE, survey.CAMERA_MODEL)
        rotation, translation = survey.camera_pose(plan, i)
        enu = enu_from_wgs84(np.array([info.gps]), np.array(survey.ORIGIN_WGS84))[0]
        errors.append(enu + rotation.T @ translation)
    errors = np.array(errors)
    assert np.abs(errors).max() < 5 * SMALL.gps_noise_m and errors.std() > 0.3 * SMALL.gps_noise_m
    # Without noise the EXIF position is the centre itself (rationals of DMS, metres above WGS84).
    exact = dataclasses.replace(plan, gps_noise_m=0.0)
    for i in (0, 3):
        info = probe_image(_write(tmp_path / f"{i}.jpg", survey.photo(exact, i)))
        rotation, translation = survey.camera_pose(exact, i)
        enu = enu_from_wgs84(np.array([info.gps]), np.array(survey.ORIGIN_WGS84))[0]
        assert np.linalg.norm(enu + rotation.T @ translation) < 0.01


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


def test_photos_are_deterministic_and_synth_resumes(tmp_path, workspace):
    plan = survey.survey_plan(SMALL)
    first = (workspace / "images" / survey.image_name(3)).read_bytes()
    assert survey.photo(plan, 3) == first
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    (resumed / "images").mkdir()
    (resumed / "gt").mkdir()
    (resumed / "gt" / "survey.json").write_text((workspace / "gt" / "survey.json").read_text())
    for i in range(SMALL.num_images):
        if i != 3:  # a run stopped with photo 3 in flight
            (resumed / "images" / survey.image_name(i)).write_bytes(b"kept as it is")
    (resumed / "images" / f".{survey.image_name(3)}.tmp").write_bytes(b"half a photo")
    summary = run_synth(resumed, SMALL)
    assert summary["rendered"] == 1 and summary["already_there"] == SMALL.num_images - 1
    assert (resumed / "images" / survey.image_name(3)).read_bytes() == first
    assert (resumed / "images" / survey.image_name(4)).read_bytes() == b"kept as it is"
    assert not list((resumed / "images").glob(".*"))
    assert (resumed / "gt" / "cameras_gt_opencv.txt").read_text() == (
        workspace / "gt" / "cameras_gt_opencv.txt"
    ).read_text()
    with pytest.raises(InputError, match="other options.*num_images 10 \\(now 12\\)"):
        run_synth(resumed, dataclasses.replace(SMALL, num_images=12))
    (resumed / "gt" / "survey.json").unlink()
    with pytest.raises(InputError, match="holds no survey"):
        run_synth(resumed, SMALL)
    with pytest.raises(InputError, match="twins 40: the survey area has only"):
        run_synth(tmp_path / "crowded", dataclasses.replace(SMALL, twins=40))


def test_twins_are_one_design_in_several_places():
    plan = survey.survey_plan(dataclasses.replace(SMALL, num_images=200, twins=3))
    cells = survey.twin_cells(plan)
    by_design: dict[int, list] = {}
    for (i, j), k in cells.items():
        by_design.setdefault(k, []).append(survey.building_in_cell(plan, i, j))
    assert sorted(by_design) == [0, 1, 2] and all(2 <= len(b) <= 3 for b in by_design.values())
    for buildings in by_design.values():
        first = buildings[0]
        for other in buildings[1:]:
            assert other.design == first.design and other.center[:2] != first.center[:2]
            for f, g in zip(survey.design_faces(first.design), survey.design_faces(other.design)):
                np.testing.assert_array_equal(f.vertices, g.vertices)  # same geometry in its own frame
                np.testing.assert_array_equal(f.tex_matrix, g.tex_matrix)
            # Their world points differ by the placement only.
            r1, t1 = survey.world_from_building(first)
            r2, t2 = survey.world_from_building(other)
            np.testing.assert_allclose(r1, r2)
            assert np.linalg.norm(t1 - t2) > survey.CELL_M / 2
    unique = [
        survey.building_in_cell(plan, i, j) for i in range(-3, 3) for j in range(-3, 3) if (i, j) not in cells
    ]
    designs = [b.design for b in unique if b is not None]
    assert len(designs) > 10 and len(set(designs)) == len(designs)
    assert all(d not in designs for d in (b[0].design for b in by_design.values()))
    # Without twins no cell borrows a design.
    assert survey.twin_cells(dataclasses.replace(plan, twins=0)) == {}
    described = survey.description(plan)
    assert sum(len(t["places"]) for t in described["twins"]) == len(cells)


def test_twins_look_the_same_from_the_same_place():
    """Photographed from the same place relative to each, two placements of a twin design show
    the same pixels: texture and shading are the design's, not the place's."""
    plan = survey.survey_plan(dataclasses.replace(SMALL, num_images=200, twins=1))
    first, second = (survey.building_in_cell(plan, *cell) for cell in list(survey.twin_cells(plan))[:2])
    looks = []
    for building in (first, second):
        center = np.array(building.center)
        top = center + [0.0, 0.0, building.design.height]
        rotation, translation = look_at(top + [4.0, -9.0, 30.0], top, up=np.array([0.0, 1.0, 0.0]))
        traced = survey.trace(plan, rotation, translation, np.arange(320), np.arange(240))
        own = np.isin(
            traced.surface,
            [
                k
                for k, rgb in enumerate(traced.base_rgb.tolist())
                if k >= 2 and (tuple(rgb) in (_f32(building.design.wall_rgb), _f32(building.design.roof_rgb)))
            ],
        )
        looks.append((own, survey.shade(plan, traced)))
    (own1, rgb1), (own2, rgb2) = looks
    both = own1 & own2
    assert both.sum() > 0.9 * max(own1.sum(), own2.sum()) and both.sum() > 10000  # a quarter of the view
    assert np.abs(rgb1[both] - rgb2[both]).max() < 0.05  # grey levels


def _f32(rgb) -> tuple:
    return tuple(np.float32(rgb).tolist())
