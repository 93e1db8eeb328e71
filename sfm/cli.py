"""``graphsfm`` command line: parses arguments and calls one stage function per command.

Commands only parse arguments and call the ``run_*`` functions of ``sfm.stages``.  Every option
flag is made from a field of an options dataclass (``sfm.core.options``): ``--max-cluster-size``
is ``ClusterOptions.max_cluster_size``, with the same help, default and allowed values, and the
dataclass checks the values before any stage runs.  Paths (``--workspace``, ``--images``, a
model folder, an output) are the commands' arguments.  Errors reach the user as one line on
stderr with the exit code of ``sfm.errors`` (details go to ``WORK/log.txt`` when a workspace is
known).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import traceback
import typing
from pathlib import Path

from sfm.clustering.options import ClusterOptions
from sfm.core.options import OptionError, base_type, option_fields
from sfm.errors import GraphsfmError, InputError
from sfm.evaluation.options import EvaluateOptions
from sfm.execution.options import ExecutionOptions, make_executor
from sfm.features.options import ExtractOptions
from sfm.io.options import ExportOptions
from sfm.mapper.options import MapperOptions
from sfm.matching.options import MatchOptions
from sfm.merge.options import MergeOptions
from sfm.synthetic.options import DemoOptions, SynthOptions
from sfm.viz.options import RecordingOptions

log = logging.getLogger("sfm")

# Each command's flags: the fields of these options dataclasses, in pipeline order.
COMMAND_OPTIONS: dict[str, tuple[type, ...]] = {
    "extract": (ExtractOptions, ExecutionOptions, RecordingOptions),
    "match": (MatchOptions, ExecutionOptions, RecordingOptions),
    "cluster": (ClusterOptions, RecordingOptions),
    "map": (MapperOptions, ExecutionOptions, RecordingOptions),
    "merge": (MergeOptions, MapperOptions, RecordingOptions),
    "reconstruct": (ExtractOptions, MatchOptions, ClusterOptions, MapperOptions, MergeOptions, ExecutionOptions,
                    RecordingOptions),
    "demo": (DemoOptions, ExecutionOptions, RecordingOptions),
    "evaluate": (EvaluateOptions,),
    "export": (ExportOptions,),
    "synth": (SynthOptions,),
}
# ``graphsfm merge`` offers the mapper's options that the refinement after merging reads; the
# others steer registration, which merging does not do.
ONLY_FIELDS: dict[tuple[str, type], tuple[str, ...]] = {
    ("merge", MapperOptions): ("min_num_matches", "max_reproj_error", "min_tri_angle", "intrinsics_refinement",
                               "refine_given_intrinsics", "loss", "loss_scale", "scale_weights",
                               "ba_max_observations", "min_model_size", "seed"),
}


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


# ------------------------------------------------------------------------------- options <-> flags
def flag_of(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_options(parser: argparse.ArgumentParser, cls: type, only: tuple[str, ...] | None = None) -> None:
    """One ``--flag`` per field of the options dataclass ``cls`` (``only``: these fields), with the
    field's type, choices, help and default.  A flag another dataclass already added (``--seed``)
    is shared: its value goes to every dataclass that has the field."""
    hints = typing.get_type_hints(cls)
    group = parser.add_argument_group(cls.__name__)
    for f in option_fields(cls):
        flag = flag_of(f.name)
        if (only is not None and f.name not in only) or flag in parser._option_string_actions:
            continue
        kind, help_text = base_type(hints[f.name]), f.metadata["help"].replace("%", "%%")
        if kind is bool:
            group.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=f.default,
                               help=help_text)
            continue
        choices = f.metadata.get("choices")
        if f.default is not None:  # an optional field's help says what its absence means
            help_text += f" (default: {f.default})"
        group.add_argument(flag, dest=f.name, type=str if kind is Path else kind, default=f.default, choices=choices,
                           metavar=None if choices else f.name.upper(), help=help_text)


def options_of(cls: type, args: argparse.Namespace):
    """The dataclass ``cls`` from the parsed flags that belong to it; a value it refuses is a
    bad argument (exit code 2) naming the flag."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
    try:
        return cls(**values)
    except OptionError as exc:
        raise InputError(f"{flag_of(exc.field)}: {exc.message}") from exc
    except ValueError as exc:
        raise InputError(str(exc)) from exc


