"""The ``cluster`` stage on synthetic databases: clusters.json contract, cut quality, Rerun."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from graph.image_graph import build_image_graph
from graph.partition import cut_weight
from sfm.cli import main
from sfm.clustering.options import ClusterOptions
from sfm.stages.cluster import run_cluster
from sfm.io.database import Database
from sfm.errors import InputError
from sfm.viz.recorder import entity_paths
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def _graph_from_db(path):
    with Database(path, readonly=True) as db:
        images = db.read_images()
        i, j, w = db.verified_pairs()
    ids = sorted(images)
    node = {v: k for k, v in enumerate(ids)}
    names = [images[v].name for v in ids]
    ei = np.array([node[int(a)] for a in i])
    ej = np.array([node[int(b)] for b in j])
    return names, build_image_graph(len(ids), ei, ej, w.astype(float))


def _check_clusters(workspace, s_max, completeness, n_images, min_overlap=6):
    data = json.loads((workspace / "clusters.json").read_text())
    for key in ("clusters", "max_cluster_size", "completeness_ratio", "max_overlap", "maxst", "extra_edges",
                "lost_edges", "isolated_images", "num_images", "num_components", "cut_weight_fraction", "options",
                "min_overlap", "core_size_bound", "common_images", "thin_overlaps", "warnings"):
        assert key in data
    cores = [set(c["core"]) for c in data["clusters"]]
    members = [set(c["members"]) for c in data["clusters"]]
    assert sum(len(c) for c in cores) == len(set().union(*cores)) == n_images  # cores partition
    assert max(len(m) for m in members) <= s_max  # the bound is on the expanded cluster
    assert max(len(c) for c in cores) <= data["core_size_bound"] < s_max
    assert all(c <= m for c, m in zip(cores, members))
    warned = " ".join(data["warnings"])
    for k, m in enumerate(members):  # completeness as the paper defines it
        eta = sum(len(m & o) for j, o in enumerate(members) if j != k) / len(m)
        assert eta == pytest.approx(data["clusters"][k]["completeness"], abs=1e-5)
        assert (eta < completeness) == (data["clusters"][k]["below_completeness"] is not None)
        assert eta >= completeness or f"cluster C{k} " in warned
    thin = {(a, b) for a, b, *_ in data["thin_overlaps"]}
    for a, b, _ in data["maxst"]:  # every MaxST edge is an overlap the merge can use, or is reported
        assert len(members[a] & members[b]) >= min_overlap or ((a, b) in thin and f"clusters C{a} and C{b}," in warned)
        assert len(members[a] & members[b]) >= 2
    return data, cores


def test_cluster_aerial_database(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="aerial", num_images=300, observations_per_image=500, seed=0))
    assert main(["cluster", "--workspace", str(tmp_path), "--max-cluster-size", "40", "--completeness", "0.5", "--max-overlap", "20", "--seed", "0"]) == 0
    data, cores = _check_clusters(tmp_path, 40, 0.5, 300)
    assert len(data["clusters"]) >= 8 and len(data["maxst"]) == len(data["clusters"]) - 1
    # The cut is good: far less weight than random partitions of the same sizes.
    names, graph = _graph_from_db(tmp_path / "database.db")
    labels = np.empty(len(names), int)
    index = {n: k for k, n in enumerate(names)}
    for k, core in enumerate(cores):
        labels[[index[n] for n in core]] = k
    rng = np.random.default_rng(0)
    random_cuts = [cut_weight(graph, rng.permutation(labels)) for _ in range(5)]
    assert cut_weight(graph, labels) <= 0.5 * np.mean(random_cuts)
    # Rerun: the image graph coloured by cluster and the cluster graph with the MaxST.
    assert {"/graph/images", "/graph/clusters"} <= entity_paths(tmp_path / "recording-cluster.rrd")
    # Same seed, same clusters.
    first = (tmp_path / "clusters.json").read_text()
    run_cluster(tmp_path, ClusterOptions(max_cluster_size=40, max_overlap=20, seed=0))
    assert (tmp_path / "clusters.json").read_text() == first


def test_clusters_that_cannot_reach_c_are_named_in_the_log_clusters_json_and_report(tmp_path, caplog):
    run_synth(tmp_path, SynthOptions(scene="aerial", num_images=300, observations_per_image=500, seed=0))
    # C = 1 with at most 5 images added between two clusters: some cannot get there
    with caplog.at_level(logging.WARNING, logger="sfm.stages.cluster"):
        result = run_cluster(tmp_path, ClusterOptions(max_cluster_size=40, completeness=1.0, max_overlap=5))
    data, _ = _check_clusters(tmp_path, 40, 1.0, 300)
    below = [c for c in data["clusters"] if c["below_completeness"]]
    assert below and all(c["size"] < 40 and c["below_completeness"] == "max_overlap" for c in below)
    assert len(data["warnings"]) >= len(below) and result.warnings == data["warnings"]
    for c in below:
        [line] = [w for w in data["warnings"] if w.startswith(f"cluster C{c['id']} ")]
        assert f"reaches completeness {c['completeness']:.2f}, below --completeness 1:" in line
        assert "some at the --overlap 5 images per pair" in line
        assert line in caplog.text
    for a, b, common, reason in data["thin_overlaps"]:  # MaxST edges capped at 5 images
        assert common == 5 and reason == "max_overlap"
        assert any(w.startswith(f"clusters C{a} and C{b}, ") and "--overlap 5 images were added along it" in w
                   for w in data["warnings"])
    assert json.loads((tmp_path / "report.json").read_text())["warnings"] == data["warnings"]
    # a reachable C: no warning, and none left in the report
    run_cluster(tmp_path, ClusterOptions(max_cluster_size=40, seed=0))
    data, _ = _check_clusters(tmp_path, 40, 0.5, 300)
    assert data["warnings"] == [] and json.loads((tmp_path / "report.json").read_text())["warnings"] == []


def test_small_scene_is_one_cluster(tmp_path):
    run_synth(tmp_path, SynthOptions(num_images=12, observations_per_image=300, seed=1))
    result = run_cluster(tmp_path, ClusterOptions(max_cluster_size=100))
    assert result.num_clusters == 1 and result.cluster_sizes == [12]
    data = json.loads((tmp_path / "clusters.json").read_text())
    assert data["maxst"] == [] and data["clusters"][0]["completeness"] == 0.0


def test_cluster_without_database_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="no database"):
        run_cluster(tmp_path, ClusterOptions())


@pytest.mark.slow
def test_cut_quality_on_2000_image_aerial(tmp_path):
    """Issue acceptance: on a 2,000-image aerial graph the cut weighs <= 0.5x a random partition."""
    run_synth(tmp_path, SynthOptions(scene="aerial", num_images=2000, outlier_ratio=0.2, seed=0))
    result = run_cluster(tmp_path, ClusterOptions())
    data, cores = _check_clusters(tmp_path, 100, 0.5, 2000)
    names, graph = _graph_from_db(tmp_path / "database.db")
    index = {n: k for k, n in enumerate(names)}
    labels = np.empty(len(names), int)
    for k, core in enumerate(cores):
        labels[[index[n] for n in core]] = k
    rng = np.random.default_rng(0)
    ratio = cut_weight(graph, labels) / np.mean([cut_weight(graph, rng.permutation(labels)) for _ in range(5)])
    assert ratio <= 0.5, ratio
    assert result.num_clusters >= 20


@pytest.mark.slow
def test_demo_scene_clusters_keep_the_bound(tmp_path):
    """Issue 31: on the demo (30 rendered views, S_max 12) one cluster held all 30 images."""
    from sfm.stages.extract import ExtractOptions, run_extract
    from sfm.stages.match import MatchOptions, run_match
    from sfm.synthetic.rendered import RenderOptions, write_rendered_scene

    scene = write_rendered_scene(tmp_path / "scene", RenderOptions(num_images=30, seed=0))
    run_extract(Path(scene["image_dir"]), tmp_path, ExtractOptions())
    run_match(tmp_path, MatchOptions())
    result = run_cluster(tmp_path, ClusterOptions(max_cluster_size=12))
    data, _ = _check_clusters(tmp_path, 12, 0.5, 30)
    assert result.num_clusters >= 3 and max(result.cluster_sizes) <= 12
    assert data["warnings"] == []  # every cluster complete, every MaxST edge with 6 common images
