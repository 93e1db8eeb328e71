"""Rerun views of the front end: each image with its keypoints (extract), the image graph and
the inlier matches of a sample of pairs (match)."""

from __future__ import annotations

import logging

import numpy as np

from sfm.viz.graphs import draw_graph, graph_layout
from sfm.viz.palette import ramp
from sfm.viz.recorder import Recorder, entity_part
from sfm.viz.thumbnails import Thumbnail, encode_thumbnail

log = logging.getLogger(__name__)

MAX_KEYPOINTS = 4096  # keypoints drawn per image (an even sample beyond)
MAX_MATCH_LINES = 500  # inlier matches drawn per pair (an even sample beyond)
SCALE_RANGE = (1.0, 32.0)  # keypoint scales (sigma, full-resolution pixels) from blue to red


def even_sample(n: int, at_most: int) -> np.ndarray:
    """Indices of an even sample of at most ``at_most`` of ``n`` items (all when n is smaller)."""
    if n <= at_most:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, at_most).round().astype(np.int64))


def log_image(recorder: Recorder, name: str, thumb: Thumbnail, keypoints: np.ndarray) -> None:
    """``images/<name>``: the thumbnail, and ``images/<name>/keypoints``: each keypoint as a
    disc of its scale, coloured by scale (blue 1 px to red 32 px, logarithmic), at stage extract."""
    if not recorder.enabled:
        return
    import rerun as rr

    recorder.thumbnails[name] = thumb
    recorder.stage("extract")
    entity = f"images/{entity_part(name)}"
    recorder.log(entity, rr.EncodedImage(contents=thumb.jpeg, media_type="image/jpeg"))
    kp = np.asarray(keypoints, dtype=np.float64)
    kp = kp[even_sample(len(kp), MAX_KEYPOINTS)]
    scale = kp[:, 2] if kp.shape[1] >= 3 else np.ones(len(kp))
    order = np.argsort(-scale, kind="stable")  # small keypoints drawn over large ones
    kp, scale = kp[order], scale[order]
    colors = ramp(np.log2(np.maximum(scale, 1e-3)), *np.log2(SCALE_RANGE))
    radii = np.clip(scale * thumb.scale_x, 0.7, 16.0)
    recorder.log(f"{entity}/keypoints", rr.Points2D(thumb.to_thumbnail(kp[:, :2]), radii=radii, colors=colors))
    if name not in recorder.views["images"]:
        recorder.views["images"].append(name)


def log_image_graph(recorder: Recorder, names: list[str], i: np.ndarray, j: np.ndarray,
                    weights: np.ndarray) -> dict[int, np.ndarray]:
    """``graph/images`` at stage match: the image graph of paper section 3.1.1, one node per
    image and one edge per verified pair, its width and colour (blue few, red many) and label
    the number of verified inliers, its weight.  Returns the layout (node -> position)."""
    positions = graph_layout(len(names), i, j, weights)
    if recorder.enabled:
        w = np.asarray(weights, dtype=np.float64)
        colors = ramp(np.log(np.maximum(w, 1)), np.log(max(w.min(initial=1), 1)), np.log(max(w.max(initial=2), 2)))
        draw_graph(recorder, "graph/images", positions, names, node_colors=[(200, 200, 200)] * len(names),
                   edges=list(zip(i.tolist(), j.tolist())), edge_colors=colors,
                   edge_widths=1.0 + 3.0 * w / max(w.max(initial=1), 1), edge_labels=[str(int(x)) for x in w])
    return positions


def pair_sample(weights: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` pairs (0: all) spread evenly over the pairs sorted from the most to
    the fewest inliers, so the sample shows strong and weak pairs alike."""
    order = np.argsort(-np.asarray(weights), kind="stable")
    if count <= 0 or count >= len(order):
        return order
    return order[even_sample(len(order), count)]


def log_match_pair(recorder: Recorder, name1: str, name2: str, thumb1: Thumbnail, thumb2: Thumbnail,
                   xy1: np.ndarray, xy2: np.ndarray, config: str) -> None:
    """``matches/<name1> ~ <name2>``: the two thumbnails side by side and a line per inlier
    match (at most :data:`MAX_MATCH_LINES`, an even sample), at stage match."""
    if not recorder.enabled:
        return
    import rerun as rr

    a, b = thumb1.pixels(), thumb2.pixels()
    height = max(a.shape[0], b.shape[0])
    side = np.zeros((height, a.shape[1] + b.shape[1], 3), np.uint8)
    side[: a.shape[0], : a.shape[1]] = a
    side[: b.shape[0], a.shape[1]:] = b
    entity = f"matches/{entity_part(name1 + ' ~ ' + name2)}"
    composite = encode_thumbnail(side, side.shape[1], side.shape[0])
    recorder.log(entity, rr.EncodedImage(contents=composite.jpeg, media_type="image/jpeg"))
    keep = even_sample(len(xy1), MAX_MATCH_LINES)
    p1 = thumb1.to_thumbnail(xy1[keep])
    p2 = thumb2.to_thumbnail(xy2[keep]) + [a.shape[1], 0]
    strips = np.stack([p1, p2], axis=1)
    hue = ramp(np.arange(len(keep)), 0, max(len(keep) - 1, 1))
    recorder.log(f"{entity}/inliers", rr.LineStrips2D(strips, colors=hue, radii=0.5))
    recorder.log(f"{entity}/about", rr.TextDocument(
        f"**{name1}** and **{name2}**: {len(xy1)} verified inlier matches ({config}); "
        f"{len(keep)} drawn.", media_type=rr.MediaType.MARKDOWN))
    recorder.views["pairs"].append(entity)
