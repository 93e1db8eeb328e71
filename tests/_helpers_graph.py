"""Random weighted graphs for the graph/ property tests (hypothesis)."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from graph.image_graph import ImageGraph, build_image_graph


@st.composite
def random_graphs(draw, max_nodes: int = 120, distinct_weights: bool = True) -> ImageGraph:
    """Erdos-Renyi or random geometric weighted graphs, sparse to dense, often disconnected.

    ``distinct_weights=False`` draws few distinct weights, so that ties in "strongest edges
    first" orders are exercised."""
    n = draw(st.integers(min_value=1, max_value=max_nodes))
    rng = np.random.default_rng(draw(st.integers(min_value=0, max_value=2**32 - 1)))
    if draw(st.booleans()):
        ii, jj = np.triu_indices(n, 1)
        keep = rng.random(ii.size) < draw(st.floats(min_value=0.0, max_value=0.3))
        ii, jj = ii[keep], jj[keep]
    else:
        pts = rng.random((n, 2))
        radius = draw(st.floats(min_value=0.05, max_value=0.4))
        pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray").reshape(-1, 2)
        ii, jj = pairs[:, 0], pairs[:, 1]
    weights = rng.integers(1, 300, ii.size) if distinct_weights else rng.integers(1, 6, ii.size) * 20
    return build_image_graph(n, ii, jj, weights)
