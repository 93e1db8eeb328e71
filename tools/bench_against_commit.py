"""Total time of a default ``graphsfm reconstruct``: this checkout against an earlier commit, in one run.

    python tools/bench_against_commit.py --base REF --sets lund_door temple_ring [--repeat N] [--data DIR] [--out DIR]

The peer here is graphsfm itself at ``--base`` (a commit or tag): its ``sfm/``, ``graph/`` and
``backend/`` are exported by ``git archive`` into ``OUT/base``, and each side runs as a user
runs it, ``graphsfm reconstruct --images SET/images --workspace W -q`` (supervisor, every
stage, the Rerun recording), in a fresh workspace, with the same interpreter and packages:
``graphsfm`` is what that commit's ``pyproject.toml`` names as the script's entry point, called
as pip's script calls it.  Both sides run ``--repeat`` times on each set, alternating which goes first (a shared
machine drifts by tens of percent within minutes).  Each run's model is evaluated against the
set's ground truth (``gt/cameras_gt_opencv.txt``) by this checkout's evaluator.  Prints every
run and, per set, the medians of the wall time and of the map stage, and the ratio of the
medians; refreshes its section of ``tools/BENCHMARKS.md``.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tarfile
import time
import tomllib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_page import ROOT, add_page_arguments, markdown_table, publish, run_context

from sfm.evaluation.ground_truth import read_gt_table
from sfm.evaluation.metrics import evaluate
from sfm.io.colmap_model import read_model

def export_tree(ref: str, dest: Path) -> str:
    """``sfm/``, ``graph/`` and ``backend/`` of commit ``ref`` into ``dest``; its short hash."""
    short = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=7", ref], capture_output=True, text=True,
                           check=True).stdout.strip()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "sfm", "graph", "backend"], capture_output=True,
                             check=True).stdout
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(dest)
    return short


def program(ref: str | None) -> list[str]:
    """The ``graphsfm`` script of commit ``ref`` (None: this checkout) as a command: the
    interpreter calling the entry point its ``pyproject.toml`` names, as pip's script does."""
    text = (ROOT / "pyproject.toml").read_text() if ref is None else subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{ref}:pyproject.toml"], capture_output=True, text=True, check=True).stdout
    module, _, func = tomllib.loads(text)["project"]["scripts"]["graphsfm"].partition(":")
    return [sys.executable, "-c", f"import sys; from {module} import {func}; sys.exit({func}())"]


def run_side(tree: Path, command: list[str], images: Path, workspace: Path, gt: Path) -> dict:
    """One default reconstruct with the code of ``tree`` run by ``command`` (:func:`program`):
    wall seconds, map stage, AUC@1."""
    if workspace.exists():
        shutil.rmtree(workspace)
    env = dict(os.environ, PYTHONPATH=str(tree))
    t0 = time.perf_counter()
    done = subprocess.run([*command, "reconstruct", "--images", str(images), "--workspace", str(workspace), "-q"],
                          env=env, capture_output=True, text=True,
                          cwd=workspace.parent)  # not the checkout: "python -c" puts the working directory first on sys.path
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"reconstruct failed with {tree}: {done.stderr.strip().splitlines()[-1:]}")
    report = json.loads((workspace / "report.json").read_text())
    metrics = evaluate(read_model(workspace / "sparse" / "0"), read_gt_table(gt))
    return {"wall": wall, "map": report["times_s"]["map"], "auc1": metrics.auc[1], "registered": report["registered"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", required=True, help="the earlier commit (or tag) to time against")
    parser.add_argument("--sets", nargs="+", default=["lund_door", "temple_ring"],
                        help="sets of ../shared/data with images/ and gt/cameras_gt_opencv.txt")
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data", help="folder of the real sets")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each side per set (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_against_commit"), help="workspaces")
    add_page_arguments(parser)
    args = parser.parse_args()
    base = export_tree(args.base, args.out / "base")
    context = run_context()
    sides = {"base": (args.out / "base", program(args.base), base), "head": (ROOT, program(None), context["code"])}
    runs, summary = [], []
    for name in args.sets:
        images, gt = args.data / name / "images", args.data / name / "gt" / "cameras_gt_opencv.txt"
        if not images.is_dir() or not gt.is_file():
            raise SystemExit(f"{name}: no {images} or {gt}")
        measured = {"base": [], "head": []}
        for rep in range(args.repeat):
            for side in (("base", "head") if rep % 2 == 0 else ("head", "base")):
                tree, command, code = sides[side]
                r = run_side(tree, command, images, args.out / f"{name}_{side}", gt)
                measured[side].append(r)
                runs.append({"set": name, "run": rep + 1, "code": code, "wall_s": round(r["wall"], 1),
                             "map_s": round(r["map"], 1), "registered": r["registered"], "auc@1": round(r["auc1"], 4)})
                print(markdown_table(runs[-1:]).splitlines()[-1], flush=True)
        med = {side: statistics.median(r["wall"] for r in rs) for side, rs in measured.items()}
        summary.append({"set": name, "runs": args.repeat, f"wall_s {base}": round(med["base"], 1),
                        f"wall_s {context['code']}": round(med["head"], 1), "ratio": round(med["head"] / med["base"], 3),
                        f"map_s {base}": round(statistics.median(r["map"] for r in measured["base"]), 1),
                        f"map_s {context['code']}": round(statistics.median(r["map"] for r in measured["head"]), 1),
                        "date": context["date"], "machine": context["machine"]})
    text = (f"Medians of {args.repeat} interleaved runs per side (ratio: this checkout over {base}):\n\n"
            f"{markdown_table(summary)}\n\nEvery run:\n\n{markdown_table(runs)}")
    print(text)
    publish(args, "against-commit", f"Total time of a default reconstruct against {base}", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
