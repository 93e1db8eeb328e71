"""Thousands of photos on one machine: the front end against pycolmap's, the matcher against the
exact one, retrieval against the survey's co-visibility, images to model at survey sizes, and
what that projects to at 10,000 and 50,000 photos.

    python tools/bench_scale.py --out DIR [--parts matcher frontend retrieval endtoend projection]
                                [--data ../shared/data] [--frontend-images 200] [--sizes 1000 2000 5000]
                                [--force PART ...] [--report-only]

Parts, each cached in ``DIR/results.json`` as soon as it is measured (a rerun skips what is
there unless ``--force`` names it, so a long benchmark spans sessions; ``--report-only``
prints and publishes the cached results alone):

- ``matcher``: the ``match`` stage with the default matcher (``auto``: the inverted file) and
  with ``--matcher brute`` on copies of one database, lund_door's and a 200-photo survey's
  (``graphsfm synth --scene survey``), the same pairs: wall time, worker seconds of descriptor
  matching and of verification, verified pairs, and per pair the default's verified inliers over
  brute's (median and 10th percentile over the pairs both verify).
- ``frontend``: the same 200 survey photos through graphsfm's extract and match (defaults) and
  through pycolmap's ``extract_features`` and ``match_image_pairs`` on graphsfm's pair list
  (pycolmap's defaults on the CPU: its faiss index, ratio 0.8, cross check, 4 px, 15 inliers;
  all cores): seconds per image of extraction, pairs per second, verified pairs and inliers.
- ``retrieval``: on the 200-photo survey's database, the pairs of each image's ``top_k`` most
  similar by VLAD (10, 20, 30, 50) and of ``--pairs spatial`` (GPS), against the ground truth's
  co-visible pairs (a grid of each photo's pixels cast onto the ground by the GT pose lands
  inside the other photo, seen from directions at most ``MAX_VIEW_ANGLE_DEG`` apart, for at
  least ``COVISIBLE`` of it): recall of the co-visible pairs,
  pairs per image, and recall of the strongly co-visible ones (half the photo).
- ``endtoend``: ``graphsfm reconstruct`` with defaults on a survey of each ``--sizes`` (rendered
  once into ``DIR/survey<N>``, resumable) in a child process: time per stage (``report.json``),
  peak summed RSS of its process tree, registered photos, AUC@1/5 and median rotation error
  against the survey's GT.  The reconstruct itself resumes when interrupted.
- ``projection``: from the largest end-to-end run's stage times, the time of 10,000 and 50,000
  photos on one such machine and on a Dask cluster of ten: extraction, matching and mapping
  scale with the photos (matching with the pairs, a fixed number per photo) and divide over
  machines; merge and final bundle adjustment scale as measured between the two largest runs
  and run on one machine.  Says which stage bounds each.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
import zlib  # noqa: F401 - before pycolmap
from pathlib import Path

import cv2  # noqa: F401 - before pycolmap
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scaling import run_child  # noqa: E402
from benchmarks_page import add_page_arguments, markdown_table, peer_version, publish, run_context  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("matcher", "frontend", "retrieval", "endtoend", "projection")
COVISIBLE, STRONGLY_COVISIBLE = 0.2, 0.5
MAX_VIEW_ANGLE_DEG = 40.0  # SIFT matches a surface seen from directions up to about this far apart
TOP_KS = (10, 20, 30, 50)


def graphsfm(*args: str, quiet: bool = True) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "sfm", *(["-q"] if quiet else []), *args]
    return subprocess.run(cmd, check=True, capture_output=True, text=True)


def survey(out: Path, n: int) -> Path:
    """``out/survey<n>``: a rendered survey of ``n`` photos (rendered once; resumes)."""
    folder = out / f"survey{n}"
    if not (folder / "gt" / "cameras_gt_opencv.txt").is_file():
        print(f"rendering a survey of {n} photos into {folder}", flush=True)
        graphsfm("synth", "--scene", "survey", "--num-images", str(n), "--workspace", str(folder), quiet=False)
    return folder


def extracted(out: Path, name: str, images: Path) -> Path:
    """``out/<name>-extract``: a workspace with the images' features (once)."""
    ws = out / f"{name}-extract"
    if not (ws / "stages.json").is_file() or "extract" not in json.loads((ws / "stages.json").read_text()):
        shutil.rmtree(ws, ignore_errors=True)
        graphsfm("extract", "--images", str(images), "--workspace", str(ws), "--no-recording")
    return ws


