"""Time against number of images: graphsfm (1 and 2 workers) and pycolmap's incremental, global
and hierarchical mappers on the same synthetic aerial databases (the paper's efficiency table,
Table 2).

    python tools/bench_scaling.py --out DIR [--sizes 250 500 1000 2000 4000] [--skip-peers-above N]

For each size, ``graphsfm synth --scene aerial --outlier-ratio 0.2 --seed 0`` makes
``DIR/data/<n>/database.db`` once; every method then maps a copy of that same database in its
own child process, from database to final model (graphsfm: cluster, map, merge and final BA
with default options).  Each run's result is cached in ``DIR/runs/<n>/<method>.json``, so an
interrupted benchmark resumes where it stopped (``--force`` reruns).  Peak memory is the
largest summed RSS of the run's process tree, sampled every 0.2 s.  Writes ``DIR/scaling.md``
(the table, the time ratio to COLMAP's incremental mapper, and the exponent b of a least-squares
fit t = a n^b over 500..4000 images) and ``DIR/scaling.png`` (log-log); ``--report-only`` writes
them from the cached results alone (say, after runs of different sizes or methods).  Peers are skipped above
``--skip-peers-above`` images (the table says so).  Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_page import add_page_arguments, machine, publish  # noqa: E402

METHODS = ("graphsfm-1", "graphsfm-2", "colmap-incremental", "colmap-global", "colmap-hierarchical")
PEERS = ("colmap-incremental", "colmap-global", "colmap-hierarchical")


def tree_rss(pid: int) -> int:
    """Summed resident memory (bytes) of ``pid`` and all its descendants, from /proc."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
                children.setdefault(ppid, []).append(int(entry))
            except (OSError, ValueError, IndexError):
                continue
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        todo.extend(children.get(p, []))
        try:
            with open(f"/proc/{p}/statm") as f:
                total += int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, IndexError):
            continue
    return total


def run_child(argv: list[str]) -> tuple[int, float, int]:
    """(return code, seconds, peak tree RSS in bytes) of a child process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv)
    peak = [0]

    def sample() -> None:
        while proc.poll() is None:
            peak[0] = max(peak[0], tree_rss(proc.pid))
            time.sleep(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    code = proc.wait()
    sampler.join()
    return code, time.perf_counter() - t0, peak[0]


# The child's exit code when COLMAP's incremental mapper stopped at --peer-budget (resumable).
STOPPED = 3


def make_aerial(data: Path, n: int) -> None:
    """``graphsfm synth --scene aerial --outlier-ratio 0.2 --seed 0`` of ``n`` images into
    ``data``, in a child process: the scene's arrays (gigabytes at 10,000 images) leave with it
    instead of staying in this process beside the runs it measures."""
    shutil.rmtree(data, ignore_errors=True)
    subprocess.run([sys.executable, "-m", "sfm", "-q", "synth", "--scene", "aerial", "--num-images", str(n),
                    "--outlier-ratio", "0.2", "--seed", "0", "--workspace", str(data)],
                   check=True, cwd=Path(__file__).resolve().parents[1], stdout=subprocess.DEVNULL)


def code_version(method: str) -> str:
    """What ran: for graphsfm, the git tree ids of ``sfm/``, ``graph/`` and ``backend/`` (one
    short hash, so rows from commits that differ only in tools or docs compare as the same code;
    ``+dirty`` when those folders have uncommitted changes); for a peer, pycolmap's version."""
    if method in PEERS:
        import pycolmap

        return f"pycolmap {pycolmap.__version__}"
    import hashlib

    root = Path(__file__).resolve().parents[1]
    git = lambda *a: subprocess.run(["git", "-C", str(root), *a], capture_output=True, text=True)
    trees = git("rev-parse", "HEAD:sfm", "HEAD:graph", "HEAD:backend")
    if trees.returncode != 0:
        return "unknown (not a git checkout)"
    dirty = git("status", "--porcelain", "--", "sfm", "graph", "backend").stdout.strip()
    return "code " + hashlib.sha1(trees.stdout.encode()).hexdigest()[:8] + ("+dirty" if dirty else "")