def _reconstruct_options(args: argparse.Namespace):
    from sfm.stages.reconstruct import ReconstructOptions

    return ReconstructOptions(
        extract=options_of(ExtractOptions, args), match=options_of(MatchOptions, args),
        cluster=options_of(ClusterOptions, args), mapper=options_of(MapperOptions, args),
        merge=options_of(MergeOptions, args), execution=options_of(ExecutionOptions, args),
        recording=options_of(RecordingOptions, args))


def _recorder(args: argparse.Namespace, stage: str):
    from sfm.viz.recorder import Recorder

    rec = options_of(RecordingOptions, args)
    if not rec.recording:
        return Recorder.disabled()
    workspace = Path(args.workspace)
    return Recorder(workspace / f"recording-{stage}.rrd", workspace=workspace, spawn=rec.spawn, options=rec)


def _print(obj) -> None:
    print(json.dumps(_rounded(obj, 6), indent=2, default=str))


def _image_dir(images: str) -> Path:
    path = Path(images)
    if not path.is_dir():
        raise InputError(f"image folder not found: {images}")
    return path


# ------------------------------------------------------------------------------- commands
def cmd_extract(args: argparse.Namespace) -> int:
    from sfm.stages.extract import run_extract

    images = _image_dir(args.images)
    options = options_of(ExtractOptions, args)
    with _recorder(args, "extract") as recorder, make_executor(options_of(ExecutionOptions, args)) as executor:
        result = run_extract(images, Path(args.workspace), options, executor, recorder)
    _print(dataclasses.asdict(result))
    return 0


def cmd_match(args: argparse.Namespace) -> int:
    from sfm.stages.match import run_match

    options = options_of(MatchOptions, args)
    with _recorder(args, "match") as recorder, make_executor(options_of(ExecutionOptions, args)) as executor:
        result = run_match(Path(args.workspace), options, executor, recorder)
    _print(dataclasses.asdict(result))
    return 0


def cmd_cluster(args: argparse.Namespace) -> int:
    from sfm.stages.cluster import run_cluster

    options = options_of(ClusterOptions, args)
    with _recorder(args, "cluster") as recorder:
        result = run_cluster(Path(args.workspace), options, recorder)
    _print(dataclasses.asdict(result))
    return 0


def cmd_map(args: argparse.Namespace) -> int:
    from sfm.stages.map import run_map

    options = options_of(MapperOptions, args)
    with _recorder(args, "map") as recorder, make_executor(options_of(ExecutionOptions, args)) as executor:
        result = run_map(Path(args.workspace), options, recorder, executor)
    _print({"clusters": result.num_clusters, "models": result.models})
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    from sfm.stages.merge import run_merge

    mapper, merge = options_of(MapperOptions, args), options_of(MergeOptions, args)
    with _recorder(args, "merge") as recorder:
        result = run_merge(Path(args.workspace), mapper, merge, recorder)
    _print(dataclasses.asdict(result))
    return 0


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from sfm.stages.reconstruct import reconstruct

    images = _image_dir(args.images) if args.images is not None else None
    report = reconstruct(images, Path(args.workspace), _reconstruct_options(args))
    _print({k: report.get(k) for k in ("images", "registered", "points", "mean_track_length",
            "mean_reprojection_error", "num_clusters", "num_models", "times", "warnings") if k in report})
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from sfm.stages.demo import run_demo

    summary = run_demo(Path(args.workspace), options_of(DemoOptions, args), _reconstruct_options(args))
    print(json.dumps(_rounded(summary, 4), indent=2))
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from sfm.evaluation.ground_truth import gt_from_reconstruction, read_gt_table
    from sfm.evaluation.metrics import evaluate
    from sfm.io.colmap_model import read_model

    options = options_of(EvaluateOptions, args)
    model, gt_path = Path(args.model), Path(args.gt)
    if not model.exists():
        raise InputError(f"model not found: {model}")
    if not gt_path.exists():
        raise InputError(f"ground truth not found: {gt_path}")
    recon = read_model(model)
    gt = gt_from_reconstruction(read_model(gt_path)) if gt_path.is_dir() else read_gt_table(gt_path)
    result = evaluate(recon, gt, seed=options.seed)
    print(json.dumps(_rounded(result.to_dict(per_image=options.per_image)), indent=2))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from sfm.io.colmap_model import read_model, write_model, write_ply

    options = options_of(ExportOptions, args)
    model = Path(args.model)
    if not model.exists():
        raise InputError(f"model not found: {model}")
    recon = read_model(model)
    out = Path(args.out)
    if options.to == "ply":
        out.parent.mkdir(parents=True, exist_ok=True)
        write_ply(recon, out)
    else:
        out.mkdir(parents=True, exist_ok=True)
        write_model(recon, out, fmt=options.to)
    log.info("wrote %s (%d images, %d points)", out, len(recon.images), len(recon.points3D))
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from sfm.stages.synth import run_synth

    _print(run_synth(Path(args.workspace), options_of(SynthOptions, args)))
    return 0


