"""Which image pairs to match: exhaustive, retrieval, sequential.

- ``exhaustive``: every pair, n (n - 1) / 2 of them.
- ``retrieval``: one global descriptor per image, VLAD (Jegou et al. 2010; intra-normalised as in
  Arandjelovic & Zisserman 2013) over a small vocabulary learned from the dataset's own
  descriptors with a seeded ``MiniBatchKMeans``; similarity is the dot product of the VLAD
  vectors and every image keeps its ``top_k`` most similar images (symmetric union).
- ``auto``: exhaustive below ``exhaustive_threshold`` images, retrieval at or above it.
- ``spatial``: retrieval, plus each image's ``spatial_neighbors`` nearest images by position
  (GPS in a local metric frame) no further than ``spatial_max_distance`` (COLMAP's spatial
  matcher, OpenSfM's GPS neighbours: drone and street sets); images without a position get
  their retrieval pairs only.
- ``sequential`` window N > 0 adds (i, i+1 .. i+N) in the order the ids are given (callers pass
  name order), on top of the pairs above.
- ``extension_pairs``: the pairs of images added to a finished model, each with at least one
  new image: new x new by the rule above, and each new image with its ``top_k`` most similar
  old images (VLAD over a vocabulary learned from the new images), so the matching grows with
  the new images, not with the whole set.

A pair is ``(id1, id2)`` with ``id1 < id2``; results are sorted unique ``(P, 2)`` int64 arrays.
No I/O here: retrieval reads descriptors through a callable the caller provides, twice per image
(vocabulary sample, then VLAD), so never more than one image's descriptors are held at a time.
The same input and seed give the same pairs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

PAIR_METHODS = ("auto", "exhaustive", "retrieval", "spatial")
VOCABULARY_WORDS = 64
SAMPLES_PER_IMAGE = 200
MAX_VOCABULARY_SAMPLES = 100_000


def _unique_pairs(pairs: np.ndarray) -> np.ndarray:
    """Rows sorted so that id1 < id2, self pairs dropped, sorted unique."""
    pairs = np.sort(np.asarray(pairs, np.int64).reshape(-1, 2), axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    return np.unique(pairs, axis=0) if len(pairs) else np.zeros((0, 2), np.int64)


def exhaustive_pairs(image_ids: Sequence[int]) -> np.ndarray:
    """All n (n - 1) / 2 pairs of the given images."""
    ids = np.asarray(image_ids, np.int64)
    i, j = np.triu_indices(len(ids), k=1)
    return _unique_pairs(np.stack([ids[i], ids[j]], axis=1))


def sequential_pairs(image_ids: Sequence[int], window: int) -> np.ndarray:
    """Pairs (i, i+1 .. i+window) of consecutive images in the given order (window 0: none)."""
    ids = np.asarray(image_ids, np.int64)
    parts = [np.stack([ids[:-k], ids[k:]], axis=1) for k in range(1, min(window, len(ids) - 1) + 1)]
    return _unique_pairs(np.concatenate(parts)) if parts else np.zeros((0, 2), np.int64)


def _normalized(descriptors: np.ndarray) -> np.ndarray:
    """float32 rows of unit L2 norm (RootSIFT uint8 rows are unit vectors up to a scale)."""
    d = np.asarray(descriptors, np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def vocabulary_sample(descriptors: np.ndarray, count: int, seed: int, image_id: int) -> np.ndarray:
    """Up to ``count`` rows of one image's descriptors, drawn with a seed of (seed, image_id)."""
    rng = np.random.default_rng([int(seed), int(image_id)])
    n = len(descriptors)
    rows = np.sort(rng.choice(n, size=min(count, n), replace=False)) if n else np.zeros(0, int)
    return _normalized(descriptors[rows])


def learn_vocabulary(
    samples: np.ndarray, num_words: int = VOCABULARY_WORDS, seed: int = 0
) -> np.ndarray:
    """(K, D) float32 visual words: seeded MiniBatchKMeans of unit-normalised descriptors.

    Runs on one thread: OpenMP's busy-waiting threads stall on a machine whose cores are
    taken by other work (the other workers of a run), and the result does not depend on the
    machine."""
    from sklearn.cluster import MiniBatchKMeans
    from threadpoolctl import threadpool_limits

    samples = _normalized(samples)
    k = int(min(num_words, len(samples)))
    if k < 1:
        raise ValueError("no descriptors to learn a vocabulary from")
    kmeans = MiniBatchKMeans(n_clusters=k, random_state=int(seed), batch_size=4096, n_init=3,
                             max_iter=50)  # fmt: skip
    with threadpool_limits(limits=1):
        return kmeans.fit(samples).cluster_centers_.astype(np.float32)


