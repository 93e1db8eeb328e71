"""Matching and verifying one image pair from its images' features (arrays in, arrays out).

:class:`PairMatcher` matches descriptors (``sfm.matching.descriptors``: ratio test and mutual
check) and verifies the matches (``sfm.matching.verification``: E, F and H by USAC MAGSAC).  It
gets each image's features from a loader (the database on this machine, or arrays that
travelled with the task) through an LRU cache, since a batch of pairs shares images.
:func:`match_batch` is the ``match`` stage's task: one batch of pairs.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sfm.io.database import Database
from sfm.io.database_schema import CameraRecord, TwoViewGeometry
from sfm.matching.descriptors import match_descriptors, normalize_descriptors, resolve_matcher
from sfm.matching.inverted_file import InvertedFile, match_inverted
from sfm.matching.options import MatchOptions
from sfm.matching.verification import pair_seed, verify_pair

# Per worker process: the images' features and search structures held between pairs.  An
# image's inverted file is about the size of its unit descriptors, so this holds over a hundred
# images of ten thousand features.
CACHE_BYTES = 1024 * 2**20


class ImageFeatures:
    """One image's keypoints and unit float32 descriptors, with the search structures a matcher
    asks for built once, on first use: the descriptors' C-contiguous transpose (``brute``) and
    their inverted file (``ivf``, built with the options' seed, so an image's index is the same
    whatever pair it is in)."""

    def __init__(self, keypoints: np.ndarray, unit: np.ndarray, seed: int) -> None:
        self.keypoints, self.unit, self.seed = keypoints, unit, seed
        self._transposed: np.ndarray | None = None
        self._inverted: InvertedFile | None = None

    @property
    def transposed(self) -> np.ndarray:
        if self._transposed is None:
            self._transposed = np.ascontiguousarray(self.unit.T)
        return self._transposed

    @property
    def inverted_file(self) -> InvertedFile:
        if self._inverted is None:
            self._inverted = InvertedFile.build(self.unit, self.seed)
        return self._inverted

    @property
    def nbytes(self) -> int:
        extra = (0 if self._transposed is None else self._transposed.nbytes) + (
            0 if self._inverted is None else self._inverted.nbytes - self.unit.nbytes)
        return self.keypoints.nbytes + self.unit.nbytes + extra


# What one image's features take in the cache, per keypoint: its row (4 float32), its unit
# descriptor (128 float32) and its inverted file's listings (int64; about ten per descriptor at
# inverted_file.CELL_MARGIN).
CACHED_BYTES_PER_KEYPOINT = 4 * 4 + 128 * 4 + 10 * 8


def images_in_cache(mean_keypoints: float) -> int:
    """How many images of ``mean_keypoints`` features a worker's cache holds."""
    return max(2, int(CACHE_BYTES // max(CACHED_BYTES_PER_KEYPOINT * mean_keypoints, 1.0)))


def cache_order(pairs: list[tuple[int, int]], capacity_images: int) -> list[tuple[int, int]]:
    """``pairs`` reordered so that a worker whose cache holds ``capacity_images`` images reads
    each image's features about once (the order changes no result: each pair's matches depend
    only on its two images and the seed).  Images are numbered along the reverse Cuthill-McKee
    order of the pair graph, which gives images that share pairs nearby numbers, then the pairs
    are taken block by block of ``capacity_images // 2`` numbers (by the block of the larger
    number, then of the smaller): one block pair needs at most two blocks of images."""
    if len(pairs) < 2:
        return list(pairs)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    ids, index = np.unique(np.asarray(pairs, np.int64).reshape(-1, 2), return_inverse=True)
    index = index.reshape(-1, 2)
    n = len(ids)
    graph = coo_matrix((np.ones(len(index)), (index[:, 0], index[:, 1])), shape=(n, n)).tocsr()
    rank = np.empty(n, np.int64)
    rank[reverse_cuthill_mckee(graph + graph.T, symmetric_mode=True)] = np.arange(n)
    first, second = rank[index[:, 0]], rank[index[:, 1]]
    low, high = np.minimum(first, second), np.maximum(first, second)
    block = max(1, capacity_images // 2)
    order = np.lexsort((high, low, low // block, high // block))
    return [pairs[k] for k in order.tolist()]


class PairMatcher:
    """Matches and verifies pairs, reading features from a database through an LRU cache."""

    def __init__(self, load: Callable[[int], tuple[np.ndarray, np.ndarray]], camera_of: dict[int, int],
                 cameras: dict[int, CameraRecord], options: MatchOptions, name_of: dict[int, str]) -> None:  # fmt: skip
        """``load``: image id -> (keypoints, uint8 descriptors); ``camera_of``: image id -> camera
        id; ``cameras``: camera id -> record; ``name_of``: image id -> image name."""
        self.load, self.camera_of, self.cameras, self.options = load, camera_of, cameras, options
        self.name_of = name_of
        self.verify_options = options.verify_options()
        self._cache: OrderedDict[int, ImageFeatures] = OrderedDict()

    def features(self, image_id: int) -> ImageFeatures:
        """An image's features, from the cache or the loader (the least recently used images
        leave the cache once it holds more than ``CACHE_BYTES``, counted as they grow)."""
        if image_id in self._cache:
            self._cache.move_to_end(image_id)
            return self._cache[image_id]
        keypoints, descriptors = self.load(image_id)
        item = ImageFeatures(keypoints, normalize_descriptors(descriptors), self.options.seed)
        self._cache[image_id] = item
        while len(self._cache) > 2 and sum(f.nbytes for f in self._cache.values()) > CACHE_BYTES:
            self._cache.popitem(last=False)
        return item

    def __call__(
        self, pair: tuple[int, int]
    ) -> tuple[int, int, np.ndarray, TwoViewGeometry, float, float]:
        """``(id1, id2, matches, geometry, match seconds, verify seconds)`` of the pair, matched
        from the image whose name sorts first to the other (the ratio test is one-sided) with the
        seed of the two names: a pair of images gives the same matches and geometry in every
        workspace, whatever ids its database gave them.  ``id1`` is that first image (the
        database stores a pair either way round)."""
        id1, id2 = sorted((int(pair[0]), int(pair[1])), key=lambda i: (self.name_of[i], i))
        f1, f2 = self.features(id1), self.features(id2)
        kp1, kp2 = f1.keypoints, f2.keypoints
        seed = pair_seed(self.options.seed, self.name_of[id1], self.name_of[id2])
        o = self.options
        t0 = time.perf_counter()
        matcher = resolve_matcher(o.matcher, len(f1.unit), len(f2.unit))
        if matcher == "ivf":
            matches = match_inverted(f1.inverted_file, f2.inverted_file, o.max_ratio, o.cross_check)
        else:  # only brute uses the transpose: flann would build it for nothing
            matches = match_descriptors(f1.unit, f2.unit, o.max_ratio, o.cross_check, matcher, seed=seed,
                                        normalized=True, transposed2=f2.transposed if matcher == "brute" else None)
        t1 = time.perf_counter()
        cam1, cam2 = self.cameras[self.camera_of[id1]], self.cameras[self.camera_of[id2]]
        geometry = verify_pair(kp1, kp2, matches, cam1, cam2, self.verify_options, seed)
        return id1, id2, matches.astype(np.uint32), geometry, t1 - t0, time.perf_counter() - t1


@dataclass
class PairBatch:
    """One task of the ``match`` stage: pairs of image ids with what matching them needs.
    ``features`` (image id -> keypoints, descriptors) travel with the batch to remote workers;
    ``None``: the worker reads them from ``database`` (a path on its own machine)."""

    pairs: list[tuple[int, int]]
    camera_of: dict[int, int]
    cameras: dict[int, CameraRecord]
    options: MatchOptions
    name_of: dict[int, str]
    database: str | None = None
    features: dict[int, tuple[np.ndarray, np.ndarray]] | None = None


# One matcher per worker process and database, so its feature cache outlives a batch; with the
# database connection it reads through.
_MATCHERS: dict[tuple, tuple[PairMatcher, Database]] = {}


def close_matchers() -> None:
    """Close the database connections of this process's cached matchers (a run in this process
    must not leave a reader open on the database it writes)."""
    for _, db in _MATCHERS.values():
        db.close()
    _MATCHERS.clear()


def match_batch(batch: PairBatch) -> list[tuple[int, int, np.ndarray, TwoViewGeometry, float, float]]:
    """Match and verify every pair of ``batch`` (see :meth:`PairMatcher.__call__`)."""
    if batch.features is not None:
        matcher = PairMatcher(batch.features.__getitem__, batch.camera_of, batch.cameras, batch.options, batch.name_of)
    else:
        key = (batch.database, batch.options)
        if key not in _MATCHERS:
            close_matchers()  # one database at a time
            db = Database(Path(batch.database), readonly=True)
            loader = lambda image_id: (db.read_keypoints(image_id), db.read_descriptors(image_id))  # noqa: E731
            _MATCHERS[key] = (PairMatcher(loader, batch.camera_of, batch.cameras, batch.options, batch.name_of), db)
        matcher = _MATCHERS[key][0]
        matcher.camera_of.update(batch.camera_of)  # each batch brings the cameras and names of its images
        matcher.name_of.update(batch.name_of)
        matcher.cameras.update(batch.cameras)
    return [matcher(pair) for pair in batch.pairs]
