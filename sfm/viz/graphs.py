"""Graphs drawn in a 2D view: nodes as labelled discs, edges as lines whose width, colour and
label carry the edge's weight (Rerun's graph view cannot show edge weights).

The image graph (match, cluster), the cluster graph with its MaxST (cluster) and the cluster
graph of the local models with its MinST and anchor (merge) are all drawn this way, with a
deterministic layout (:func:`graph_layout`), so the same run gives the same picture; the walkthrough
(``tools/walkthrough.py``) draws its figures with the same layout.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sfm.viz.recorder import Recorder

CANVAS = 1000.0  # the layout's box, in the 2D view's units
FORCE_MAX_NODES = 150  # above: a spectral layout (Kamada-Kawai is quadratic in the nodes)
_LAYOUTS: dict[bytes, np.ndarray] = {}  # the last layouts: match and cluster draw the same graph


def graph_layout(n: int, i: np.ndarray, j: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``(n, 2)`` node positions in ``[0, CANVAS]^2``, the same for the same graph: up to
    :data:`FORCE_MAX_NODES` nodes, Kamada-Kawai's layout (graph distances drawn as distances)
    with an edge as long as ``1 / sqrt(w / w_max)``, so strongly matched images sit together;
    above, a spectral layout."""
    import networkx as nx

    if n == 0:
        return np.zeros((0, 2))
    w = np.asarray(weights, dtype=np.float64)
    key = b"".join([str(n).encode(), np.asarray(i, np.int64).tobytes(), np.asarray(j, np.int64).tobytes(), w.tobytes()])
    if key in _LAYOUTS:
        return _LAYOUTS[key].copy()
    top = max(float(w.max(initial=0.0)), 1e-12)
    g = nx.Graph()
    g.add_nodes_from(range(n))
    for a, b, x in zip(np.asarray(i).tolist(), np.asarray(j).tolist(), w.tolist()):
        g.add_edge(int(a), int(b), length=1.0 / np.sqrt(max(x, 1e-12) / top), weight=x / top)
    if n == 1:
        pos = {0: np.zeros(2)}
    elif n <= FORCE_MAX_NODES:
        lengths = dict(nx.shortest_path_length(g, weight="length"))
        unreachable = 1.5 * max((d for row in lengths.values() for d in row.values() if d > 0), default=1.0)
        dist = {a: {b: lengths[a].get(b, unreachable) for b in range(n)} for a in range(n)}
        pos = nx.kamada_kawai_layout(g, dist=dist)
    else:
        pos = nx.spectral_layout(g, weight="weight")
    xy = np.array([pos[k] for k in range(n)], dtype=np.float64)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    _LAYOUTS.clear()
    _LAYOUTS[key] = 0.05 * CANVAS + 0.9 * CANVAS * (xy - lo) / span.max()
    return _LAYOUTS[key].copy()


def draw_graph(recorder: Recorder, entity: str, positions: np.ndarray, labels: Sequence[str],
               node_colors: Sequence, edges: Sequence[tuple[int, int]], edge_colors: Sequence | np.ndarray,
               edge_widths: Sequence[float] | np.ndarray, edge_labels: Sequence[str] | None = None,
               node_radii: Sequence[float] | np.ndarray | None = None,
               halos: Sequence[tuple[int, tuple[int, int, int], float]] = ()) -> None:
    """``<entity>`` (nodes: discs with labels), ``<entity>/edges`` (lines) and, when given,
    ``<entity>/halos`` (rings drawn under nodes: ``(node, colour, radius)``)."""
    if not recorder.enabled:
        return
    import rerun as rr

    positions = np.asarray(positions, dtype=np.float64)
    radii = np.full(len(positions), 10.0) if node_radii is None else np.asarray(node_radii, dtype=np.float64)
    if len(edges):
        strips = np.array([[positions[a], positions[b]] for a, b in edges])
        recorder.log(f"{entity}/edges", rr.LineStrips2D(strips, colors=np.asarray(edge_colors),
                                                        radii=np.asarray(edge_widths, dtype=np.float64) / 2,
                                                        labels=list(edge_labels) if edge_labels is not None else None,
                                                        draw_order=10.0))
    else:
        recorder.log(f"{entity}/edges", rr.Clear(recursive=False))
    if halos:
        recorder.log(f"{entity}/halos", rr.Points2D([positions[k] for k, _, _ in halos], colors=[c for _, c, _ in halos],
                                                    radii=[r for _, _, r in halos], draw_order=20.0))
    recorder.log(entity, rr.Points2D(positions, colors=list(node_colors), radii=radii, labels=list(labels),
                                     draw_order=30.0))