def one_run(out: Path, n: int, method: str, budget_s: float | None = None) -> int:
    """The child: map DIR/data/<n>/database.db with ``method`` (bench_mapping's runners, the
    time from database to final model); write its metrics to ``result.json``.  COLMAP's
    incremental mapper resumes an earlier stopped run (``resumable_colmap``) and stops after
    ``budget_s`` seconds (exit code ``STOPPED``)."""
    import logging

    from bench_mapping import row, run_colmap, run_graphsfm
    from resumable_colmap import run_incremental

    from sfm.clustering.options import ClusterOptions
    from sfm.evaluation.ground_truth import read_gt_table

    logging.basicConfig(level=logging.WARNING)
    data, work = out / "data" / str(n), out / "runs" / str(n) / method
    extra = {}
    if method == "colmap-incremental":
        model_dir, seconds, finished, segments = run_incremental(data / "database.db", work, budget_s)
        if not finished:
            print(f"  stopped after the budget at {seconds:.0f} s credited; the next run resumes", flush=True)
            return STOPPED
        extra["segments"] = segments
    elif method.startswith("graphsfm"):  # the default cluster size, as graphsfm cluster uses
        shutil.rmtree(work, ignore_errors=True)
        s_max = ClusterOptions().max_cluster_size
        model_dir, seconds, _ = run_graphsfm(data / "database.db", work, s_max, int(method.split("-")[1]))
    else:
        shutil.rmtree(work, ignore_errors=True)
        model_dir, seconds = run_colmap(data / "database.db", work, method.split("-")[1])
    r = row(method, model_dir if model_dir is not None and model_dir.exists() else None, seconds,
            read_gt_table(data / "gt" / "cameras_gt_opencv.txt"))
    result = {"images": n, **{k: r[k] for k in ("method", "time_s", "registered", "points", "med_rot_deg", "auc@1")
                              if k in r}, **extra,
              "code": code_version(method), "date": datetime.date.today().isoformat(), "machine": machine()}
    (work / "database.db").unlink()
    (work / "result.json").write_text(json.dumps(result))
    return 0


def fit_exponent(rows: list[dict], lo: int = 500) -> float | None:
    import numpy as np

    pts = [(r["images"], r["time_s"]) for r in rows if r["images"] >= lo and r.get("time_s")]
    if len(pts) < 2:
        return None
    n, t = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(n, t, 1)[0])


def unfinished(out: Path, n: int, method: str) -> str:
    """"not run", or how far a run without a result got by its progress log."""
    try:
        seconds, count = (out / "runs" / str(n) / method / "progress.txt").read_text().split()[-2:]
    except (OSError, ValueError):
        return "not run"
    return f"> {float(seconds):.0f} (stopped unfinished: {count}/{n} registered by then)"


