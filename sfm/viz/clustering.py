"""Rerun views of the cluster stage (paper section 3.1, Alg. 1): the image graph coloured by
cluster, and the cluster graph with its maximum spanning tree."""

from __future__ import annotations

import numpy as np

from sfm.viz.graphs import draw_graph, graph_layout
from sfm.viz.palette import GREY, cluster_color
from sfm.viz.recorder import Recorder
from sfm.viz.tour import cluster_text

MAXST_COLOR = (255, 200, 0)  # Alg. 1 line 5: the MaxST's edges
EXTRA_COLOR = (120, 170, 255)  # Alg. 1 lines 10-12: random edges added for completeness


def log_clusters(recorder: Recorder, data: dict, names: list[str], ei: np.ndarray, ej: np.ndarray,
                 weights: np.ndarray, cut_fraction: float) -> None:
    """At stage cluster: ``graph/images`` with each image in its core's colour, a ring in the
    colour of each other cluster it was copied into (its overlap), the edges the cut removed in
    grey; ``graph/clusters``: the cluster graph (Alg. 1 lines 3-5: one node per cluster, an edge
    per pair of cores with lost image edges, labelled with their number), the MaxST's edges
    thick and gold, the random edges added for completeness (lines 10-12) blue, each cluster
    labelled with its sizes and completeness; and the stage's text of the tour."""
    if not recorder.enabled:
        return
    recorder.stage("cluster")
    clusters = data["clusters"]
    node = {n: k for k, n in enumerate(names)}
    core_of = np.full(len(names), -1, dtype=np.int64)
    for c in clusters:
        core_of[[node[n] for n in c["core"]]] = c["id"]
    positions = graph_layout(len(names), ei, ej, weights)
    same = (core_of[ei] == core_of[ej]) & (core_of[ei] >= 0)
    edge_colors = np.array([cluster_color(int(core_of[a])) if s else GREY for a, s in zip(ei.tolist(), same)],
                           dtype=np.uint8).reshape(-1, 3)
    w = np.asarray(weights, dtype=np.float64)
    widths = np.where(same, 1.0 + 3.0 * w / max(w.max(initial=1), 1), 0.6)
    halos = []
    copies: dict[int, list[int]] = {}
    for c in clusters:
        core = set(c["core"])
        for n in c["members"]:
            if n not in core:
                copies.setdefault(node[n], []).append(c["id"])
    for k, others in sorted(copies.items()):
        for r, cid in enumerate(others):
            halos.append((k, cluster_color(cid), 10.0 + 4.0 * (len(others) - r)))
    labels = [n + (" (also in " + ", ".join(f"C{c}" for c in copies[k]) + ")" if k in copies else "")
              for k, n in enumerate(names)]
    draw_graph(recorder, "graph/images", positions, labels,
               node_colors=[cluster_color(int(c)) if c >= 0 else GREY for c in core_of],
               edges=list(zip(ei.tolist(), ej.tolist())), edge_colors=edge_colors, edge_widths=widths,
               edge_labels=[str(int(x)) for x in w], halos=halos)

    maxst = {(a, b) for a, b, _ in data["maxst"]}
    extra = {(a, b) for a, b, _ in data["extra_edges"]}
    lost = [(a, b, n) for a, b, n in data["lost_edges"]]
    arrays = np.array(lost, dtype=np.int64).reshape(-1, 3)
    centres = graph_layout(len(clusters), arrays[:, 0], arrays[:, 1], arrays[:, 2])
    colors = [MAXST_COLOR if (a, b) in maxst else EXTRA_COLOR if (a, b) in extra else GREY for a, b, _ in lost]
    draw_graph(recorder, "graph/clusters", centres,
               [f"C{c['id']}: {c['core_size']} core + {c['size'] - c['core_size']} copied, "
                f"completeness {c['completeness']:.2f}" for c in clusters],
               node_colors=[cluster_color(c["id"]) for c in clusters],
               node_radii=[8.0 + 2.0 * np.sqrt(c["size"]) for c in clusters],
               edges=[(a, b) for a, b, _ in lost], edge_colors=colors,
               edge_widths=[8.0 if (a, b) in maxst else 3.0 if (a, b) in extra else 1.5 for a, b, _ in lost],
               edge_labels=[f"{n} lost" for _, _, n in lost])
    recorder.tour("cluster", cluster_text(data, cut_fraction, len(names)))