# ------------------------------------------------------------------------------ matcher
def match_copy(source: Path, target: Path, *options: str) -> dict:
    """Run the match stage on a copy of ``source``'s database; the stage's summary and wall time."""
    shutil.rmtree(target, ignore_errors=True)
    target.mkdir(parents=True)
    shutil.copy2(source / "database.db", target / "database.db")
    t0 = time.perf_counter()
    done = graphsfm("match", "--workspace", str(target), "--no-recording", *options)
    wall = time.perf_counter() - t0
    summary = json.loads(done.stdout[done.stdout.index("{"):])
    return {"wall_s": wall, **summary}


def verified_inliers(workspace: Path) -> dict[tuple[int, int], int]:
    from sfm.io.database import Database

    with Database(workspace / "database.db", readonly=True) as db:
        a, b, n = db.verified_pairs(15)
    return {(int(i), int(j)): int(k) for i, j, k in zip(a, b, n)}


def part_matcher(out: Path, data: Path) -> list[dict]:
    rows = []
    sets = {"lund_door": data / "lund_door" / "images", "survey 200": survey(out, 200) / "images"}
    for name, images in sets.items():
        if not images.is_dir():
            print(f"matcher: {images} not found; {name} skipped")
            continue
        ws = extracted(out, name.replace(" ", ""), images)
        brute = match_copy(ws, out / f"{name.replace(' ', '')}-brute", "--matcher", "brute")
        default = match_copy(ws, out / f"{name.replace(' ', '')}-default")
        inl_b = verified_inliers(out / f"{name.replace(' ', '')}-brute")
        inl_d = verified_inliers(out / f"{name.replace(' ', '')}-default")
        common = sorted(set(inl_b) & set(inl_d))
        ratio = np.array([inl_d[p] / inl_b[p] for p in common]) if common else np.array([np.nan])
        for label, r, inl in (("brute", brute, inl_b), ("default (ivf)", default, inl_d)):
            rows.append({"set": name, "matcher": label, "pairs": r["num_pairs_processed"], "wall_s": round(r["wall_s"], 1),
                         "match_worker_s": round(r["time_match_s"], 1), "verify_worker_s": round(r["time_verify_s"], 1),
                         "verified": len(inl), "median_inliers": float(np.median(list(inl.values()))) if inl else 0})
        rows[-1].update({"speedup_wall": round(brute["wall_s"] / default["wall_s"], 2),
                         "speedup_worker": round((brute["time_match_s"] + brute["time_verify_s"])
                                                 / (default["time_match_s"] + default["time_verify_s"]), 2),
                         "inliers_vs_brute_median": round(float(np.median(ratio)), 4),
                         "inliers_vs_brute_p10": round(float(np.percentile(ratio, 10)), 4)})
        print(markdown_table(rows[-2:]), flush=True)
    return rows


# ------------------------------------------------------------------------------ front end
def part_frontend(out: Path, threads: int) -> list[dict]:
    import pycolmap

    images = survey(out, 200) / "images"
    ours = out / "frontend-graphsfm"
    shutil.rmtree(ours, ignore_errors=True)
    t0 = time.perf_counter()
    graphsfm("extract", "--images", str(images), "--workspace", str(ours), "--no-recording")
    t_extract = time.perf_counter() - t0
    t0 = time.perf_counter()
    graphsfm("match", "--workspace", str(ours), "--no-recording")
    t_match = time.perf_counter() - t0
    from sfm.io.database import Database

    with Database(ours / "database.db", readonly=True) as db:
        names = {i: r.name for i, r in db.read_images().items()}
        pairs = sorted(db.pairs_with_geometry())
    pair_list = out / "frontend-pairs.txt"
    pair_list.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pairs))
    peer = out / "frontend-colmap"
    shutil.rmtree(peer, ignore_errors=True)
    peer.mkdir(parents=True)
    pycolmap.logging.minloglevel = 2
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pair_list)
    t0 = time.perf_counter()
    pycolmap.extract_features(str(peer / "database.db"), str(images), extraction_options=extraction,
                              device=pycolmap.Device.cpu)
    p_extract = time.perf_counter() - t0
    t0 = time.perf_counter()
    pycolmap.match_image_pairs(str(peer / "database.db"), matching_options=matching, pairing_options=pairing,
                               device=pycolmap.Device.cpu)
    p_match = time.perf_counter() - t0
    rows = []
    for label, ws, te, tm in (("graphsfm", ours, t_extract, t_match), (peer_version(), peer, p_extract, p_match)):
        with Database(ws / "database.db", readonly=True) as db:
            n_images = len(db.read_images())
            kp = [len(k) for k in db.read_all_keypoints().values()]
            _, _, inl = db.verified_pairs(15)
        rows.append({"front end": label, "images": n_images, "pairs": len(pairs), "keypoints_mean": round(float(np.mean(kp))),
                     "extract_s": round(te, 1), "s_per_image": round(te / n_images, 3), "match_s": round(tm, 1),
                     "pairs_per_s": round(len(pairs) / tm, 1), "verified": len(inl),
                     "median_inliers": float(np.median(inl)) if len(inl) else 0, "total_s": round(te + tm, 1)})
    rows[0]["total_vs_peer"] = round(rows[0]["total_s"] / rows[1]["total_s"], 3)
    print(markdown_table(rows), flush=True)
    return rows


