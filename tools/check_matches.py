"""Check a workspace's verified matches against ground-truth poses (epipolar distances, recall).

    python tools/check_matches.py --workspace W --gt TABLE [--overlap-deg 30] [--min-inliers 15]

For every verified pair of ``W/database.db`` (two_view_geometries config >= 2 and at least
``--min-inliers`` inliers) whose two images are in the GT table (``sfm.evaluation.ground_truth``:
``IMAGE_NAME W H FX FY CX CY QW QX QY QZ TX TY TZ``, cam_from_world, OpenCV pixels), the GT
fundamental matrix ``F = K2^-T [t]x R K1^-1`` (``R = R2 R1^T``, ``t = t2 - R t1``: the pose of
camera 2 from camera 1) gives each stored inlier match its symmetric epipolar distance: the mean
of the distance of x2 to the epipolar line F x1 and of x1 to the line F^T x2, in pixels.
Keypoints come from ``Database.read_keypoints`` (OpenCV pixel centres, like the GT K), so the
database may be ours or COLMAP's. The GT table has no lens distortion; ``--k1`` undistorts the
keypoints with COLMAP's SIMPLE_RADIAL model of the GT K (``x_d = x_u (1 + k1 r_u^2)`` on
normalised coordinates) first: lund_door's GT camera has k1 = -0.0336422, up to ~9 px at the
image corners (its median inlier distance drops from about 0.19 to 0.13 px with it).

Printed: the median over all inliers, the median and 90th percentile of the per-pair medians,
the number of verified pairs (and how many have both images in the GT), and with
``--overlap-deg`` the recall of GT-overlapping pairs (optical axes, the third rows of the GT
rotations, within that angle) among the SELECTED pairs (pairs with a two_view_geometries or a
matches row: the pairs the matcher considered) and among the verified pairs.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sfm.io.database import Database
from sfm.evaluation.ground_truth import GTPose, read_gt_table


# ------------------------------------------------------------------------------ library
def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix ``[v]x`` (``[v]x @ w == cross(v, w)``)."""
    x, y, z = np.asarray(v, np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def gt_fundamental(pose1: GTPose, pose2: GTPose) -> np.ndarray:
    """F with ``x2^T F x1 = 0`` for pixels (OpenCV convention) of image 1 and image 2.

    ``c2_from_c1 = (R2 R1^T, t2 - R2 R1^T t1)`` from the two cam_from_world poses; ``E = [t]x R``;
    ``F = K2^-T E K1^-1``, scaled to unit Frobenius norm. Raises ``ValueError`` when the two
    centres coincide (no baseline: F is undefined).
    """
    rot_c2_from_c1 = pose2.rotation @ pose1.rotation.T
    t_c2_from_c1 = pose2.translation - rot_c2_from_c1 @ pose1.translation
    scale = max(np.linalg.norm(pose1.translation), np.linalg.norm(pose2.translation), 1.0)
    if np.linalg.norm(t_c2_from_c1) <= 1e-12 * scale:
        raise ValueError(f"{pose1.name} and {pose2.name} have the same GT centre: no F")
    E = skew(t_c2_from_c1) @ rot_c2_from_c1
    F = np.linalg.inv(pose2.K).T @ E @ np.linalg.inv(pose1.K)
    return F / np.linalg.norm(F)


def symmetric_epipolar_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Per match, ``(d(x2, F x1) + d(x1, F^T x2)) / 2`` in pixels (point-to-line distances)."""
    h1 = np.column_stack([np.asarray(x1, np.float64)[:, :2], np.ones(len(x1))])
    h2 = np.column_stack([np.asarray(x2, np.float64)[:, :2], np.ones(len(x2))])
    lines2 = h1 @ F.T  # epipolar lines in image 2: F x1
    lines1 = h2 @ F  # epipolar lines in image 1: F^T x2
    residual = np.abs(np.sum(h2 * lines2, axis=1))
    d2 = residual / np.maximum(np.hypot(lines2[:, 0], lines2[:, 1]), 1e-300)
    d1 = residual / np.maximum(np.hypot(lines1[:, 0], lines1[:, 1]), 1e-300)
    return 0.5 * (d1 + d2)


def undistort_simple_radial(x: np.ndarray, K: np.ndarray, k1: float) -> np.ndarray:
    """Pixels (N, 2) without the radial distortion ``x_d = x_u (1 + k1 |x_u|^2)`` (normalised
    coordinates of ``K``, COLMAP's SIMPLE_RADIAL), by fixed-point iteration."""
    x = np.asarray(x, np.float64)[:, :2]
    if k1 == 0.0:
        return x
    focal = np.array([K[0, 0], K[1, 1]])
    distorted = (x - K[:2, 2]) / focal
    undistorted = distorted.copy()
    for _ in range(50):
        r2 = np.sum(undistorted**2, axis=1, keepdims=True)
        undistorted = distorted / (1.0 + k1 * r2)
    return undistorted * focal + K[:2, 2]


def optical_axis_angle_deg(pose1: GTPose, pose2: GTPose) -> float:
    """Angle between the viewing directions (third rows of the cam_from_world rotations)."""
    cos = float(np.clip(pose1.rotation[2] @ pose2.rotation[2], -1.0, 1.0))
    return float(np.degrees(np.arccos(cos)))


@dataclass
class MatchCheck:
    """What :func:`check_matches` found.

    num_verified: verified pairs in the database; num_checked: those with both images in the GT
    and a GT baseline; pair_medians: ``{(name1, name2): median distance}`` of the checked pairs
    (names sorted); distances: every
    checked inlier's symmetric epipolar distance (px); num_no_baseline: verified GT pairs left out
    because their GT centres coincide (F undefined). Overlap fields are None without
    ``overlap_deg``: num_gt_overlap GT pairs (both images in the database) whose optical axes are
    within the angle; of them num_overlap_selected have a matches or two_view_geometries row and
    num_overlap_verified are verified; num_selected: all selected pairs.
    """

    num_verified: int
    num_checked: int
    distances: np.ndarray
    pair_medians: dict[tuple[str, str], float] = field(default_factory=dict)
    num_no_baseline: int = 0
    overlap_deg: float | None = None
    num_selected: int | None = None
    num_gt_overlap: int | None = None
    num_overlap_selected: int | None = None
    num_overlap_verified: int | None = None
    missed_overlap: list[tuple[str, str, float]] = field(default_factory=list)

    @property
    def median_px(self) -> float:
        return float(np.median(self.distances)) if len(self.distances) else float("nan")

    @property
    def median_of_pair_medians_px(self) -> float:
        v = list(self.pair_medians.values())
        return float(np.median(v)) if v else float("nan")

    @property
    def p90_of_pair_medians_px(self) -> float:
        v = list(self.pair_medians.values())
        return float(np.percentile(v, 90)) if v else float("nan")

    @property
    def recall_selected(self) -> float | None:
        if self.num_gt_overlap is None or self.num_overlap_selected is None:
            return None
        return (
            self.num_overlap_selected / self.num_gt_overlap if self.num_gt_overlap else float("nan")
        )

    @property
    def recall_verified(self) -> float | None:
        if self.num_gt_overlap is None or self.num_overlap_verified is None:
            return None
        return (
            self.num_overlap_verified / self.num_gt_overlap if self.num_gt_overlap else float("nan")
        )


def check_matches(
    db: Database,
    gt: dict[str, GTPose],
    min_inliers: int = 15,
    overlap_deg: float | None = None,
    k1: float = 0.0,
) -> MatchCheck:
    """Epipolar distances of the verified inliers of ``db`` against ``gt`` (module docstring);
    ``k1``: radial distortion of the GT cameras (keypoints are undistorted first)."""
    names = {i: r.name for i, r in db.read_images().items()}
    geometries = db.read_two_view_geometries(min_config=2, min_inliers=min_inliers)
    keypoints = db.read_all_keypoints([i for i in names if names[i] in gt])
    distances, pair_medians, no_baseline = [], {}, 0
    for (id1, id2), geometry in sorted(geometries.items()):
        n1, n2 = names.get(id1), names.get(id2)
        if n1 not in gt or n2 not in gt or id1 not in keypoints or id2 not in keypoints:
            continue
        try:
            F = gt_fundamental(gt[n1], gt[n2])
        except ValueError:
            no_baseline += 1
            continue
        m = geometry.inlier_matches.astype(np.int64)
        x1 = undistort_simple_radial(keypoints[id1][m[:, 0], :2], gt[n1].K, k1)
        x2 = undistort_simple_radial(keypoints[id2][m[:, 1], :2], gt[n2].K, k1)
        d = symmetric_epipolar_distance(F, x1, x2)
        distances.append(d)
        pair_medians[tuple(sorted((n1, n2)))] = float(np.median(d))
    result = MatchCheck(
        num_verified=len(geometries),
        num_checked=len(pair_medians),
        distances=np.concatenate(distances) if distances else np.zeros(0),
        pair_medians=pair_medians,
        num_no_baseline=no_baseline,
    )
    if overlap_deg is not None:
        selected = db.pairs_with_geometry() | db.pairs_with_matches()
        verified = set(geometries)
        in_gt = sorted((i for i in names if names[i] in gt), key=lambda i: names[i])
        overlap, hit_sel, hit_ver, missed = 0, 0, 0, []
        for a, b in itertools.combinations(in_gt, 2):
            angle = optical_axis_angle_deg(gt[names[a]], gt[names[b]])
            if angle > overlap_deg:
                continue
            key = (min(a, b), max(a, b))
            overlap += 1
            hit_sel += key in selected
            hit_ver += key in verified
            if key not in selected:
                missed.append((names[a], names[b], angle))
        result.overlap_deg, result.num_selected = overlap_deg, len(selected)
        result.num_gt_overlap, result.num_overlap_selected = overlap, hit_sel
        result.num_overlap_verified, result.missed_overlap = hit_ver, missed
    return result


def format_report(check: MatchCheck, title: str = "") -> str:
    """A Markdown table of the figures of ``check``."""
    rows = [
        ("verified pairs (config >= 2, enough inliers)", f"{check.num_verified}"),
        ("verified pairs checked (both images in the GT, GT baseline > 0)", f"{check.num_checked}"),
        ("verified pairs skipped: same GT centre (no F)", f"{check.num_no_baseline}"),
        ("inliers checked", f"{len(check.distances)}"),
        ("median symmetric epipolar distance, all inliers (px)", f"{check.median_px:.3f}"),
        ("median of per-pair medians (px)", f"{check.median_of_pair_medians_px:.3f}"),
        ("90th percentile of per-pair medians (px)", f"{check.p90_of_pair_medians_px:.3f}"),
        (
            "inliers within 1 px / 4 px",
            f"{np.mean(check.distances <= 1):.1%} / {np.mean(check.distances <= 4):.1%}"
            if len(check.distances)
            else "-",
        ),
    ]
    if check.num_gt_overlap is not None:
        deg = f"{check.overlap_deg:g}"

        def recall(hits: int | None) -> str:
            total = check.num_gt_overlap
            return f"{hits / total:.1%} ({hits}/{total})" if total and hits is not None else "-"

        rows += [
            ("selected pairs (matches or two_view_geometries row)", f"{check.num_selected}"),
            (f"GT-overlapping pairs (optical axes within {deg} deg)", f"{check.num_gt_overlap}"),
            (
                "recall of GT-overlapping pairs among selected pairs",
                recall(check.num_overlap_selected),
            ),
            (
                "recall of GT-overlapping pairs among verified pairs",
                recall(check.num_overlap_verified),
            ),
        ]
    lines = ([f"### {title}", ""] if title else []) + ["| figure | value |", "|---|---|"]
    return "\n".join(lines + [f"| {k} | {v} |" for k, v in rows])


# ------------------------------------------------------------------------------ command
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--workspace", type=Path, required=True, help="folder with database.db")
    parser.add_argument(
        "--gt",
        type=Path,
        required=True,
        help="GT table (IMAGE_NAME W H FX FY CX CY QW..QZ TX TY TZ)",
    )
    parser.add_argument(
        "--overlap-deg",
        type=float,
        default=None,
        help="also report the recall of pairs whose optical axes are within this angle",
    )
    parser.add_argument(
        "--k1",
        type=float,
        default=0.0,
        help="radial distortion of the GT cameras (SIMPLE_RADIAL k1; lund_door: -0.0336422)",
    )
    parser.add_argument(
        "--min-inliers", type=int, default=15, help="inliers of a verified pair (default 15)"
    )
    parser.add_argument(
        "--worst", type=int, default=5, help="list this many worst pairs and missed pairs"
    )
    args = parser.parse_args(argv)
    db_path = args.workspace / "database.db"
    if not db_path.is_file() or not args.gt.is_file():
        print(f"error: need {db_path} and {args.gt}", file=sys.stderr)
        return 2
    gt = read_gt_table(args.gt)
    with Database(db_path, readonly=True) as db:
        check = check_matches(db, gt, args.min_inliers, args.overlap_deg, args.k1)
    print(format_report(check, str(args.workspace)))
    if args.worst and check.pair_medians:
        worst = sorted(check.pair_medians.items(), key=lambda kv: -kv[1])[: args.worst]
        print("\nworst pairs (median px): " + ", ".join(f"{a}-{b} {d:.2f}" for (a, b), d in worst))
    if args.worst and check.missed_overlap:
        missed = sorted(check.missed_overlap, key=lambda m: m[2])[: args.worst]
        print(
            f"missed overlapping pairs ({len(check.missed_overlap)}, smallest angle first): "
            + ", ".join(f"{a}-{b} {d:.1f}deg" for a, b, d in missed)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