# ------------------------------------------------------------------------------- parser
def _workspace(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--workspace", required=True, help=what)


def _command(sub, name: str, help_text: str, func) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help=help_text)
    p.set_defaults(func=func)
    return p


def _add_command_options(p: argparse.ArgumentParser, name: str) -> None:
    for cls in COMMAND_OPTIONS[name]:
        add_options(p, cls, only=ONLY_FIELDS.get((name, cls)))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="graphsfm", description="Graph-based parallel Structure-from-Motion (GraphSfM).")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug messages on stderr")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = _command(sub, "extract", "SIFT features of every image into WORK/database.db", cmd_extract)
    p.add_argument("--images", required=True, help="image folder (searched recursively)")
    _workspace(p, "output folder")
    p = _command(sub, "match", "select pairs, match descriptors, verify two-view geometry", cmd_match)
    _workspace(p, "workspace with database.db")
    p = _command(sub, "cluster", "cut the image graph into overlapping clusters (WORK/clusters.json)", cmd_cluster)
    _workspace(p, "workspace with database.db")
    p = _command(sub, "map", "incremental SfM of each cluster (or of all images) -> sparse/ or clusters/", cmd_map)
    _workspace(p, "workspace with database.db (and clusters.json)")
    p = _command(sub, "merge", "merge the local models along the MinST into sparse/N, then refine", cmd_merge)
    _workspace(p, "workspace with clusters/C<k>/<m> models")
    p = _command(sub, "reconstruct", "every stage: extract, match, cluster, map, merge", cmd_reconstruct)
    p.add_argument("--images", help="image folder (omit to start from an existing database.db)")
    _workspace(p, "output folder")
    p = _command(sub, "demo", "render a small scene, reconstruct it with several clusters, print its accuracy",
                 cmd_demo)
    p.add_argument("workspace", help="output folder (new)")
    p = _command(sub, "evaluate", "compare a model with ground truth; prints JSON", cmd_evaluate)
    p.add_argument("model", help="COLMAP model folder (.bin or .txt)")
    p.add_argument("--gt", required=True, help="GT table (cameras_gt_opencv.txt) or a COLMAP model folder")
    p = _command(sub, "export", "convert a model to COLMAP text, binary, or a PLY point cloud", cmd_export)
    p.add_argument("model", help="COLMAP model folder (.bin or .txt)")
    p.add_argument("out", help="output folder (txt, bin) or .ply file")
    p = _command(sub, "synth", "make a scene with exact ground truth: a database of simulated matches, or images",
                 cmd_synth)
    _workspace(p, "output folder (new)")
    for name, command_parser in sub.choices.items():
        _add_command_options(command_parser, name)
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