# ------------------------------------------------------------------------------ retrieval
def overlap_matrix(gt: dict, ground_z: float = 0.0, grid: tuple[int, int] = (16, 12),
                   max_angle_deg: float = MAX_VIEW_ANGLE_DEG) -> tuple[list[str], np.ndarray]:
    """Share of a grid of each photo's pixels that, cast onto the plane ``z = ground_z`` by its GT
    pose, lands inside each other photo (rows: the casting photo) and is seen by the two from
    directions at most ``max_angle_deg`` apart (beyond that SIFT does not match a surface)."""
    names = sorted(gt)
    pts = []
    for name in names:
        p = gt[name]
        u, v = np.meshgrid(np.linspace(0, p.width - 1, grid[0]), np.linspace(0, p.height - 1, grid[1]))
        rays_cam = np.linalg.inv(p.K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
        rays = p.rotation.T @ rays_cam
        center = p.center
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (ground_z - center[2]) / rays[2]
        hit = center[:, None] + s * rays
        pts.append(np.where(s > 0, hit, np.nan))
    n = len(names)
    share = np.zeros((n, n))
    cos_limit = np.cos(np.radians(max_angle_deg))
    for j, name in enumerate(names):
        p = gt[name]
        for i in range(n):
            if i == j:
                continue
            x = p.rotation @ pts[i] + p.translation[:, None]
            to_i, to_j = gt[names[i]].center[:, None] - pts[i], p.center[:, None] - pts[i]
            with np.errstate(invalid="ignore", divide="ignore"):
                uv = (p.K @ x)[:2] / x[2]
                cos = np.sum(to_i * to_j, axis=0) / (np.linalg.norm(to_i, axis=0) * np.linalg.norm(to_j, axis=0))
                inside = (x[2] > 0) & (uv[0] >= 0) & (uv[0] < p.width) & (uv[1] >= 0) & (uv[1] < p.height)
            share[i, j] = np.mean(inside & (cos >= cos_limit))
    return names, share


def part_retrieval(out: Path) -> list[dict]:
    from sfm.evaluation.ground_truth import read_gt_table
    from sfm.io.database import Database
    from sfm.matching.options import MatchOptions
    from sfm.matching.pairs import select_pairs
    from sfm.stages.match import _gps_positions

    folder = survey(out, 200)
    gt = read_gt_table(folder / "gt" / "cameras_gt_opencv.txt")
    names, share = overlap_matrix(gt)
    both = np.maximum(share, share.T)
    ws = extracted(out, "survey200", folder / "images")
    rows = []
    with Database(ws / "database.db", readonly=True) as db:
        by_name = {r.name: i for i, r in db.read_images().items()}
        ids = [by_name[n] for n in names]
        index = {i: k for k, i in enumerate(ids)}
        truth = {s: {(a, b) for a in range(len(ids)) for b in range(a + 1, len(ids)) if both[a, b] >= s}
                 for s in (COVISIBLE, STRONGLY_COVISIBLE)}
        methods = [(f"retrieval top_k {k}", dict(method="retrieval", top_k=k)) for k in TOP_KS]
        methods.append(("spatial (top_k 30 + 50 GPS neighbours)",
                        dict(method="spatial", top_k=30, positions=_gps_positions(db, ids))))
        for label, kwargs in methods:
            pairs = select_pairs(ids, load_descriptors=db.read_descriptors, seed=MatchOptions().seed, **kwargs)
            got = {tuple(sorted((index[int(a)], index[int(b)]))) for a, b in pairs}
            rows.append({"pairs": label, "pairs_per_image": round(2 * len(got) / len(ids), 1),
                         f"recall (overlap >= {COVISIBLE})": round(len(got & truth[COVISIBLE]) / len(truth[COVISIBLE]), 3),
                         f"recall (overlap >= {STRONGLY_COVISIBLE})":
                             round(len(got & truth[STRONGLY_COVISIBLE]) / len(truth[STRONGLY_COVISIBLE]), 3),
                         "precision": round(len(got & truth[COVISIBLE]) / max(len(got), 1), 3)})
    rows.append({"pairs": "GT co-visible", "pairs_per_image": round(2 * len(truth[COVISIBLE]) / len(ids), 1)})
    print(markdown_table(rows), flush=True)
    return rows


# ------------------------------------------------------------------------------ end to end
def part_endtoend(out: Path, n: int) -> dict:
    from sfm.evaluation.ground_truth import read_gt_table
    from sfm.evaluation.metrics import evaluate
    from sfm.io.colmap_model import read_model

    folder = survey(out, n)
    ws = out / f"survey{n}-reconstruct"
    code, seconds, peak = run_child([sys.executable, "-m", "sfm", "-q", "reconstruct", "--images",
                                     str(folder / "images"), "--workspace", str(ws), "--no-recording"])
    if code != 0 or not (ws / "sparse" / "0").is_dir():
        raise SystemExit(f"reconstruct of {n} photos failed with exit code {code}; see {ws / 'log.txt'}")
    report = json.loads((ws / "report.json").read_text())
    result = evaluate(read_model(ws / "sparse" / "0"), read_gt_table(folder / "gt" / "cameras_gt_opencv.txt"))
    row = {"photos": n, "wall_s": round(seconds), "peak_rss_gb": round(peak / 2**30, 2),
           **{f"{k}_s": round(v) for k, v in report["times_s"].items() if v is not None},
           "registered": f"{result.num_registered}/{n}", "auc@1": round(result.auc[1.0], 4),
           "auc@5": round(result.auc[5.0], 4), "med_rot_deg": round(result.median_rotation_error_deg, 4),
           "pairs": report["pairs_tried"], "clusters": report["num_clusters"]}
    print(markdown_table([row]), flush=True)
    return row


def partial_row(out: Path, n: int) -> dict | None:
    """What an unfinished end-to-end run of ``n`` photos measured: its report's stage times,
    pairs, verified pairs and clusters so far (None when it has no report)."""
    report_path = out / f"survey{n}-reconstruct" / "report.json"
    if not report_path.is_file():
        return None
    from sfm.io.database import Database

    report = json.loads(report_path.read_text())
    with Database(report_path.parent / "database.db", readonly=True) as db:
        pairs, (_, _, verified) = len(db.pairs_with_geometry()), db.verified_pairs(15)
    return {"photos": n, **{f"{k}_s": round(v) for k, v in report["times_s"].items() if v},
            "status": report.get("status"), "pairs": pairs, "verified": len(verified),
            "clusters": report.get("num_clusters")}


STAGE_COLUMNS = ("extract_s", "match_s", "cluster_s", "map_s", "merge_s", "final_ba_s", "extend_s", "total_s")


def with_earlier_invocation(finished: dict, partial: dict | None) -> dict:
    """A run that an earlier, unfinished invocation started (``--record-partial``'s row of the
    same photos) and a resumed one finished: each stage's seconds summed over the two (the time
    the model took), ``wall_s`` and ``peak_rss_gb`` those of the finishing invocation."""
    if not partial or partial.get("photos") != finished.get("photos"):
        return finished
    row = dict(finished)
    for column in STAGE_COLUMNS:
        if column in partial or column in finished:
            row[column] = finished.get(column, 0) + partial.get(column, 0)
    row["invocations"] = 2
    return row


def finished_runs(results: dict) -> list[dict]:
    """The finished end-to-end runs by size, each summed with its unfinished earlier invocation."""
    partial = results.get("endtoend_partial", {})
    return sorted((with_earlier_invocation(r, partial.get(k)) for k, r in results.get("endtoend", {}).items()),
                  key=lambda r: r["photos"])


def part_projection(runs: list[dict]) -> list[dict]:
    """Stage times at 10,000 and 50,000 photos from the measured ones (see the module docstring)."""
    runs = sorted(runs, key=lambda r: r["photos"])
    if not runs:
        return []
    big = runs[-1]
    exponent = 1.0
    if len(runs) >= 2:
        small = runs[-2]
        tail = lambda r: r.get("merge_s", 0) + r.get("final_ba_s", 0)  # noqa: E731
        if tail(small) > 0 and tail(big) > 0:
            exponent = float(np.log(tail(big) / tail(small)) / np.log(big["photos"] / small["photos"]))
    rows = []
    for n in (10_000, 50_000):
        f = n / big["photos"]
        linear = {s: big.get(f"{s}_s", 0) * f for s in ("extract", "match", "cluster", "map")}
        tail = {s: big.get(f"{s}_s", 0) * f ** max(exponent, 1.0) for s in ("merge", "final_ba")}
        for machines in (1, 10):
            stages = {s: v / machines if s in ("extract", "match", "map") else v for s, v in linear.items()} | tail
            bound = max(stages, key=stages.get)
            rows.append({"photos": n, "machines": machines, **{f"{s}_h": round(v / 3600, 2) for s, v in stages.items()},
                         "total_h": round(sum(stages.values()) / 3600, 1), "bound by": bound,
                         "merge+BA exponent": round(exponent, 2)})
    print(markdown_table(rows), flush=True)
    return rows


# ------------------------------------------------------------------------------ page
def page_text(results: dict) -> str:
    contexts = results.get("contexts", {})

    def measured(key: str) -> str:
        c = contexts.get(key, {})
        return f"\n\nMeasured {c.get('date')} on {c.get('machine')}; graphsfm at {c.get('code')}." if c else ""

    parts = ["Each part measured by `python tools/bench_scale.py --out DIR --parts PART` (its docstring says how); "
             "the survey is `graphsfm synth --scene survey` (1600x1200 JPEGs, EXIF focal and GPS, exact GT)."]
    if results.get("matcher"):
        parts.append("### Match stage: the default (inverted file) against `--matcher brute`, same database\n\n"
                     + markdown_table(results["matcher"]) + measured("matcher"))
    if results.get("frontend"):
        parts.append("### Front end on the same 200 survey photos and the same pairs: graphsfm against pycolmap\n\n"
                     + markdown_table(results["frontend"]) + measured("frontend"))
    if results.get("retrieval"):
        parts.append("### Pairs against the 200-photo survey's co-visibility (ground truth)\n\n"
                     + markdown_table(results["retrieval"]) + measured("retrieval"))
    if results.get("endtoend"):
        parts.append("### Survey photos to model, defaults, one machine\n\n" + markdown_table(finished_runs(results))
                     + measured("endtoend") + "\n\nA run with `invocations` 2 was finished by resuming an unfinished "
                     "one (below): its stage times are summed over both, `wall_s` and `peak_rss_gb` are the "
                     "finishing invocation's.")
    if results.get("endtoend_partial"):
        parts.append("### Runs recorded unfinished: the stages their report.json had finished when recorded (`--record-partial`; "
                     "`--parts endtoend` resumes a run)\n\n"
                     + markdown_table(sorted(results["endtoend_partial"].values(), key=lambda r: r["photos"]))
                     + measured("endtoend_partial"))
    if results.get("projection"):
        parts.append("### Projected from the largest run (hours)\n\n" + markdown_table(results["projection"])
                     + measured("projection"))
    return "\n\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--sizes", nargs="+", type=int, default=[1000, 2000, 5000])
    parser.add_argument("--force", nargs="*", choices=PARTS, default=[])
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument("--record-partial", action="store_true",
                        help="record what the unfinished end-to-end runs of --sizes measured so far, then report")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    store = args.out / "results.json"
    results = json.loads(store.read_text()) if store.is_file() else {}

    def save(key: str, value) -> None:
        results[key] = value
        results.setdefault("contexts", {})[key] = run_context()
        tmp = store.with_suffix(".tmp")
        tmp.write_text(json.dumps(results, indent=1))
        tmp.replace(store)

    if args.record_partial:
        finished = results.get("endtoend", {})
        rows = {k: v for k, v in results.get("endtoend_partial", {}).items() if k in finished}  # kept for the sums
        rows |= {str(n): row for n in args.sizes if str(n) not in finished
                 and (row := partial_row(args.out, n)) is not None}
        save("endtoend_partial", rows)
    elif not args.report_only:
        threads = len(os.sched_getaffinity(0))
        for part in args.parts:
            if part in results and part not in args.force and part != "endtoend":
                print(f"{part}: cached (--force {part} to measure again)")
                continue
            print(f"--- {part}", flush=True)
            if part == "matcher":
                save(part, part_matcher(args.out, args.data))
            elif part == "frontend":
                save(part, part_frontend(args.out, threads))
            elif part == "retrieval":
                save(part, part_retrieval(args.out))
            elif part == "endtoend":
                runs = dict(results.get("endtoend", {}))
                for n in args.sizes:
                    if str(n) in runs and "endtoend" not in args.force:
                        print(f"endtoend {n}: cached")
                        continue
                    runs[str(n)] = part_endtoend(args.out, n)
                    save("endtoend", runs)
            elif part == "projection":
                save(part, part_projection(finished_runs(results)))
    text = page_text(results)
    print(text)
    publish(args, "scale", "Scale: front end, pairs and survey photos to model", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