def report(out: Path, sizes: list[int], results: dict, skip_peers_above: int | None = None) -> str:
    head = ["images", "method", "time_s", "peak_rss_gb", "registered", "points", "med_rot_deg", "auc@1",
            "time / colmap-incremental", "time / colmap-global", "code", "date", "machine"]
    machine = (f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
               f"Python {platform.python_version()}; command: python tools/bench_scaling.py --out {out} "
               f"--sizes {' '.join(map(str, sizes))}")
    lines = [machine, "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for n in sizes:
        base = results.get((n, "colmap-incremental"), {}).get("time_s")
        base_global = results.get((n, "colmap-global"), {}).get("time_s")
        for m in METHODS:
            r = results.get((n, m))
            if r is None:
                skipped = m in PEERS and skip_peers_above is not None and n > skip_peers_above
                why = f"skipped (peers above {skip_peers_above} images)" if skipped else unfinished(out, n, m)
                lines.append(f"| {n} | {m} | {why} |" + " |" * (len(head) - 3))
                continue
            ratio = f"{r['time_s'] / base:.2f}" if base and r.get("time_s") else ""
            ratio_global = f"{r['time_s'] / base_global:.2f}" if base_global and r.get("time_s") else ""
            cells = [str(r.get(k, "")) for k in head[:-5]] + [ratio, ratio_global, r.get("code", "not recorded"),
                                                              r.get("date", "not recorded"), r.get("machine", "")]
            lines.append("| " + " | ".join(cells) + " |")
    resumed = [f"{m} at {n} images ran in {r['segments']} segments (stopped at --peer-budget and resumed from "
               "its snapshots; its time is their sum)" for (n, m), r in sorted(results.items()) if r.get("segments", 1) > 1]
    lines += [""] + [f"- {line}" for line in resumed] if resumed else []
    lines += ["", "code: the graphsfm code that ran (a hash of the git trees of sfm/, graph/ and backend/) "
              "or the peer's version; rows with one code come from the same algorithm code."]
    lines += ["", "Fitted exponent b of t = a n^b over 500 images and up, on the rows of the code of each "
              "method's newest row:"]
    for m in METHODS:
        rows = [r for (n, mm), r in sorted(results.items()) if mm == m]
        newest = max(rows, key=lambda r: (r.get("date", ""), r["images"])).get("code") if rows else None
        same = [r for r in rows if r.get("code") == newest]
        b = fit_exponent(same)
        fitted = sum(1 for r in same if r["images"] >= 500)
        lines.append(f"- {m}: " + (f"{b:.2f} ({newest}, {fitted} sizes)" if b is not None else "too few sizes"))
    return "\n".join(lines) + "\n"


def plot(out: Path, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    for m in METHODS:
        rows = sorted((n, r["time_s"]) for (n, mm), r in results.items() if mm == m and r.get("time_s"))
        if rows:
            b = fit_exponent([{"images": n, "time_s": t} for n, t in rows])
            label = m + (f" (b = {b:.2f})" if b is not None else "")
            ax.plot([n for n, _ in rows], [t for _, t in rows], "o-", label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("images (synthetic aerial, 20% outlier matches)")
    ax.set_ylabel("time from database to final model (s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "scaling.png", dpi=120)


def run_method(out: Path, n: int, method: str, budget_s: float | None, force: bool) -> dict | None:
    """One method at one size in a child process: its result row (peak memory over every
    segment of a resumed run), or None when it failed or stopped at the budget."""
    work = out / "runs" / str(n) / method
    if force:
        shutil.rmtree(work, ignore_errors=True)
    print(f"{n} images, {method} ...", flush=True)
    argv = [sys.executable, __file__, "--out", str(out), "--run", str(n), method]
    code, seconds, peak = run_child(argv + (["--budget", str(budget_s)] if budget_s else []))
    peaks_file = work / "segment_peaks.json"
    peaks = json.loads(peaks_file.read_text()) if peaks_file.exists() else []
    if code == STOPPED:
        peaks_file.write_text(json.dumps(peaks + [peak]))
        return None
    if code != 0:
        print(f"  failed with exit code {code}; not cached", flush=True)
        return None
    r = json.loads((work / "result.json").read_text())
    earlier = peaks[-(r.get("segments", 1) - 1):] if r.get("segments", 1) > 1 else []  # this run's segments
    peaks_file.unlink(missing_ok=True)
    r["peak_rss_gb"] = round(max(earlier + [peak]) / 1024**3, 2)
    r["wall_s"] = round(seconds, 1)
    print(f"  {r['time_s']} s, {r['registered']}/{n} registered, peak {r['peak_rss_gb']} GB", flush=True)
    return r


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder for data, cached runs, scaling.md/png")
    parser.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000, 2000, 4000])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--skip-peers-above", type=int, default=2000, help="no pycolmap run above this size")
    parser.add_argument("--force", action="store_true", help="rerun cached results")
    parser.add_argument("--report-only", action="store_true",
                        help="run nothing: the table and plot from the cached results of --sizes and --methods")
    parser.add_argument("--peer-budget", type=float, metavar="SECONDS",
                        help="stop COLMAP's incremental mapper after this long in this run; the next run resumes "
                             "it from its last snapshot (its time is the sum of the segments)")
    parser.add_argument("--run", nargs=2, metavar=("N", "METHOD"), help=argparse.SUPPRESS)  # the child
    parser.add_argument("--budget", type=float, help=argparse.SUPPRESS)  # the child's --peer-budget
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    out = args.out.resolve()
    if args.run:
        return one_run(out, int(args.run[0]), args.run[1], args.budget)
    results: dict = {}
    for n in args.sizes:
        data = out / "data" / str(n)
        if not (data / "database.db").exists() and not args.report_only:
            make_aerial(data, n)
        for m in METHODS:  # the table shows every cached row, of methods not run this time too
            cache = out / "runs" / str(n) / f"{m}.json"
            run_now = m in args.methods and not args.report_only and not (m in PEERS and n > args.skip_peers_above)
            if cache.exists() and not (run_now and args.force):
                results[(n, m)] = json.loads(cache.read_text())
            elif run_now:
                r = run_method(out, n, m, args.peer_budget, args.force)
                if r is not None:
                    cache.write_text(json.dumps(r))
                    results[(n, m)] = r
        text = report(out, args.sizes, results, args.skip_peers_above)
        (out / "scaling.md").write_text(text)
    print(text)
    if results:
        plot(out, results)
        publish(args, "scaling", "Time and memory against the number of images (synthetic aerial, 20% outlier matches)",
                text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
