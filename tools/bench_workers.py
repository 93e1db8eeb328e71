"""The local-SfM stage with 1 and 2 workers, on the local and on the Dask executor, in one run.

    python tools/bench_workers.py --workspace W [--images 1000] [--workers 1 2] [--out DIR]

``W/database.db`` is made by ``graphsfm synth --scene aerial --images N --outlier-ratio 0.2``
when absent; it is clustered once (``--max-cluster-size``, default 100 as in ``graphsfm
cluster``), then ``map`` (only the local-SfM stage: payloads out, local models back and written)
runs once per executor and worker count on the same clusters.  The speedup is T(1 worker) over
T(n workers) of the same executor.  Prints a Markdown table; ``--out`` also writes it with a JSON
copy.  Run it on an otherwise idle machine: the point is how the cores are used.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_page import add_page_arguments, publish, run_context  # noqa: E402

from sfm.clustering.options import ClusterOptions
from sfm.stages.cluster import run_cluster
from sfm.execution.local import LocalExecutor
from sfm.mapper.options import MapperOptions
from sfm.stages.map import run_map
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def time_map(workspace: Path, executor) -> dict:
    """One ``map`` of every cluster; seconds, registered images summed over clusters, workers used."""
    shutil.rmtree(workspace / "clusters", ignore_errors=True)
    (workspace / "stages.json").unlink(missing_ok=True)  # else map would reuse the clusters just mapped
    t0 = time.perf_counter()
    with executor:
        result = run_map(workspace, MapperOptions(), executor=executor)
    seconds = time.perf_counter() - t0
    registered = sum(m["registered"] for m in result.models)
    workers = sorted({c["worker"] for c in result.clusters if c.get("worker")})
    failed = sum(1 for c in result.clusters if c.get("error"))
    return {"time_s": round(seconds, 1), "registered_in_clusters": registered, "workers_seen": len(workers),
            "failed_clusters": failed}


def make_executor(kind: str, workers: int):
    if kind == "dask":
        from sfm.execution.dask_cluster import DaskExecutor

        return DaskExecutor(workers=workers)
    return LocalExecutor(workers=workers)


def table(rows: list[dict]) -> str:
    head = ["executor", "workers", "time_s", "speedup", "registered_in_clusters", "workers_seen", "failed_clusters",
            "date", "machine", "code"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(str(r.get(k, "")) for k in head) + " |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workspace", required=True, help="workspace (made with synth when it has no database.db)")
    parser.add_argument("--images", type=int, default=1000, help="synthetic aerial images when making it (default 1000)")
    parser.add_argument("--max-cluster-size", type=int, default=100, help="S_max of the clustering (default 100)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts (default 1 2)")
    parser.add_argument("--executors", nargs="+", default=["local", "dask"], choices=["local", "dask"])
    parser.add_argument("--out", help="folder for bench_workers.md and .json")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    work = Path(args.workspace)
    if not (work / "database.db").exists():
        run_synth(work, SynthOptions(scene="aerial", num_images=args.images, outlier_ratio=0.2, seed=0))
    clusters = run_cluster(work, ClusterOptions(max_cluster_size=args.max_cluster_size)).num_clusters
    print(f"{work}: {clusters} clusters (S_max {args.max_cluster_size})", flush=True)
    rows, context = [], run_context()
    for kind in args.executors:
        base = None
        for n in args.workers:
            r = {"executor": kind, "workers": n, **time_map(work, make_executor(kind, n))}
            base = base or r["time_s"]
            r["speedup"] = round(base / r["time_s"], 2)
            r.update(context)
            rows.append(r)
            print(json.dumps(r), flush=True)
    text = table(rows)
    print(text)
    publish(args, "workers", "The local-SfM stage with 1 and 2 workers, local and Dask",
            f"{work.name}: {clusters} clusters (S_max {args.max_cluster_size})\n\n{text}")
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "bench_workers.md").write_text(f"{work}, {clusters} clusters\n\n{text}\n")
        (out / "bench_workers.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
