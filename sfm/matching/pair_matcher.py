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
from sfm.matching.descriptors import match_descriptors, normalize_descriptors
from sfm.matching.options import MatchOptions
from sfm.matching.verification import pair_seed, verify_pair

CACHE_BYTES = 256 * 2**20


class PairMatcher:
    """Matches and verifies pairs, reading features from a database through an LRU cache."""

    def __init__(self, load: Callable[[int], tuple[np.ndarray, np.ndarray]], camera_of: dict[int, int],
                 cameras: dict[int, CameraRecord], options: MatchOptions, name_of: dict[int, str]) -> None:  # fmt: skip
        """``load``: image id -> (keypoints, uint8 descriptors); ``camera_of``: image id -> camera
        id; ``cameras``: camera id -> record; ``name_of``: image id -> image name."""
        self.load, self.camera_of, self.cameras, self.options = load, camera_of, cameras, options
        self.name_of = name_of
        self.verify_options = options.verify_options()
        self._cache: OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()
        self._cache_bytes = 0

    def features(self, image_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keypoints, unit float32 descriptors, their C-contiguous transpose) of an image."""
        if image_id in self._cache:
            self._cache.move_to_end(image_id)
            return self._cache[image_id]
        keypoints, descriptors = self.load(image_id)
        unit = normalize_descriptors(descriptors)
        item = (keypoints, unit, np.ascontiguousarray(unit.T))
        self._cache[image_id] = item
        self._cache_bytes += sum(a.nbytes for a in item)
        while self._cache_bytes > CACHE_BYTES and len(self._cache) > 2:
            _, old = self._cache.popitem(last=False)
            self._cache_bytes -= sum(a.nbytes for a in old)
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
        (kp1, d1, _), (kp2, d2, d2t) = self.features(id1), self.features(id2)
        seed = pair_seed(self.options.seed, self.name_of[id1], self.name_of[id2])
        o = self.options
        t0 = time.perf_counter()
        matches = match_descriptors(d1, d2, o.max_ratio, o.cross_check, o.matcher, seed=seed, normalized=True,
                                    transposed2=d2t)  # fmt: skip
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
