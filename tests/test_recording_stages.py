"""Every stage is in the recording, the same for one cluster or many: read back with
``rerun.chunk.RrdReader``, a reconstruct of the rendered facade holds each stage's entities
(image pixels, keypoints, match lines, the image and cluster graphs, the growing local models,
the merge, the final coloured model) and a markdown text per stage, and a default layout."""

from __future__ import annotations

import json
import shutil
from collections import defaultdict

import numpy as np
import pytest

import sfm
from sfm.io.colmap_model import read_model
from sfm.synthetic.options import RenderOptions
from sfm.synthetic.rendered import write_rendered_scene

rr = pytest.importorskip("rerun")
NUM_IMAGES = 12


class Recording:
    """Per entity path: its component columns, its timelines, and its rows' values."""

    def __init__(self, path):
        from rerun.chunk import RrdReader

        reader = RrdReader(str(path))
        self.blueprints = reader.blueprints()
        self.components: dict[str, set[str]] = defaultdict(set)
        self.timelines: dict[str, set[str]] = defaultdict(set)
        self.values: dict[tuple[str, str], list] = defaultdict(list)
        for chunk in reader.stream():
            entity = str(chunk.entity_path)
            batch = chunk.to_record_batch()
            self.timelines[entity] |= set(chunk.timeline_names)
            for name in batch.schema.names:
                if ":" in name:
                    self.components[entity].add(name)
                    self.values[(entity, name)] += batch.column(name).to_pylist()

    def has(self, entity: str, *components: str) -> bool:
        return set(components) <= self.components.get(entity, set())

    def under(self, prefix: str, *components: str) -> list[str]:
        return sorted(e for e in self.components if e.startswith(prefix) and self.has(e, *components))

    def last(self, entity: str, component: str):
        return self.values[(entity, component)][-1]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One run of 12 images in one cluster, then the same workspace clustered by 5 (its extract
    and match resumed: their views come from the database and the image files)."""
    root = tmp_path_factory.mktemp("recording")
    scene = write_rendered_scene(root / "scene", RenderOptions(num_images=NUM_IMAGES, seed=2))
    one, many = root / "one", root / "many"
    sfm.reconstruct(scene["image_dir"], one, workers=2, seed=0, record_pairs=4)
    shutil.copytree(one, many)
    (many / "recording.rrd").unlink()
    _, report = sfm.reconstruct(scene["image_dir"], many, workers=2, seed=0, max_cluster_size=5, record_pairs=4)
    assert report["num_clusters"] >= 3
    return {"one": one, "many": many}


@pytest.mark.parametrize("run", ["one", "many"])
def test_every_stage_is_in_the_recording(runs, run):
    ws = runs[run]
    rec = Recording(ws / "recording.rrd")
    names = [f"view_{i:03d}.png" for i in range(NUM_IMAGES)]
    # extract: every image's pixels and keypoints
    for name in names:
        assert rec.has(f"/images/{name}", "EncodedImage:blob")
        assert rec.has(f"/images/{name}/keypoints", "Points2D:positions", "Points2D:colors", "Points2D:radii")
        assert len(rec.last(f"/images/{name}/keypoints", "Points2D:positions")) > 500
    # match: the image graph with weights, the inlier matches of 4 pairs drawn between their images
    assert rec.has("/graph/images", "Points2D:positions", "Points2D:labels")
    assert rec.has("/graph/images/edges", "LineStrips2D:strips", "LineStrips2D:labels")
    pairs = rec.under("/matches/", "EncodedImage:blob")
    assert len(pairs) == 4
    for pair in pairs:
        assert len(rec.last(f"{pair}/inliers", "LineStrips2D:strips")) >= 15
    # cluster: the cluster graph; the image graph coloured by cluster
    assert rec.has("/graph/clusters", "Points2D:positions", "Points2D:labels")
    # map: every cluster's model growing on the registration timeline, frustums with images
    clusters = sorted({e.split("/")[2] for e in rec.under("/clusters/", "Points3D:positions")})
    assert len(clusters) == json.loads((ws / "report.json").read_text())["num_clusters"]
    for label in clusters:
        points = f"/clusters/{label}/model0/points"
        assert rec.has(points, "Points3D:positions", "Points3D:colors") and "registration" in rec.timelines[points]
        assert rec.has(f"/clusters/{label}/model0/ba_rms_px", "Scalars:scalars")
        frustums = rec.under(f"/clusters/{label}/model0/cams/", "Pinhole:image_from_camera", "EncodedImage:blob")
        assert len(frustums) >= 3
        assert rec.has(f"/clusters/{label}/unregistered", "TextDocument:text")
        # what the final BAs refined of the camera, and why (the rendered lens has no distortion)
        calibration = rec.last(f"/clusters/{label}/model0/calibration", "TextDocument:text")[0]
        assert "camera 1 (SIMPLE_RADIAL): distortion (" in calibration and "principal point shift (" in calibration
    # merge (several clusters only): the MSD-weighted cluster graph, the models moving
    if run == "many":
        assert len(clusters) >= 3
        assert rec.has("/graph/merge", "Points2D:labels") and rec.has("/graph/merge/edges", "LineStrips2D:labels")
        moved = rec.under("/merge/", "Transform3D:mat3x3")
        assert len(moved) == len(clusters) and all("merge_layer" in rec.timelines[e] for e in moved)
        assert any("anchor" in label for label in rec.last("/graph/merge", "Points2D:labels"))
    # final: the coloured model, the same as sparse/0's, its errors, its frustums with images
    model = read_model(ws / "sparse" / "0")
    rgba = np.array(rec.last("/world/points", "Points3D:colors"), dtype=np.uint32)
    rgb = np.stack([(rgba >> 24) & 255, (rgba >> 16) & 255, (rgba >> 8) & 255], axis=1)
    np.testing.assert_array_equal(rgb, [model.points3D[i].color for i in sorted(model.points3D)])
    assert len(np.unique(rgb, axis=0)) > 100
    assert len(rec.last("/world/points_error", "Points3D:colors")) == len(model.points3D)
    assert len(rec.under("/world/cams/", "Pinhole:image_from_camera", "EncodedImage:blob")) == len(model.images)
    # a markdown text per stage, and the tour so far
    stages = ["1_extract", "2_match", "3_cluster", "4_map", "7_final"] + (["5_merge", "6_refine"] if run == "many" else [])
    for stage in stages:
        assert rec.has(f"/tour/{stage}", "TextDocument:text", "TextDocument:media_type")
        assert rec.last(f"/tour/{stage}", "TextDocument:media_type") == ["text/markdown"]
    tour = rec.last("/tour", "TextDocument:text")[0]
    assert tour.index("## 1. Extract") < tour.index("## 3. Cluster") < tour.index("## 7. The final model")
    assert "Alg. 1" in tour and ("Alg. 2" in tour) == (run == "many")
    if run == "many":  # the merged model's own self-calibration decisions
        refine = rec.last("/tour/6_refine", "TextDocument:text")[0]
        assert "- camera 1 (SIMPLE_RADIAL): distortion (" in refine
    assert rec.blueprints  # the default layout
