"""Two clusterings side by side on the same databases: the whole run from cluster to merged model.

    python tools/bench_clustering.py --out DIR [--sets demo lund_door temple_ring aerial500 ...]
                                     [--baseline COMMIT] [--seeds 0 1 2] [--repeat 1] [--workers 2]

For each set, the database is made once (``DIR/data/<set>``, by this checkout's code): the demo's
rendered scene (30 views, seed 0; ``demo-dK``: rendered with seed K) and the real ``lund_door`` and ``temple_ring`` photos (from
``--data``) are extracted and matched with default options; the aerial sets are
``graphsfm synth --scene aerial --images N --outlier-ratio 0.2 --seed 0`` (``aerialN-dK``: ``--seed K``,
another draw of the same block).  Then each variant
(the ``--baseline`` commit, unpacked by ``git archive`` into ``DIR/code/<commit>``, and a copy of
this checkout's code taken at the start) runs ``cluster`` (with the set's ``--max-cluster-size``,
other options default), ``map`` (``--workers`` local workers) and ``merge`` on its own copy of
the database, in a child process whose ``PYTHONPATH`` and working directory are that variant's
code, once per ``--seeds`` value (the seed of the clustering, the mappers and the merge) and
``--repeat``.  The variants alternate which goes first, run after run, so both see the same load.

Writes every run to ``DIR/clustering.md`` and ``DIR/runs.json``, and one row per set and variant
(medians over the runs, [min, max] where they differ) to the ``bench_clustering`` section of
``tools/BENCHMARKS.md`` (created if needed; rows of sets not measured this time are kept).
Columns: clusters, largest core and cluster, how many clusters hold every image, summed cluster
sizes, warnings of ``cluster``, the times of local SfM (``map``) and of merge + final BA, the
merged models (1: every local model was aligned into one), registered images, median rotation
error, AUC@1 and AUC@5 against the ground truth.
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
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SETS = {  # name: (max cluster size, how the database is made)
    "demo": 12,
    # Other renders of the demo's facade (``-dK``: rendered with seed K): its texture, the camera
    # arc's jitter and so the features differ, and the merged models' errors with them.
    "demo-d1": 12,
    "demo-d2": 12,
    "lund_door": 5,
    "temple_ring": 15,
    "aerial500": 100,
    "aerial1000": 100,
    "aerial2000": 100,
}
# Other synthetic draws of the aerial blocks (``-dK``: synthesised with seed K): a nadir block's
# calibration and tilt trade along a flat valley, and each draw's estimates land at their own point.
SETS.update({f"aerial{n}-d{k}": 100 for n in (500, 1000, 2000) for k in (1, 2)})
SECTION = "bench:clustering"
BASELINE = "07cbda0"  # main before the bounded clustering: the unbounded expansion


def git(*args: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", "-C", str(cwd), *args], capture_output=True, text=True, check=True).stdout.strip()


def code_version(code: Path) -> str:
    """The commit a variant's code comes from, and a hash of its ``sfm/``, ``graph/`` and
    ``backend/`` trees (``+dirty`` when this checkout has uncommitted changes there)."""
    if code == ROOT:
        commit = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--", "sfm", "graph", "backend")
        return commit + ("+dirty" if dirty else "")
    return (code / "COMMIT").read_text().strip()


def baseline_code(out: Path, commit: str) -> Path:
    """The baseline commit's files in ``DIR/code/<commit>`` (``git archive``, no worktree)."""
    full = git("rev-parse", commit)
    dest = out / "code" / full[:10]
    if not (dest / "COMMIT").exists():
        shutil.rmtree(dest, ignore_errors=True)
        dest.mkdir(parents=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", full], capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
        (dest / "COMMIT").write_text(full[:7] + "\n")
    return dest


def current_code(out: Path) -> Path:
    """A copy of this checkout's ``sfm/``, ``graph/`` and ``backend/`` (uncommitted changes
    included), so that edits made while the benchmark runs do not reach its runs."""
    version = code_version(ROOT)
    dest = out / "code" / ("current-" + version)
    shutil.rmtree(dest, ignore_errors=True)
    for package in ("sfm", "graph", "backend"):
        shutil.copytree(ROOT / package, dest / package, ignore=shutil.ignore_patterns("__pycache__"))
    (dest / "COMMIT").write_text(version + "\n")
    return dest


def make_data(out: Path, name: str, data_root: Path) -> tuple[Path, Path]:
    """``(database, GT table)`` of a set, made once by this checkout."""
    folder = out / "data" / name
    if name.startswith("demo"):  # the rendered scene's own GT
        gt = folder / "scene" / "gt" / "cameras_gt_opencv.txt"
    elif name in ("lund_door", "temple_ring"):  # real photos: the dataset's GT
        gt = data_root / name / "gt" / "cameras_gt_opencv.txt"
    else:  # synthetic: written with the database
        gt = folder / "gt" / "cameras_gt_opencv.txt"
    if (folder / "database.db").exists() and (folder / "done").exists():
        return folder / "database.db", gt
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    if name.startswith("aerial"):
        from sfm.stages.synth import run_synth
        from sfm.synthetic.options import SynthOptions

        shutil.rmtree(folder)
        size, _, draw = name[len("aerial"):].partition("-d")
        run_synth(folder, SynthOptions(scene="aerial", num_images=int(size), outlier_ratio=0.2, seed=int(draw or 0)))
    else:
        from sfm.features.options import ExtractOptions
        from sfm.matching.options import MatchOptions
        from sfm.stages.extract import run_extract
        from sfm.stages.match import run_match

        if name.startswith("demo"):  # the scene of `graphsfm demo`: its default 30 views, seed 0 (-dK: seed K)
            from sfm.synthetic.options import RenderOptions
            from sfm.synthetic.rendered import write_rendered_scene

            draw = int(name.partition("-d")[2] or 0)
            images = Path(write_rendered_scene(folder / "scene", RenderOptions(num_images=30, seed=draw))["image_dir"])
        else:
            images = data_root / name / "images"
        run_extract(images, folder, ExtractOptions())
        run_match(folder, MatchOptions())
    (folder / "done").write_text("")
    return folder / "database.db", gt


def child(work: Path, db: Path, gt: Path, s_max: int, workers: int, seed: int, keep: bool = False) -> int:
    """One variant on one set (runs with the variant's code first on sys.path): cluster, map and
    merge a copy of ``db`` in ``work``; writes ``work/result.json`` (``keep``: the workspace's
    database and local models stay, to merge them again)."""
    import logging

    from sfm.clustering.options import ClusterOptions
    from sfm.evaluation.ground_truth import read_gt_table
    from sfm.evaluation.metrics import evaluate
    from sfm.execution.local import LocalExecutor
    from sfm.io.colmap_model import read_model
    from sfm.mapper.options import MapperOptions
    from sfm.merge.options import MergeOptions
    from sfm.stages.cluster import run_cluster
    from sfm.stages.map import run_map
    from sfm.stages.merge import run_merge

    import sfm

    logging.basicConfig(level=logging.WARNING, format="%(levelname).1s %(name)s: %(message)s")
    assert Path(sfm.__file__).resolve().parents[1] == Path.cwd().resolve(), "the variant's code must be imported"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    shutil.copy(db, work / "database.db")
    t0 = time.perf_counter()
    run_cluster(work, ClusterOptions(max_cluster_size=s_max, seed=seed))
    t1 = time.perf_counter()
    mapped = run_map(work, MapperOptions(seed=seed), executor=LocalExecutor(workers))
    t2 = time.perf_counter()
    merged = None if mapped.direct else run_merge(work, MapperOptions(seed=seed), MergeOptions())
    t3 = time.perf_counter()
    clusters = json.loads((work / "clusters.json").read_text())
    num_images = clusters["num_images"]
    sizes = [len(c["members"]) for c in clusters["clusters"]]
    cores = [len(c["core"]) for c in clusters["clusters"]]
    result = {
        "clusters": len(sizes), "max_core": max(cores), "max_cluster": max(sizes), "images": num_images,
        "whole_scene_clusters": sum(s == num_images for s in sizes), "cluster_images": sum(sizes),
        "min_completeness": round(min(c["completeness"] for c in clusters["clusters"]), 3),
        "warnings": len(clusters.get("warnings", [])),
        "t_cluster": round(t1 - t0, 2), "t_map": round(t2 - t1, 1),
        "t_merge": round(merged.time_merge_s, 1) if merged else 0.0,
        "t_ba": round(merged.time_ba_s, 1) if merged else 0.0, "t_total": round(t3 - t0, 1),
    }
    merge_json = work / "merge.json"
    if merge_json.exists():
        plan = json.loads(merge_json.read_text())
        largest = max((len(c["clusters"]) for c in plan["components"]), default=0)
        result["merged_local_models"] = f"{largest}/{len(plan['nodes'])}"
    else:
        result["merged_local_models"] = "direct"
    result["models"] = merged.num_models if merged else len(mapped.models)
    model = read_model(work / "sparse" / "0")
    ev = evaluate(model, read_gt_table(gt))
    result.update({"registered": len(model.images), "med_rot_deg": round(ev.median_rotation_error_deg, 4),
                   "auc@1": round(ev.auc[1], 4), "auc@5": round(ev.auc[5], 4)})
    (work / "result.json").write_text(json.dumps(result))
    for sub in () if keep else ("database.db", "clusters"):  # the large files; the final model and JSONs stay
        p = work / sub
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
    return 0


def run_variant(code: Path, work: Path, db: Path, gt: Path, s_max: int, workers: int, seed: int,
                keep: bool = False) -> dict | None:
    argv = [sys.executable, str(Path(__file__).resolve()), "--child", str(work), str(db), str(gt), str(s_max),
            str(workers), str(seed), str(int(keep))]
    env = {**os.environ, "PYTHONPATH": str(code)}
    t0 = time.perf_counter()
    code_rc = subprocess.run(argv, cwd=code, env=env).returncode
    if code_rc != 0:
        print(f"  {work}: failed with exit code {code_rc}", flush=True)
        return None
    r = json.loads((work / "result.json").read_text())
    r["wall_s"] = round(time.perf_counter() - t0, 1)
    return r


RUN_HEAD = ["set", "S_max", "variant", "seed", "code", "clusters", "max core / cluster", "whole-scene clusters",
            "images in clusters", "min eta", "warnings", "T_SfM s", "T_merge s", "T_BA s", "T_total s", "models",
            "merged local models", "registered", "med rot deg", "AUC@1", "AUC@5"]
HEAD = ["set", "S_max", "variant", "code", "runs (seeds)", "clusters", "max core / cluster", "whole-scene clusters",
        "images in clusters", "warnings", "T_SfM s", "T_merge + T_BA s", "models", "merged local models",
        "registered", "med rot deg", "AUC@1", "AUC@5", "date", "machine"]


def run_row(r: dict) -> str:
    cells = [r["set"], r["s_max"], r["variant"], r["seed"], r["code"], r["clusters"],
             f"{r['max_core']} / {r['max_cluster']}", r["whole_scene_clusters"],
             f"{r['cluster_images']} ({r['images']})", r["min_completeness"], r["warnings"], r["t_map"], r["t_merge"],
             r["t_ba"], r["t_total"], r["models"], r["merged_local_models"], f"{r['registered']}/{r['images']}",
             r["med_rot_deg"], r["auc@1"], r["auc@5"]]
    return "| " + " | ".join(str(c) for c in cells) + " |"


def summary_row(runs: list[dict], date: str, machine: str) -> str:
    """One set and variant over its runs: medians, and [min, max] where runs differ."""
    import statistics

    def spread(key: str, digits: int = 4) -> str:
        values = [r[key] for r in runs]
        med = round(statistics.median(values), digits)
        return str(med) if min(values) == max(values) else f"{med} [{min(values)}, {max(values)}]"

    def span(key: str) -> str:
        values = sorted({str(r[key]) for r in runs})
        return values[0] if len(values) == 1 else ", ".join(values)

    r0 = runs[0]
    cells = [r0["set"], r0["s_max"], r0["variant"], r0["code"],
             f"{len(runs)} ({', '.join(sorted({str(r['seed']) for r in runs}))})", span("clusters"),
             ", ".join(sorted({f"{r['max_core']} / {r['max_cluster']}" for r in runs})), span("whole_scene_clusters"),
             ", ".join(sorted({f"{r['cluster_images']} ({r['images']})" for r in runs})), span("warnings"),
             spread("t_map", 1), str(round(statistics.median(r["t_merge"] + r["t_ba"] for r in runs), 1)),
             span("models"), span("merged_local_models"),
             ", ".join(sorted({f"{r['registered']}/{r['images']}" for r in runs})), spread("med_rot_deg"),
             spread("auc@1"), spread("auc@5"), date, machine]
    return "| " + " | ".join(str(c) for c in cells) + " |"


def refresh_benchmarks(rows: list[tuple[str, str]], command: str) -> None:
    """Write the rows into the ``bench_clustering`` section of tools/BENCHMARKS.md: a row of a
    set measured now replaces that set's earlier rows, other sets' rows stay."""
    path = ROOT / "tools" / "BENCHMARKS.md"
    text = path.read_text() if path.exists() else "# Benchmarks\n\nMeasured figures, written by the scripts in tools/.\n"
    begin, end = f"<!-- {SECTION} -->", f"<!-- /{SECTION} -->"
    old_rows: list[str] = []
    if begin in text:
        before, rest = text.split(begin, 1)
        body, after = rest.split(end, 1)
        old_rows = [line for line in body.splitlines() if line.startswith("| ") and not line.startswith("| set ")]
    else:
        before, after = text.rstrip("\n") + "\n\n", "\n"
    measured = {name for name, _ in rows}
    kept = [line for line in old_rows if line.split("|")[1].strip() not in measured]
    order = {name: k for k, name in enumerate(SETS)}
    all_rows = sorted(kept + [line for _, line in rows], key=lambda line: order.get(line.split("|")[1].strip(), 99))
    section = "\n".join([
        begin,
        "## Clustering: bounded clusters against the unbounded expansion (tools/bench_clustering.py)",
        "",
        "Both variants run cluster, map and merge on copies of the same database, one after the other, "
        "alternating which goes first; `code` is the commit the variant's code comes from. "
        "Times are seconds on the machine named in the row (noisy: compare rows of one date only). "
        "`max core / cluster`: the largest NCut core and the largest expanded cluster; `whole-scene clusters`: "
        "clusters holding every image; `images in clusters`: summed cluster sizes (scene images); `warnings`: "
        "clusters below C and thin MaxST overlaps reported by `cluster` (the baseline reports none); "
        "`merged local models`: local models in the largest merge component / all local models. "
        f"Last command: `{command}`.",
        "",
        "| " + " | ".join(HEAD) + " |",
        "|" + "---|" * len(HEAD),
        *all_rows,
        end,
    ])
    path.write_text(before + section + after)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, help="folder for code, data and runs")
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=list(SETS))
    parser.add_argument("--baseline", default=BASELINE, help=f"commit of the other variant (default {BASELINE}: "
                        "the clustering before the size bound)")
    parser.add_argument("--repeat", type=int, default=1, help="runs of each variant per set and seed")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0],
                        help="seeds of the clustering, the mappers and the merge (default 0)")
    parser.add_argument("--workers", type=int, default=2, help="local map workers (default 2)")
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data", help="folder of the real sets")
    parser.add_argument("--no-benchmarks-md", action="store_true", help="do not touch tools/BENCHMARKS.md")
    parser.add_argument("--keep", action="store_true", help="keep each run's database and local models")
    parser.add_argument("--child", nargs=7, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        work, db, gt, s_max, workers, seed, keep = args.child
        return child(Path(work), Path(db), Path(gt), int(s_max), int(workers), int(seed), keep == "1")
    if args.out is None:
        parser.error("--out is required")
    # The databases are made by this checkout's code, here and in the pools' fork server.
    sys.path.insert(0, str(ROOT))
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    out = args.out.resolve()
    variants = {"baseline": baseline_code(out, args.baseline), "bounded": current_code(out)}
    versions = {name: code_version(code) for name, code in variants.items()}
    date = datetime.date.today().isoformat()
    machine = f"{platform.machine()} {os.cpu_count()} cores"
    command = "python tools/bench_clustering.py " + " ".join(sys.argv[1:] if argv is None else argv)
    runs: list[dict] = []
    turn = 0
    for name in args.sets:
        s_max = SETS[name]
        db, gt = make_data(out, name, args.data)
        for seed in args.seeds:
            for rep in range(args.repeat):
                order = list(variants) if turn % 2 == 0 else list(variants)[::-1]
                turn += 1
                for variant in order:
                    print(f"{name} (S_max {s_max}), {variant}, seed {seed}, run {rep + 1} ...", flush=True)
                    r = run_variant(variants[variant], out / "runs" / name / f"{variant}-s{seed}-{rep}", db, gt,
                                    s_max, args.workers, seed, args.keep)
                    if r is None:
                        continue
                    r.update({"set": name, "s_max": s_max, "variant": variant, "seed": seed, "code": versions[variant]})
                    print(f"  {r['t_total']} s, map {r['t_map']} s, {r['registered']}/{r['images']}, "
                          f"AUC@1 {r['auc@1']}, AUC@5 {r['auc@5']}", flush=True)
                    runs.append(r)
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in runs:
        groups.setdefault((r["set"], r["variant"]), []).append(r)
    rows = [(name, summary_row(group, date, machine)) for (name, _), group in groups.items()]
    text = "\n".join(["| " + " | ".join(HEAD) + " |", "|" + "---|" * len(HEAD), *[line for _, line in rows]]) + "\n"
    per_run = "\n".join(["| " + " | ".join(RUN_HEAD) + " |", "|" + "---|" * len(RUN_HEAD), *map(run_row, runs)])
    (out / "clustering.md").write_text(text + "\nEvery run:\n\n" + per_run + "\n")
    (out / "runs.json").write_text(json.dumps(runs, indent=1))
    print(per_run + "\n\n" + text)
    if not args.no_benchmarks_md and rows:
        refresh_benchmarks(rows, command)
    return 0


if __name__ == "__main__":
    sys.exit(main())
