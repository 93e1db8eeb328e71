"""``graphsfm`` command line: parses arguments and calls one stage function per command.

Commands only parse arguments and call ``run_*`` functions; errors reach the user as one line
on stderr with the exit code of ``sfm.errors`` (details go to ``WORK/log.txt`` when a workspace
is known).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import traceback
from pathlib import Path

from sfm.stages.cluster import ClusterOptions
from sfm.errors import GraphsfmError, InputError
from sfm.mapper.payload import MapperOptions
from sfm.core.options import add_options, options_from_args
from sfm.synthetic.rendered import RenderOptions
from sfm.synthetic.scenes import SynthOptions

log = logging.getLogger("sfm")


def _rounded(obj, digits: int = 10):
    """Floats rounded to ``digits`` significant digits for printing (1 - 1e-15 prints as 1.0)."""
    if isinstance(obj, float):
        return float(f"{obj:.{digits}g}")
    if isinstance(obj, dict):
        return {k: _rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_rounded(v, digits) for v in obj]
    return obj


def _setup_logging(workspace: Path | None, verbose: bool) -> None:
    root = logging.getLogger()
    root.setLevel(logging.DEBUG)
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(logging.DEBUG if verbose else logging.INFO)
    console.setFormatter(logging.Formatter("%(levelname).1s %(name)s: %(message)s"))
    root.addHandler(console)
    if workspace is not None:
        try:
            workspace.mkdir(parents=True, exist_ok=True)
            handler = logging.FileHandler(workspace / "log.txt")
        except OSError as exc:
            raise InputError(f"cannot write to workspace {workspace}: {exc.strerror}") from exc
        handler.setLevel(logging.DEBUG)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.addHandler(handler)


# ------------------------------------------------------------------------------- commands
def cmd_synth(args: argparse.Namespace) -> int:
    workspace = Path(args.workspace)
    if args.scene == "rendered":
        opts = RenderOptions(num_images=args.num_images, seed=args.seed)
        from sfm.synthetic.rendered import write_rendered_scene

        summary = write_rendered_scene(workspace, opts)
    else:
        from sfm.synthetic.scenes import run_synth

        opts = options_from_args(SynthOptions, args)
        try:
            summary = run_synth(workspace, opts)
        except FileExistsError as exc:
            raise InputError(str(exc)) from exc
    print(json.dumps(summary, indent=2))
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from sfm.io.colmap_model import read_model
    from sfm.evaluation.metrics import evaluate, gt_from_reconstruction, read_gt_table

    model = Path(args.model)
    gt_path = Path(args.gt)
    if not model.exists():
        raise InputError(f"model not found: {model}")
    if not gt_path.exists():
        raise InputError(f"ground truth not found: {gt_path}")
    recon = read_model(model)
    gt = gt_from_reconstruction(read_model(gt_path)) if gt_path.is_dir() else read_gt_table(gt_path)
    result = evaluate(recon, gt, seed=args.seed)
    print(json.dumps(_rounded(result.to_dict(per_image=args.per_image)), indent=2))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from sfm.io.colmap_model import read_model, write_model, write_ply

    model = Path(args.model)
    if not model.exists():
        raise InputError(f"model not found: {model}")
    recon = read_model(model)
    out = Path(args.out)
    if args.to == "ply":
        out.parent.mkdir(parents=True, exist_ok=True)
        write_ply(recon, out)
    else:
        out.mkdir(parents=True, exist_ok=True)
        write_model(recon, out, fmt=args.to)
    log.info("wrote %s (%d images, %d points)", out, len(recon.images), len(recon.points3D))
    return 0


def _recorder(args: argparse.Namespace, stage: str):
    from sfm.viz.recorder import Recorder

    workspace = Path(args.workspace)
    if args.no_recording:
        return Recorder.disabled()
    return Recorder(workspace / f"recording-{stage}.rrd", workspace=workspace, spawn=args.spawn)


def cmd_cluster(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from sfm.stages.cluster import run_cluster

    options = options_from_args(ClusterOptions, args)
    with _recorder(args, "cluster") as recorder:
        result = run_cluster(Path(args.workspace), options, recorder)
    print(json.dumps(asdict(result), indent=2))
    return 0


def _executor(args: argparse.Namespace):
    if getattr(args, "executor", "local") == "dask":
        from sfm.execution.dask_cluster import DaskExecutor

        return DaskExecutor(scheduler=args.scheduler, workers=getattr(args, "workers", 0) or getattr(args, "num_workers", 0))
    if getattr(args, "scheduler", None):
        raise InputError("--scheduler needs --executor dask")
    from sfm.execution.local import LocalExecutor

    return LocalExecutor(workers=getattr(args, "workers", 0))


def _add_executor_flags(p: argparse.ArgumentParser, workers: bool = True) -> None:
    if workers:
        p.add_argument("--workers", type=int, default=0, help="parallel cluster workers (default 0: all cores)")
    p.add_argument("--executor", choices=["local", "dask"], default="local",
                   help="where the work runs: local processes, or a Dask cluster (default: local)")
    p.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT (default: start a LocalCluster)")


def cmd_map(args: argparse.Namespace) -> int:
    from sfm.stages.map import run_map

    options = options_from_args(MapperOptions, args)
    with _recorder(args, "map") as recorder, _executor(args) as executor:
        result = run_map(Path(args.workspace), options, recorder, executor)
    print(json.dumps({"clusters": result.num_clusters, "models": result.models}, indent=2))
    return 0


def cmd_extract(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from sfm.stages.extract import ExtractOptions, run_extract

    options = options_from_args(ExtractOptions, args)
    _check_image_dir(args.images)
    with _executor(args) as executor:
        result = run_extract(Path(args.images), Path(args.workspace), options, _remote(executor))
    with _recorder(args, "extract") as recorder:
        from sfm.viz.frontend import log_images

        log_images(recorder, Path(args.images), Path(args.workspace))
    print(json.dumps(asdict(result), indent=2))
    return 0


def cmd_match(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from sfm.stages.match import MatchOptions, run_match

    options = options_from_args(MatchOptions, args)
    with _executor(args) as executor:
        result = run_match(Path(args.workspace), options, _remote(executor))
    with _recorder(args, "match") as recorder:
        from sfm.viz.frontend import log_verified_graph

        log_verified_graph(recorder, Path(args.workspace))
    print(json.dumps(asdict(result), indent=2))
    return 0


def _remote(executor):
    """The executor when it is distributed (extract and match then run on it), else None."""
    return executor if hasattr(executor, "imap") else None


def _check_image_dir(images: str) -> None:
    if not Path(images).is_dir():
        raise InputError(f"image folder not found: {images}")


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from sfm.stages.cluster import ClusterOptions
    from sfm.stages.extract import ExtractOptions
    from sfm.stages.match import MatchOptions
    from sfm.merge.cluster_graph import MergeOptions
    from sfm.stages.merge import ReconstructOptions, run_reconstruct

    if args.images is not None:
        _check_image_dir(args.images)
    options = ReconstructOptions(
        extract=options_from_args(ExtractOptions, args), match=options_from_args(MatchOptions, args),
        cluster=options_from_args(ClusterOptions, args), mapper=options_from_args(MapperOptions, args),
        merge=options_from_args(MergeOptions, args))
    workspace = Path(args.workspace)
    from sfm.execution.process_pool import start_pool_server
    from sfm.viz.recorder import Recorder

    if getattr(args, "executor", "local") == "local":
        start_pool_server()  # the worker processes' imports overlap the Rerun SDK's
    recorder = Recorder.disabled() if args.no_recording else Recorder(workspace / "recording.rrd", workspace, spawn=args.spawn)
    with recorder, _executor(args) as executor:
        report = run_reconstruct(workspace, Path(args.images) if args.images else None, options, executor, recorder)
    print(json.dumps({k: report.get(k) for k in ("images", "registered", "points", "mean_track_length",
                      "mean_reprojection_error", "num_clusters", "num_models", "times", "warnings") if k in report}, indent=2))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from sfm.api import make_options
    from sfm.io.colmap_model import read_model
    from sfm.evaluation.metrics import evaluate, read_gt_table
    from sfm.execution.local import LocalExecutor
    from sfm.stages.merge import run_reconstruct
    from sfm.viz.recorder import Recorder
    from sfm.synthetic.rendered import RenderOptions, write_rendered_scene

    workspace = Path(args.workspace)
    if (workspace / "database.db").exists():
        raise InputError(f"{workspace} already holds a run; give a new folder")
    scene = write_rendered_scene(workspace / "scene", RenderOptions(num_images=args.images, seed=args.seed))
    options = make_options(max_cluster_size=args.max_cluster_size, seed=args.seed)
    with Recorder(workspace / "recording.rrd", workspace) as recorder:
        report = run_reconstruct(workspace, Path(scene["image_dir"]), options, LocalExecutor(args.workers), recorder)
    result = evaluate(read_model(workspace / "sparse" / "0"), read_gt_table(Path(scene["gt_table"])))
    summary = {"images": report["images"], "clusters": report.get("num_clusters"), "models": report.get("num_models"),
               "registered": result.num_registered, "median_rotation_error_deg": result.median_rotation_error_deg,
               "auc@1": result.auc[1], "auc@5": result.auc[5], "auc@10": result.auc[10], "times": report.get("times"),
               "model": str(workspace / "sparse" / "0"), "recording": str(workspace / "recording.rrd")}
    print(json.dumps(_rounded(summary, 4), indent=2))
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from sfm.merge.cluster_graph import MergeOptions
    from sfm.stages.merge import run_merge

    with _recorder(args, "merge") as recorder:
        result = run_merge(Path(args.workspace), options_from_args(MapperOptions, args), options_from_args(MergeOptions, args), recorder)
    print(json.dumps(asdict(result), indent=2))
    return 0


MAP_FLAGS = {"refine_given_intrinsics": "refine-intrinsics", "refine_intrinsics": "intrinsics-refinement"}


def _add_recording_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--spawn", action="store_true", help="also open a Rerun viewer (when installed)")
    p.add_argument("--no-recording", action="store_true", help="do not write the Rerun recording")


# ------------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="graphsfm",
        description="Graph-based parallel Structure-from-Motion (GraphSfM).",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug messages on stderr")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("synth", help="make a synthetic scene with exact ground truth")
    p.add_argument("--workspace", required=True, help="output folder")
    p.add_argument("--scene", choices=["orbit", "street", "aerial", "rendered"], default="orbit",
                   help="correspondence-level scene written into WORK/database.db, or 'rendered': "
                        "PNG images in WORK/images (default: orbit)")
    add_options(p, SynthOptions, flags={"num_images": "images"}, skip=("scene",))
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("cluster", help="cut the image graph into overlapping clusters (WORK/clusters.json)")
    p.add_argument("--workspace", required=True, help="workspace with database.db")
    add_options(p, ClusterOptions, flags={"completeness_ratio": "completeness", "max_overlap": "overlap"})
    _add_recording_flags(p)
    p.set_defaults(func=cmd_cluster)

    p = sub.add_parser("map", help="incremental SfM of each cluster (or of all images) -> sparse/ or clusters/")
    p.add_argument("--workspace", required=True, help="workspace with database.db (and clusters.json)")
    _add_executor_flags(p)
    add_options(p, MapperOptions, flags=MAP_FLAGS)
    _add_recording_flags(p)
    p.set_defaults(func=cmd_map)

    from sfm.stages.extract import ExtractOptions
    from sfm.stages.match import MatchOptions
    from sfm.merge.cluster_graph import MergeOptions

    p = sub.add_parser("extract", help="SIFT features of every image into WORK/database.db")
    p.add_argument("--images", required=True, help="image folder (searched recursively)")
    p.add_argument("--workspace", required=True, help="output folder")
    add_options(p, ExtractOptions)
    _add_executor_flags(p, workers=False)
    _add_recording_flags(p)
    p.set_defaults(func=cmd_extract)

    p = sub.add_parser("match", help="select pairs, match descriptors, verify two-view geometry")
    p.add_argument("--workspace", required=True, help="workspace with database.db")
    add_options(p, MatchOptions)
    _add_executor_flags(p, workers=False)
    _add_recording_flags(p)
    p.set_defaults(func=cmd_match)

    p = sub.add_parser("reconstruct", help="every stage: extract, match, cluster, map, merge")
    p.add_argument("--images", help="image folder (omit to start from an existing database.db)")
    p.add_argument("--workspace", required=True, help="output folder")
    _add_executor_flags(p)
    add_options(p, ExtractOptions)
    add_options(p, MatchOptions)
    add_options(p, ClusterOptions, flags={"completeness_ratio": "completeness", "max_overlap": "overlap"})
    add_options(p, MapperOptions, flags=MAP_FLAGS)
    add_options(p, MergeOptions)
    _add_recording_flags(p)
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser("merge", help="merge the local models along the MinST into sparse/N, then refine")
    p.add_argument("--workspace", required=True, help="workspace with clusters/C<k>/<m> models")
    add_options(p, MergeOptions)
    add_options(p, MapperOptions, flags=MAP_FLAGS)
    _add_recording_flags(p)
    p.set_defaults(func=cmd_merge)

    p = sub.add_parser("demo", help="render a small scene, reconstruct it with >= 3 clusters, print its accuracy")
    p.add_argument("workspace", help="output folder (new)")
    p.add_argument("--images", type=int, default=30, help="rendered views (default 30)")
    p.add_argument("--max-cluster-size", type=int, default=12, help="the most images in a cluster (default 12: several clusters of the 30 views)")
    p.add_argument("--workers", type=int, default=0, help="parallel cluster workers (default 0: all cores)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scene and of every stage (default 0)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("evaluate", help="compare a model with ground truth; prints JSON")
    p.add_argument("model", help="COLMAP model folder (.bin or .txt)")
    p.add_argument("--gt", required=True, help="GT table (cameras_gt_opencv.txt) or a COLMAP model folder")
    p.add_argument("--seed", type=int, default=0, help="seed of the robust alignment (default: 0)")
    p.add_argument("--per-image", action="store_true", help="also print each image's rotation and centre error")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("export", help="convert a model to COLMAP text, binary, or a PLY point cloud")
    p.add_argument("model", help="COLMAP model folder (.bin or .txt)")
    p.add_argument("--to", choices=["txt", "bin", "ply"], required=True, help="output format")
    p.add_argument("out", help="output folder (txt, bin) or .ply file")
    p.set_defaults(func=cmd_export)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # argparse exits with code 2 on bad arguments
    workspace = Path(args.workspace) if getattr(args, "workspace", None) else None
    try:
        _setup_logging(workspace, args.verbose)
        return args.func(args)
    except GraphsfmError as exc:
        print(f"graphsfm {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"graphsfm {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the one place that turns a crash into one line
        logging.getLogger("sfm").debug("unexpected error\n%s", traceback.format_exc())
        where = f"; details in {workspace / 'log.txt'}" if workspace else ""
        print(f"graphsfm {args.command}: internal error: {type(exc).__name__}: {exc}{where}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
