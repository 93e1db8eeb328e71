"""Nearest-neighbour matching of two images' SIFT descriptors (the ratio test and mutual check).

Descriptor matching: nearest neighbour on unit-normalised float32 descriptors, Lowe's ratio test
on Euclidean distances (``d1 < max_ratio * d2``) and a mutual check (the match must also be the
nearest neighbour of its partner). ``brute`` is exact: blocked BLAS products (2 - 2 x.y is the
squared distance of unit vectors), so its cost grows with the product of the two images'
feature counts. ``ivf`` is approximate: an inverted file per image (``sfm.matching.inverted_file``)
compares a descriptor only with those of its cell, a small share of the product. ``flann`` is a
KD-tree (4 trees, 64 checks), approximate, seeded through ``cv2.setRNGSeed`` so it is
deterministic. ``auto`` takes brute below ``IVF_MIN_PRODUCT`` descriptor pairs (about 1.4k x
1.4k features), where building two inverted files costs more than the product, and ivf above.
"""

from __future__ import annotations

import threading

import cv2
import numpy as np

from sfm.matching.inverted_file import InvertedFile, match_inverted

IVF_MIN_PRODUCT = 2**21
MATCHERS = ("auto", "brute", "ivf", "flann")


def normalize_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """float32 rows of unit L2 norm (uint8 RootSIFT rows are unit vectors times ~512)."""
    d = np.asarray(descriptors, np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


# Similarities one block of the brute-force product holds (1 MiB of float32, a share of a
# core's L2 cache): the passes over a block after its product read it from there.
BLOCK_SIMILARITIES = 2**18
_SCRATCH = threading.local()  # per thread: one reused block buffer (no 1 MB allocation per block)


def _nearest_brute(d1: np.ndarray, d2: np.ndarray, block: int | None = None, d2t: np.ndarray | None = None):
    """Exact: best and second-best squared distances 1->2, and whether each row's best match
    is also the nearest of its partner among all rows of 1 (the mutual check; a tie counts).

    Rows go in blocks of ``block`` (default: ``BLOCK_SIMILARITIES`` products, at least 128
    rows) computed into a reused buffer.  The column maxima come from ``max(axis=0)``, a
    contiguous running reduction; an ``argmax(axis=0)`` per block (the nearest row's index)
    would transpose the block into a copy, a second pass over memory for every block."""
    d1, d2 = np.asarray(d1, np.float32), np.asarray(d2, np.float32)  # the buffer's type: BLAS's sgemm
    n1, n2 = len(d1), len(d2)
    block = block or max(128, BLOCK_SIMILARITIES // max(n2, 1))
    scratch = getattr(_SCRATCH, "buffer", None)
    if scratch is None or scratch.size < min(block, n1) * n2:
        scratch = _SCRATCH.buffer = np.empty(min(block, n1) * n2, np.float32)
    best = np.zeros(n1, np.int64)
    sim1 = np.full(n1, -np.inf, np.float32)
    sim2 = np.full(n1, -np.inf, np.float32)
    col_max = np.full(n2, -np.inf, np.float32)
    d2t = np.ascontiguousarray(d2.T) if d2t is None else np.asarray(d2t, np.float32)
    for start in range(0, n1, block):
        rows = np.arange(min(block, n1 - start))
        sim = np.matmul(d1[start : start + block], d2t, out=scratch[: len(rows) * n2].reshape(len(rows), n2))
        j = np.argmax(sim, axis=1)
        s = sim[rows, j]
        best[start : start + block], sim1[start : start + block] = j, s
        np.maximum(col_max, sim.max(axis=0), out=col_max)
        if n2 > 1:
            sim[rows, j] = -np.inf
            sim2[start : start + block] = sim.max(axis=1)
    to_dist2 = lambda s: np.maximum(2.0 - 2.0 * s, 0.0)
    return best, to_dist2(sim1), to_dist2(sim2), sim1 >= col_max[best]


def _nearest_flann(d1: np.ndarray, d2: np.ndarray, seed: int):
    """Approximate (KD-tree, seeded), same outputs as :func:`_nearest_brute` (mutual: the
    partner's approximate nearest neighbour is the row)."""
    cv2.setRNGSeed(int(seed))
    index2 = cv2.flann_Index(d2, {"algorithm": 1, "trees": 4})
    k = min(2, len(d2))
    idx, dist2 = index2.knnSearch(d1, k, params={"checks": 64})
    second = dist2[:, 1] if k == 2 else np.full(len(d1), np.inf, np.float32)
    cv2.setRNGSeed(int(seed) + 1)
    index1 = cv2.flann_Index(d1, {"algorithm": 1, "trees": 4})
    back, _ = index1.knnSearch(d2, 1, params={"checks": 64})
    best = idx[:, 0].astype(np.int64)
    return best, dist2[:, 0], second, back[best, 0] == np.arange(len(d1))


def resolve_matcher(matcher: str, n1: int, n2: int) -> str:
    """The nearest-neighbour search ``matcher`` means for images of ``n1`` and ``n2`` descriptors
    (``auto``: ivf from ``IVF_MIN_PRODUCT`` descriptor pairs, brute below)."""
    if matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {'|'.join(MATCHERS)}, got {matcher!r}")
    if matcher == "auto":
        return "ivf" if n1 * n2 >= IVF_MIN_PRODUCT else "brute"
    return matcher


def match_descriptors(
    descriptors1: np.ndarray, descriptors2: np.ndarray, max_ratio: float = 0.8,
    cross_check: bool = True, matcher: str = "auto", max_distance: float | None = None,
    seed: int = 0, normalized: bool = False, transposed2: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(M, 2) int64 matches (index in 1, index in 2): nearest neighbours passing Lowe's ratio
    test on Euclidean distances of unit-normalised descriptors, the mutual check when
    ``cross_check``, and ``distance <= max_distance`` when given. Sorted by index in 1.
    ``normalized``: both are :func:`normalize_descriptors` output already, and ``transposed2``
    (optional) is ``descriptors2.T`` C-contiguous: the match stage caches both per image, so
    an image is normalised and transposed once, not once per pair it is in."""
    unit = (lambda d: d) if normalized else normalize_descriptors
    d1, d2 = unit(descriptors1), unit(descriptors2)
    if len(d1) == 0 or len(d2) == 0:
        return np.zeros((0, 2), np.int64)
    matcher = resolve_matcher(matcher, len(d1), len(d2))
    if matcher == "ivf":
        return match_inverted(InvertedFile.build(d1, seed), InvertedFile.build(d2, seed), max_ratio, cross_check,
                              max_distance)  # fmt: skip
    if matcher == "flann" and min(len(d1), len(d2)) >= 2:
        best, dist2_1, dist2_2, mutual = _nearest_flann(d1, d2, seed)
    else:
        best, dist2_1, dist2_2, mutual = _nearest_brute(d1, d2, d2t=transposed2 if normalized else None)
    keep = dist2_1 < (max_ratio**2) * dist2_2
    if cross_check:
        keep &= mutual
    if max_distance is not None:
        keep &= dist2_1 <= max_distance**2
    rows = np.flatnonzero(keep)
    return np.stack([rows, best[rows]], axis=1)
