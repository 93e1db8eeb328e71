"""Approximate nearest neighbours of SIFT descriptors through one inverted file per image.

Exact matching compares every descriptor of one image with every descriptor of the other, so
its cost grows with the product of their feature counts.  An inverted file (Sivic & Zisserman
2003; the IVF index of faiss, which COLMAP 4's matcher builds per image) cuts the descriptor
space into cells and compares a query only with the descriptors of its own cell.

- **Cells from the image itself.**  Each image gets a k-means vocabulary of its own
  descriptors (spherical: centroids of unit length, similarity = dot product), seeded, about
  ``DESCRIPTORS_PER_CELL`` descriptors a cell.  Nothing is learned from the other images, so a
  pair of images gives the same matches in every workspace, as the exact matcher does.
- **Soft assignment.**  A query goes to the one cell whose centroid is nearest; a descriptor of
  the indexed image is listed in every cell whose centroid is within ``CELL_MARGIN`` of its
  nearest centroid's similarity.  That is what keeps true matches: for a query ``q`` in cell
  ``c_q`` and its neighbour ``x`` nearest to ``c_x``,
  ``x.c_q - x.c_x >= -|x - q| |c_q - c_x|``, so ``x`` is listed in ``c_q`` whenever the
  difference of the two images' descriptors, projected on the line between the centroids,
  stays within the margin.  Descriptors deep inside a cell are listed once, those near a
  boundary in each cell they border, so the work goes where the ambiguity is (a fixed number
  of cells per descriptor loses more matches for the same work).
- **Blocked products.**  Per cell, the queries and the listed descriptors meet in one matrix
  product (BLAS), and the nearest and second-nearest similarities are taken from it, so Lowe's
  ratio test has both distances.  A second neighbour outside the cell is missed, which can only
  let an ambiguous match through the ratio test; verification sees it as an outlier.
- **Mutual check for free.**  A descriptor of the indexed image is listed in every cell near it,
  so the queries it meets in those cells are its own candidates, found by the same condition
  with the images' roles exchanged: the best of them, taken from the same products, is the
  mutual check's nearest neighbour, and no second search is needed.

The margin and the cell size are chosen by measurement against the exact matcher on real photos
(``tools/bench_scale.py``: the share of its verified inliers kept, and the time per pair).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DESCRIPTORS_PER_CELL = 64  # before soft assignment; cells are a power of two in number
MIN_CELLS, MAX_CELLS = 4, 512
CELL_MARGIN = 0.06  # cosine similarity to the centroids
KMEANS_ITERATIONS = 8
KMEANS_SAMPLES_PER_CELL = 40


def number_of_cells(num_descriptors: int) -> int:
    """The power of two nearest ``num_descriptors / DESCRIPTORS_PER_CELL``, within bounds."""
    target = max(num_descriptors / DESCRIPTORS_PER_CELL, 1.0)
    return int(np.clip(2 ** round(float(np.log2(target))), MIN_CELLS, MAX_CELLS))


def spherical_kmeans(unit: np.ndarray, num_cells: int, seed: int) -> np.ndarray:
    """(K, D) unit centroids of ``unit`` rows (Lloyd's iterations on a seeded sample of at most
    ``KMEANS_SAMPLES_PER_CELL`` rows a cell, each centroid the normalised mean of its rows; a
    cell that empties keeps its centroid)."""
    rng = np.random.default_rng(seed)
    n = len(unit)
    sample = unit[np.sort(rng.choice(n, min(n, KMEANS_SAMPLES_PER_CELL * num_cells), replace=False))]
    centroids = sample[rng.choice(len(sample), num_cells, replace=False)].copy()
    for _ in range(KMEANS_ITERATIONS):
        cell = np.argmax(sample @ centroids.T, axis=1)
        sums = np.zeros_like(centroids)
        order = np.argsort(cell, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(cell[order]) != 0])
        sums[cell[order][starts]] = np.add.reduceat(sample[order], starts, axis=0)
        norms = np.linalg.norm(sums, axis=1)
        filled = norms > 1e-12
        centroids[filled] = sums[filled] / norms[filled, None]
    return centroids


@dataclass(frozen=True)
class InvertedFile:
    """One image's unit descriptors listed by cell: ``members[bounds[c]:bounds[c + 1]]`` are
    the rows listed in cell ``c`` (soft assignment).  A search gathers a cell's rows when it
    visits it: holding them in cell order would take ``members / descriptors`` times the memory
    for a saving the measurements did not show."""

    descriptors: np.ndarray  # (N, D) float32 unit rows
    centroids: np.ndarray  # (K, D) float32 unit rows
    members: np.ndarray  # (M,) int64, M >= N
    bounds: np.ndarray  # (K + 1,) int64

    @classmethod
    def build(cls, unit: np.ndarray, seed: int = 0, margin: float = CELL_MARGIN) -> InvertedFile:
        """The inverted file of unit-normalised float32 descriptors (``len(unit) >= 1``)."""
        unit = np.ascontiguousarray(unit, np.float32)
        centroids = spherical_kmeans(unit, min(number_of_cells(len(unit)), len(unit)), seed)
        similarity = unit @ centroids.T
        row, cell = np.nonzero(similarity >= similarity.max(axis=1, keepdims=True) - margin)
        order = np.argsort(cell, kind="stable")  # by cell, rows ascending within a cell
        members = row[order].astype(np.int64)
        bounds = np.searchsorted(cell[order], np.arange(len(centroids) + 1)).astype(np.int64)
        return cls(unit, centroids, members, bounds)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.descriptors, self.centroids, self.members, self.bounds))

    def search(self, queries: np.ndarray):
        """Nearest neighbours of unit query rows among the listed descriptors of each query's
        cell: per query the row of its nearest (-1 when its cell is empty) and the best and
        second-best similarities (-inf when absent); per indexed descriptor the best similarity
        of a query that met it (-inf when none did), the mutual check's side: a descriptor is
        listed in every cell near it, so the queries it meets are those of all those cells."""
        n = len(queries)
        best = np.full(n, -1, np.int64)
        sim1 = np.full(n, -np.inf, np.float32)
        sim2 = np.full(n, -np.inf, np.float32)
        nearest_query = np.full(len(self.descriptors), -np.inf, np.float32)
        if n == 0:
            return best, sim1, sim2, nearest_query
        cell = np.argmax(queries @ self.centroids.T, axis=1)
        order = np.argsort(cell, kind="stable")
        sorted_queries = queries[order]
        qbounds = np.searchsorted(cell[order], np.arange(len(self.centroids) + 1))
        for c in np.unique(cell).tolist():
            q0, q1 = qbounds[c], qbounds[c + 1]
            listed = self.members[self.bounds[c]:self.bounds[c + 1]]
            if len(listed) == 0:
                continue
            sim = sorted_queries[q0:q1] @ self.descriptors[listed].T
            nearest_query[listed] = np.maximum(nearest_query[listed], sim.max(axis=0))  # a row once a cell
            rows = np.arange(q1 - q0)
            j = np.argmax(sim, axis=1)
            out = order[q0:q1]
            best[out] = listed[j]
            sim1[out] = sim[rows, j]
            if len(listed) > 1:
                sim[rows, j] = -np.inf
                sim2[out] = sim.max(axis=1)
        return best, sim1, sim2, nearest_query


def match_inverted(index1: InvertedFile, index2: InvertedFile, max_ratio: float = 0.8, cross_check: bool = True,
                   max_distance: float | None = None) -> np.ndarray:  # fmt: skip
    """(M, 2) int64 matches (row in 1, row in 2), sorted by row in 1: each descriptor of image 1
    with its nearest descriptor of image 2 found through ``index2``, kept when it passes Lowe's
    ratio test on Euclidean distances, the mutual check when ``cross_check`` (among the
    descriptors of image 1 that met the partner in a cell), and ``distance <= max_distance`` when given."""
    best, sim1, sim2, nearest_query = index2.search(index1.descriptors)
    dist2_1 = np.maximum(2.0 - 2.0 * sim1, 0.0)
    dist2_2 = np.maximum(2.0 - 2.0 * sim2, 0.0)  # inf when there is no second neighbour
    keep = (best >= 0) & (dist2_1 < (max_ratio**2) * dist2_2)
    if max_distance is not None:
        keep &= dist2_1 <= max_distance**2
    if cross_check:  # no other query that met the partner is nearer to it (a tie counts)
        keep &= sim1 >= nearest_query[np.maximum(best, 0)]
    rows = np.flatnonzero(keep)
    return np.stack([rows, best[rows]], axis=1)
