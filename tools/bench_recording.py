"""What the Rerun recording costs: a run with it and without it, side by side, and its size.

    python tools/bench_recording.py [--images DIR] [--num-images 30] [--max-cluster-size 12]
                                    [--repeat 3] [--workers 0] [--out DIR]

Without ``--images``, the demo's scene (``graphsfm demo``: the rendered facade, 30 views, S_max
12) is rendered into ``--out``.  ``graphsfm reconstruct`` runs on it, each time in a process of
its own, ``--repeat`` times with the recording and as often with ``--no-recording``, interleaved (on/off, then off/on, ...), each in a
fresh workspace, so both sides see the same machine load.  The table gives each run's stage times,
total wall time and recording size; the cost line the median time with the recording over the
median without.

A second table measures what the points' colours cost, which every run pays: per image, the
extract worker's grey decode and SIFT against the extra colour decode and the bilinear reads at
the keypoints (single-threaded, in this process).  The colour decode alone is also what reading
the registered images again at the end would cost (COLMAP's way), there serially in one process.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_page import add_page_arguments, markdown_table, publish, run_context  # noqa: E402

from sfm.synthetic.options import DemoOptions, RenderOptions  # noqa: E402
from sfm.synthetic.rendered import write_rendered_scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("T_feat", "T_match", "T_GC", "T_SfM", "T_merge", "T_BA")


def run_once(images: Path, workspace: Path, recording: bool, options: list[str]) -> dict:
    """``graphsfm reconstruct`` in a process of its own (imports included, as a user runs it)."""
    shutil.rmtree(workspace, ignore_errors=True)
    command = [sys.executable, "-m", "sfm", "reconstruct", "--images", str(images), "--workspace", str(workspace),
               "--recording" if recording else "--no-recording", *options]
    t0 = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    seconds = time.perf_counter() - t0
    report = json.loads((workspace / "report.json").read_text())
    rrd = workspace / "recording.rrd"
    row = {"recording": "on" if recording else "off", "time_s": round(seconds, 1)}
    row.update({k: round(report["times"].get(k, 0.0), 1) for k in STAGES})
    row["registered"] = report.get("registered")
    row["points"] = report.get("points")
    row["recording_mb"] = round(rrd.stat().st_size / 1e6, 1) if rrd.exists() else 0.0
    return row


def colour_cost(images: Path, limit: int = 10) -> dict:
    """Milliseconds per image (median): grey decode + SIFT, colour decode, colours at keypoints."""
    import cv2

    from sfm.features.colors import keypoint_colors
    from sfm.features.extraction import extract_features
    from sfm.features.options import ExtractOptions
    from sfm.io.image_files import find_images, read_gray, read_rgb

    cv2.setNumThreads(1)  # as in a worker
    sift, decode, sample, keypoints = [], [], [], []
    for name in find_images(images)[:limit]:
        data = (images / name).read_bytes()
        t0 = time.perf_counter()
        gray, _ = read_gray(data)
        kp, _ = extract_features(gray, ExtractOptions())
        t1 = time.perf_counter()
        rgb = read_rgb(data)
        t2 = time.perf_counter()
        keypoint_colors(rgb, kp)
        t3 = time.perf_counter()
        sift.append(1e3 * (t1 - t0))
        decode.append(1e3 * (t2 - t1))
        sample.append(1e3 * (t3 - t2))
        keypoints.append(len(kp))
    med = statistics.median
    return {"images": len(sift), "keypoints": int(med(keypoints)), "grey_decode_and_sift_ms": round(med(sift), 1),
            "colour_decode_ms": round(med(decode), 1), "colours_at_keypoints_ms": round(med(sample), 2),
            "extra_share": f"{100 * (med(decode) + med(sample)) / med(sift):.1f}%"}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=Path, help="an image folder (default: the demo's rendered scene)")
    parser.add_argument("--num-images", type=int, default=DemoOptions().num_images)
    parser.add_argument("--max-cluster-size", type=int, default=DemoOptions().max_cluster_size)
    parser.add_argument("--repeat", type=int, default=3, help="runs with and without the recording (default 3)")
    parser.add_argument("--workers", type=int, default=0, help="worker processes (default: one per core)")
    parser.add_argument("--out", type=Path, default=Path("bench_recording"), help="working folder")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    images = args.images
    if images is None:
        scene = write_rendered_scene(args.out / "scene", RenderOptions(num_images=args.num_images, seed=DemoOptions().seed))
        images = Path(scene["image_dir"])
    options = ["--max-cluster-size", str(args.max_cluster_size), "--workers", str(args.workers), "--seed", "0"]
    context = run_context()
    rows = []
    for k in range(args.repeat):
        for recording in ((True, False) if k % 2 == 0 else (False, True)):
            row = {"run": k + 1, **run_once(images, args.out / f"ws_{'on' if recording else 'off'}", recording, options),
                   **context}
            rows.append(row)
            print(json.dumps(row), flush=True)
    on = statistics.median(r["time_s"] for r in rows if r["recording"] == "on")
    off = statistics.median(r["time_s"] for r in rows if r["recording"] == "off")
    size = max(r["recording_mb"] for r in rows)
    cost = (f"recording cost: median {on:.1f} s with, {off:.1f} s without: {100 * (on / off - 1):+.1f}% "
            f"({args.repeat} runs each, interleaved); recording {size:.1f} MB")
    colours = {**colour_cost(images), **context}
    keys = ["run", "recording", "time_s", *STAGES, "registered", "points", "recording_mb", "date", "machine", "code"]
    text = (f"{images}: {len(list(images.glob('*')))} images, S_max {args.max_cluster_size}\n\n"
            f"{markdown_table(rows, keys)}\n\n{cost}\n\nWhat the points' colours cost at extraction, per image "
            f"(median, one thread):\n\n{markdown_table([colours])}")
    print(text)
    publish(args, "recording", "What the Rerun recording and the point colours cost", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
