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

from sfm.clustering import ClusterOptions
from sfm.errors import GraphsfmError, InputError
from sfm.mapper_input import MapperOptions
from sfm.options import add_options, options_from_args
from sfm.rendered import RenderOptions
from sfm.synthetic import SynthOptions

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
        from sfm.rendered import write_rendered_scene

        summary = write_rendered_scene(workspace, opts)
    else:
        from sfm.synthetic import run_synth

        try:
            opts = options_from_args(SynthOptions, args)
        except ValueError as exc:
            raise InputError(str(exc)) from exc
        try:
            summary = run_synth(workspace, opts)
        except FileExistsError as exc:
            raise InputError(str(exc)) from exc
    print(json.dumps(summary, indent=2))
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from sfm.colmap_io import read_model
    from sfm.evaluation import evaluate, gt_from_reconstruction, read_gt_table

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
    from sfm.colmap_io import read_model, write_model, write_ply

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
    from sfm.recording import Recorder

    workspace = Path(args.workspace)
    if args.no_recording:
        return Recorder.disabled()
    return Recorder(workspace / f"recording-{stage}.rrd", workspace=workspace, spawn=args.spawn)


def cmd_cluster(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from sfm.clustering import run_cluster

    options = options_from_args(ClusterOptions, args)
    with _recorder(args, "cluster") as recorder:
        result = run_cluster(Path(args.workspace), options, recorder)
    print(json.dumps(asdict(result), indent=2))
    return 0


def cmd_map(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from sfm.mapping import run_map

    options = options_from_args(MapperOptions, args)
    with _recorder(args, "map") as recorder:
        result = run_map(Path(args.workspace), options, recorder)
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
    add_options(p, MapperOptions, flags=MAP_FLAGS)
    _add_recording_flags(p)
    p.set_defaults(func=cmd_map)

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
