"""The ``cluster`` stage: image graph from the database -> clusters.json (paper section 3.1).

Reads the verified pairs from ``WORK/database.db`` (the image graph of section 3.1.1: one node per
image, edge weight = number of verified inlier matches), cuts it with normalized cuts into cores
of at most ``max_cluster_size`` images and expands the cores along the maximum spanning tree of
the cluster graph until every cluster's completeness reaches ``completeness_ratio``
(Algorithm 1; ``graph.partition`` and ``graph.expansion`` do the work on arrays).  Images
without any verified pair cannot be reconstructed and are listed as isolated, not clustered.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from graph.expansion import expand_clusters
from graph.image_graph import build_image_graph, connected_components
from graph.partition import cut_weight, labels_from_clusters, partition_graph
from sfm.clustering.options import ClusterOptions
from sfm.core import progress
from sfm.io.database import Database
from sfm.errors import InputError, NoModelError
from sfm.viz.clustering import log_clusters
from sfm.viz.recorder import Recorder
from sfm.io.ledger import Ledger, database_fingerprint, fingerprint, options_record
from sfm.io.report import update_report
from sfm.io.workspace import CLUSTERS, DATABASE, read_json, write_json_atomic

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClusterResult:
    num_images: int
    num_clusters: int
    num_isolated: int
    num_components: int
    cluster_sizes: list[int]
    core_sizes: list[int]
    min_completeness: float
    cut_fraction: float
    time_s: float
    path: str


def run_cluster(workspace: Path, options: ClusterOptions, recorder: Recorder | None = None) -> ClusterResult:
    """Cluster the image graph of ``workspace/database.db`` into ``workspace/clusters.json``
    (paper section 3.1, Alg. 1)."""
    recorder = recorder or Recorder.disabled()
    t0 = time.perf_counter()
    progress.stage("cluster")
    db_path = Path(workspace) / DATABASE
    if not db_path.exists():
        raise InputError(f"no database at {db_path}: run extract and match (or synth) first")
    with Database(db_path, readonly=True) as db:
        images = db.read_images()
        id1, id2, weights = db.verified_pairs(min_inliers=options.min_inliers)
    if len(id1) == 0:
        raise NoModelError(f"no two of the {len(images)} images overlap: no pair has >= {options.min_inliers} verified "
                           "inlier matches, so no model can be made")
    image_ids = np.array(sorted(images), dtype=np.int64)
    names = [images[i].name for i in image_ids]
    node_of = {int(i): k for k, i in enumerate(image_ids)}
    ei = np.array([node_of[int(i)] for i in id1])
    ej = np.array([node_of[int(j)] for j in id2])
    graph = build_image_graph(len(image_ids), ei, ej, weights.astype(np.float64))

    out = Path(workspace) / CLUSTERS
    ledger = Ledger(workspace)
    opts, input_fp = options_record(options), database_fingerprint(db_path)
    if ledger.is_current("cluster", opts, input_fp) and out.exists():
        result = _reuse(out, names, (ei, ej, weights), recorder, t0)
        update_report(workspace, {"num_clusters": result.num_clusters}, {"cluster": result.time_s})
        return result
    if ledger.record("cluster"):
        log.info("cluster: runs again: %s", ledger.why_stale("cluster", opts, input_fp))
    ledger.start("cluster", opts, input_fp)

    # Isolated images (no verified pair) are not clustered: nothing can register them.
    components = connected_components(graph)
    isolated = sorted(int(c[0]) for c in components if len(c) == 1)
    cores = [c for c in partition_graph(graph, options.max_cluster_size, seed=options.seed) if len(c) > 1]
    expansion = expand_clusters(graph, cores, options.completeness, options.max_overlap, seed=options.seed)
    labels = labels_from_clusters(list(expansion.cores), len(image_ids))
    total_weight = float(weights.sum())
    cut_fraction = cut_weight(graph, labels) / total_weight if total_weight > 0 else 0.0

    clusters_json = {
        "clusters": [
            {
                "id": k,
                "core": [names[i] for i in core],
                "members": [names[i] for i in members],
                "completeness": round(float(stats.completeness), 6),
                "core_size": int(stats.core_size),
                "size": int(stats.size),
            }
            for k, (core, members, stats) in enumerate(zip(expansion.cores, expansion.clusters, expansion.stats))
        ],
        "max_cluster_size": options.max_cluster_size,
        "completeness_ratio": options.completeness,
        "max_overlap": options.max_overlap,
        "maxst": [[int(a), int(b), int(w)] for a, b, w in expansion.maxst_edges],
        "extra_edges": [[int(a), int(b), int(w)] for a, b, w in expansion.extra_edges],
        "lost_edges": [[int(a), int(b), int(n)] for (a, b), n in sorted(expansion.lost_edge_counts.items())],
        "isolated_images": [names[i] for i in isolated],
        "num_images": len(image_ids),
        "num_components": sum(1 for c in components if len(c) > 1),
        "cut_weight_fraction": round(cut_fraction, 6),
        "options": asdict(options),
    }
    write_json_atomic(out, clusters_json)
    ledger.finish("cluster", fingerprint([c["members"] for c in clusters_json["clusters"]]))

    if isolated:
        log.warning("%d image(s) have no verified pair and are left out: %s", len(isolated),
                    ", ".join(names[i] for i in isolated[:5]) + (" ..." if len(isolated) > 5 else ""))
    result = _log_and_summarise(clusters_json, out, names, (ei, ej, weights), recorder, t0)
    update_report(workspace, {"num_clusters": result.num_clusters}, {"cluster": result.time_s})
    log.info("cluster: %d images -> %d clusters (sizes %d-%d), %.1f%% of the edge weight cut, %.2f s",
             result.num_images, result.num_clusters, min(result.cluster_sizes), max(result.cluster_sizes),
             100 * cut_fraction, result.time_s)
    return result


def _reuse(out: Path, names: list[str], graph_arrays, recorder: Recorder, t0: float) -> ClusterResult:
    """A current ``clusters.json``: logged to the recording and summarised, not recomputed."""
    result = _log_and_summarise(read_json(out), out, names, graph_arrays, recorder, t0)
    log.info("cluster: %s is current (same options, same database): skipped, %d clusters", out, result.num_clusters)
    return result


def _log_and_summarise(clusters_json: dict, out: Path, names: list[str], graph_arrays, recorder: Recorder,
                       t0: float) -> ClusterResult:
    ei, ej, weights = graph_arrays
    clusters = clusters_json["clusters"]
    log_clusters(recorder, clusters_json, names, ei, ej, weights, clusters_json["cut_weight_fraction"])
    return ClusterResult(
        num_images=clusters_json["num_images"],
        num_clusters=len(clusters),
        num_isolated=len(clusters_json["isolated_images"]),
        num_components=clusters_json["num_components"],
        cluster_sizes=[c["size"] for c in clusters],
        core_sizes=[c["core_size"] for c in clusters],
        min_completeness=float(min((c["completeness"] for c in clusters), default=0.0)),
        cut_fraction=clusters_json["cut_weight_fraction"],
        time_s=round(time.perf_counter() - t0, 3),
        path=str(out),
    )
