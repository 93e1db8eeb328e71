"""The ``cluster`` stage: image graph from the database -> clusters.json (paper section 3.1).

Reads the verified pairs from ``WORK/database.db`` (the image graph of section 3.1.1: one node per
image, edge weight = number of verified inlier matches), cuts it with normalized cuts into cores
small enough to leave the expansion room and expands the cores along the maximum spanning tree
of the cluster graph (and a backup forest for the merge), never beyond ``max_cluster_size``
images, until every cluster's completeness reaches ``completeness`` (Algorithm 1;
``graph.clustering``, ``graph.partition`` and ``graph.expansion`` do the work on arrays).  A
connected component that fits in ``max_cluster_size`` is one cluster.  A cluster the graph
cannot bring to the completeness within the bound, and a MaxST edge with fewer than
``min_overlap`` common images, are logged as warnings naming them and why, and listed in
``clusters.json`` and the report.  Images without any verified pair cannot be reconstructed
and are listed as isolated, not clustered.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from graph.clustering import cluster_images
from graph.expansion import ExpansionResult
from graph.image_graph import build_image_graph, connected_components
from graph.partition import cut_weight, labels_from_clusters
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
    warnings: list[str]
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
        return _reuse(out, names, (ei, ej, weights), recorder, t0)
    if ledger.record("cluster"):
        log.info("cluster: runs again: %s", ledger.why_stale("cluster", opts, input_fp))
    ledger.start("cluster", opts, input_fp)

    # Isolated images (no verified pair) are not clustered: nothing can register them.
    components = connected_components(graph)
    clustering = cluster_images(graph, options.max_cluster_size, options.completeness, options.max_overlap,
                                options.min_overlap, seed=options.seed)
    expansion, isolated = clustering.expansion, clustering.isolated.tolist()
    incomplete = {c.cluster: c for c in expansion.incomplete}
    warnings = expansion_warnings(expansion)
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
                "below_completeness": incomplete[k].reason if k in incomplete else None,
            }
            for k, (core, members, stats) in enumerate(zip(expansion.cores, expansion.clusters, expansion.stats))
        ],
        "max_cluster_size": options.max_cluster_size,
        "completeness_ratio": options.completeness,
        "max_overlap": options.max_overlap,
        "core_size_bound": clustering.core_size_bound,
        "recut_size_bound": clustering.recut_size_bound,
        "recut_cores": clustering.recut_cores,
        "min_overlap": options.min_overlap,
        "maxst": [[int(a), int(b), int(w)] for a, b, w in expansion.maxst_edges],
        "backup_edges": [[int(a), int(b), int(w)] for a, b, w in expansion.backup_edges],
        "common_images": [[a, b, n] for (a, b), n in sorted(expansion.common_images.items())],
        "thin_overlaps": [[t.k1, t.k2, t.common, t.reason] for t in expansion.thin_overlaps],
        "extra_edges": [[int(a), int(b), int(w)] for a, b, w in expansion.extra_edges],
        "lost_edges": [[int(a), int(b), int(n)] for (a, b), n in sorted(expansion.lost_edge_counts.items())],
        "isolated_images": [names[i] for i in isolated],
        "num_images": len(image_ids),
        "num_components": sum(1 for c in components if len(c) > 1),
        "cut_weight_fraction": round(cut_fraction, 6),
        "options": asdict(options),
        "warnings": warnings,
    }
    write_json_atomic(out, clusters_json)
    ledger.finish("cluster", fingerprint([c["members"] for c in clusters_json["clusters"]]))

    if isolated:
        log.warning("%d image(s) have no verified pair and are left out: %s", len(isolated),
                    ", ".join(names[i] for i in isolated[:5]) + (" ..." if len(isolated) > 5 else ""))
    result = _log_and_summarise(clusters_json, out, names, (ei, ej, weights), recorder, t0)
    _report_warnings(workspace, result)
    log.info("cluster: %d images -> %d clusters (cores %d-%d, clusters %d-%d, bound %d), %.1f%% of the edge weight cut, "
             "%.2f s", result.num_images, result.num_clusters, min(result.core_sizes), max(result.core_sizes),
             min(result.cluster_sizes), max(result.cluster_sizes), options.max_cluster_size, 100 * cut_fraction,
             result.time_s)
    return result


_WHY_INCOMPLETE = {
    "bound": "it is full at --max-cluster-size {bound}",
    "max_overlap": "its {pairs} cluster pairs are used up, some at the --overlap {o_max} images per pair",
    "lost_edges": "all {lost} image edges to other clusters are used",
}
_WHY_THIN = {
    "bound": "{full} full at --max-cluster-size {bound}",
    "max_overlap": "--overlap {o_max} images were added along it",
    "lost_edges": "the image graph joins them by only {lost} image edges, all used",
}


def expansion_warnings(expansion: ExpansionResult) -> list[str]:
    """One line per cluster left below C and per MaxST edge left below ``min_overlap`` common
    images, naming it (``C<k>``, the label ``map`` gives it) and saying why."""
    lost_of = [0] * len(expansion.clusters)
    pairs_of = [0] * len(expansion.clusters)
    for (a, b), n in expansion.lost_edge_counts.items():
        for k in (a, b):
            lost_of[k] += n
            pairs_of[k] += 1
    fmt = {"bound": expansion.max_cluster_size, "o_max": expansion.max_overlap}
    out = []
    for c in expansion.incomplete:
        why = _WHY_INCOMPLETE[c.reason].format(**fmt, pairs=pairs_of[c.cluster], lost=lost_of[c.cluster])
        out.append(f"cluster C{c.cluster} ({c.size} images) reaches completeness {c.completeness:.2f}, below "
                   f"--completeness {expansion.completeness_ratio:g}: {why}")
    for t in expansion.thin_overlaps:
        full = [f"C{k}" for k in (t.k1, t.k2) if expansion.stats[k].size >= (expansion.max_cluster_size or math.inf)]
        full_text = " and ".join(full) + (" are" if len(full) == 2 else " is")
        why = _WHY_THIN[t.reason].format(**fmt, full=full_text, lost=expansion.lost_edge_counts[(t.k1, t.k2)])
        out.append(f"clusters C{t.k1} and C{t.k2}, which the merge aligns (a maximum-spanning-tree edge), share "
                   f"{t.common} images, fewer than --min-overlap {expansion.min_overlap}: {why}")
    return out


def _reuse(out: Path, names: list[str], graph_arrays, recorder: Recorder, t0: float) -> ClusterResult:
    """A current ``clusters.json``: logged to the recording and summarised, not recomputed."""
    result = _log_and_summarise(read_json(out), out, names, graph_arrays, recorder, t0)
    log.info("cluster: %s is current (same options, same database): skipped, %d clusters", out, result.num_clusters)
    _report_warnings(out.parent, result)
    return result


def _report_warnings(workspace: Path, result: ClusterResult) -> None:
    """The clusters' warnings to the log and to ``WORK/report.json`` (its ``warnings`` start
    afresh here; ``map`` and ``merge`` keep these and add their own)."""
    for warning in result.warnings:
        log.warning("%s", warning)
    update_report(workspace, {"num_clusters": result.num_clusters, "warnings": result.warnings},
                  {"cluster": result.time_s})



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
        warnings=list(clusters_json.get("warnings", [])),
        cut_fraction=clusters_json["cut_weight_fraction"],
        time_s=round(time.perf_counter() - t0, 3),
        path=str(out),
    )