def vlad(descriptors: np.ndarray, vocabulary: np.ndarray) -> np.ndarray:
    """VLAD vector (K * D,) of one image: residuals to the nearest word summed per word, each
    word's block L2-normalised (intra-normalisation), then signed square root, then global L2."""
    k, dim = vocabulary.shape
    out = np.zeros((k, dim), np.float32)
    if len(descriptors):
        d = _normalized(descriptors)
        words = np.argmax(d @ vocabulary.T - 0.5 * np.sum(vocabulary**2, axis=1), axis=1)
        np.add.at(out, words, d - vocabulary[words])
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    out = np.sign(out) * np.sqrt(np.abs(out))
    out = out.ravel()
    return out / max(float(np.linalg.norm(out)), 1e-12)


def retrieval_pairs(
    image_ids: Sequence[int], global_descriptors: np.ndarray, top_k: int
) -> np.ndarray:
    """Each image's ``top_k`` most similar images by dot product (ties: lower index first),
    symmetric union."""
    ids = np.asarray(image_ids, np.int64)
    g = np.asarray(global_descriptors, np.float32)
    n = len(ids)
    k = min(int(top_k), n - 1)
    if k < 1:
        return np.zeros((0, 2), np.int64)
    parts = []
    for start in range(0, n, 1024):
        sim = g[start : start + 1024] @ g.T
        rows = np.arange(sim.shape[0])
        sim[rows, start + rows] = -np.inf  # never the image itself
        order = np.argsort(-sim, axis=1, kind="stable")[:, :k]
        parts.append(np.stack([np.repeat(ids[start + rows], k), ids[order.ravel()]], axis=1))
    return _unique_pairs(np.concatenate(parts))


def spatial_pairs(image_ids: Sequence[int], positions: np.ndarray, neighbors: int, max_distance: float) -> np.ndarray:
    """Each image with its ``neighbors`` nearest images by ``positions`` (N, 3) in metres, up to
    ``max_distance`` away (0: any distance); rows with a non-finite position take no part."""
    from scipy.spatial import cKDTree

    ids = np.asarray(image_ids, np.int64)
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    known = np.flatnonzero(np.all(np.isfinite(pos), axis=1))
    k = min(int(neighbors), len(known) - 1)
    if k < 1:
        return np.zeros((0, 2), np.int64)
    tree = cKDTree(pos[known])
    dist, idx = tree.query(pos[known], k=k + 1, distance_upper_bound=max_distance if max_distance > 0 else np.inf)
    rows = np.repeat(np.arange(len(known)), k + 1)
    ok = np.isfinite(dist.ravel())
    pairs = np.stack([ids[known[rows[ok]]], ids[known[idx.ravel()[ok]]]], axis=1)
    return _unique_pairs(pairs)


def global_descriptors(
    image_ids: Sequence[int], load_descriptors: Callable[[int], np.ndarray], seed: int = 0,
    num_words: int = VOCABULARY_WORDS,
) -> np.ndarray:  # fmt: skip
    """(n, K * D) VLAD vectors of the images, vocabulary learned from their own descriptors
    (up to 200 per image and 100k in total, seeded)."""
    per_image = max(1, min(SAMPLES_PER_IMAGE, MAX_VOCABULARY_SAMPLES // max(len(image_ids), 1)))
    sample = [vocabulary_sample(load_descriptors(i), per_image, seed, i) for i in image_ids]
    vocabulary = learn_vocabulary(np.concatenate(sample), num_words, seed)
    return np.stack([vlad(load_descriptors(i), vocabulary) for i in image_ids])


def select_pairs(
    image_ids: Sequence[int], method: str = "auto", *, top_k: int = 30, sequential: int = 0,
    exhaustive_threshold: int = 200, seed: int = 0,
    load_descriptors: Callable[[int], np.ndarray] | None = None,
    positions: np.ndarray | None = None, spatial_neighbors: int = 50, spatial_max_distance: float = 100.0,
) -> np.ndarray:  # fmt: skip
    """The sorted unique (P, 2) pairs to match among ``image_ids`` (given in name order).

    ``method`` one of auto|exhaustive|retrieval|spatial; retrieval needs ``load_descriptors``,
    spatial also ``positions`` (N, 3) metres, NaN rows for images without one.
    """
    if method not in PAIR_METHODS:
        raise ValueError(f"pairs must be one of {'|'.join(PAIR_METHODS)}, got {method!r}")
    spatial = np.zeros((0, 2), np.int64)
    if method == "spatial":
        if positions is None:
            raise ValueError("spatial pairs need positions")
        spatial = spatial_pairs(image_ids, positions, spatial_neighbors, spatial_max_distance)
        method = "retrieval"
    if method == "auto":
        method = "exhaustive" if len(image_ids) < exhaustive_threshold else "retrieval"
    if method == "retrieval" and top_k >= len(image_ids) - 1:
        method = "exhaustive"  # every image is among every other's top k
    if method == "exhaustive":
        pairs = exhaustive_pairs(image_ids)
    else:
        if load_descriptors is None:
            raise ValueError("retrieval pairs need descriptors (load_descriptors)")
        vectors = global_descriptors(image_ids, load_descriptors, seed)
        pairs = retrieval_pairs(image_ids, vectors, top_k)
    return _unique_pairs(np.concatenate([pairs, spatial, sequential_pairs(image_ids, sequential)]))


def extension_pairs(
    new_ids: Sequence[int], old_ids: Sequence[int], method: str = "auto", *, top_k: int = 30, sequential: int = 0,
    exhaustive_threshold: int = 200, seed: int = 0,
    load_descriptors: Callable[[int], np.ndarray] | None = None,
    positions: np.ndarray | None = None, spatial_neighbors: int = 50, spatial_max_distance: float = 100.0,
) -> np.ndarray:  # fmt: skip
    """The sorted unique (P, 2) pairs to match when ``new_ids`` are added to a model of
    ``old_ids`` (both in name order): every pair has at least one new image.

    - new x new: :func:`select_pairs` among the new images (the same ``method``).
    - new x old: every such pair when the method resolves to exhaustive over all the images
      (``auto`` below ``exhaustive_threshold`` images in all, or ``top_k`` reaching every old
      image); otherwise each new image's ``top_k`` most similar old images by VLAD, with a
      vocabulary learned from the new images' descriptors (the old images are only described,
      one at a time, never matched among themselves).  ``spatial`` adds each new image's nearest
      old images by ``positions`` (rows: new images, then old ones).
    """
    if method not in PAIR_METHODS:
        raise ValueError(f"pairs must be one of {'|'.join(PAIR_METHODS)}, got {method!r}")
    new = np.asarray(new_ids, np.int64)
    old = np.asarray(old_ids, np.int64)
    if len(new) == 0:
        return np.zeros((0, 2), np.int64)
    new_pos = None if positions is None else np.asarray(positions, np.float64)[: len(new)]
    within = select_pairs(new, method, top_k=top_k, sequential=sequential, exhaustive_threshold=exhaustive_threshold,
                          seed=seed, load_descriptors=load_descriptors, positions=new_pos,
                          spatial_neighbors=spatial_neighbors, spatial_max_distance=spatial_max_distance)
    if len(old) == 0:
        return within
    total = len(new) + len(old)
    exhaustive = method == "exhaustive" or (method == "auto" and total < exhaustive_threshold) or top_k >= len(old)
    if exhaustive:
        across = np.stack([np.repeat(new, len(old)), np.tile(old, len(new))], axis=1)
    else:
        if load_descriptors is None:
            raise ValueError("retrieval pairs need descriptors (load_descriptors)")
        across = _retrieval_across(new, old, load_descriptors, top_k, seed)
        if method == "spatial":
            if positions is None:
                raise ValueError("spatial pairs need positions")
            near = spatial_pairs(np.concatenate([new, old]), positions, spatial_neighbors, spatial_max_distance)
            is_new = np.isin(near, new)
            across = np.concatenate([across, near[is_new[:, 0] ^ is_new[:, 1]]])
    return _unique_pairs(np.concatenate([within, across]))


def _retrieval_across(new: np.ndarray, old: np.ndarray, load_descriptors: Callable[[int], np.ndarray], top_k: int,
                      seed: int) -> np.ndarray:
    """Each new image with its ``top_k`` most similar old images (VLAD dot products, ties:
    the earlier old image), the vocabulary learned from the new images' descriptors."""
    per_image = max(1, min(SAMPLES_PER_IMAGE, MAX_VOCABULARY_SAMPLES // len(new)))
    sample = [vocabulary_sample(load_descriptors(int(i)), per_image, seed, int(i)) for i in new]
    vocabulary = learn_vocabulary(np.concatenate(sample), VOCABULARY_WORDS, seed)
    g_new = np.stack([vlad(load_descriptors(int(i)), vocabulary) for i in new])
    g_old = np.stack([vlad(load_descriptors(int(i)), vocabulary) for i in old])
    k = min(int(top_k), len(old))
    order = np.argsort(-(g_new @ g_old.T), axis=1, kind="stable")[:, :k]
    return np.stack([np.repeat(new, k), old[order.ravel()]], axis=1)
