"""``graphsfm`` command line: parses arguments and calls one stage function per command.

Commands only parse arguments and call the ``run_*`` functions of ``sfm.stages``.  Every option
flag is made from a field of an options dataclass (``sfm.core.options``): ``--max-cluster-size``
is ``ClusterOptions.max_cluster_size``, with the same help, default and allowed values, and the
dataclass checks the values before any stage runs.  Paths (``--workspace``, ``--images``, a
model folder, an output) are the commands' arguments.  To add a command: a ``cmd_*`` function, a
``COMMANDS`` row and its ``COMMAND_OPTIONS``.

Errors reach the user as one line on stderr with the exit code of ``sfm.errors`` (details go to
``WORK/log.txt`` when a workspace is known): a bad argument says what is wrong and what is
allowed (a close match for a mistyped flag or command), then one short usage line, exit code 2.
``-v`` (debug) and ``-q`` (warnings only, no progress bars) go anywhere on the line.

The program ``graphsfm`` (``sfm.__main__``) runs :func:`main` in a child process that it
supervises (``sfm.execution.processes``), so Ctrl-C or SIGTERM ends the run and every process it
started within a couple of seconds, with one line saying where it stopped (:func:`stopped`).
``main(argv)`` itself runs the command in the calling process (tests, scripts).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import difflib
import json
import logging
import os
import re
import shlex
import signal
import sqlite3
import sys
import time
import traceback
import typing
from pathlib import Path

from sfm.clustering.options import ClusterOptions
from sfm.console import setup_logging, teardown_logging
from sfm.core import progress
from sfm.core.options import OptionError, allowed, base_type, option_fields
from sfm.errors import GraphsfmError, InputError
from sfm.evaluation.options import AlignOptions, EvaluateOptions
from sfm.execution.logs import DETAILS
from sfm.execution.options import ExecutionOptions, make_executor
from sfm.features.options import ExtractOptions
from sfm.io.database import damaged_database
from sfm.io.options import ExportOptions
from sfm.io.report import finish_run, start_run
from sfm.io.workspace import WorkspaceLock
from sfm.mapper.options import MapperOptions
from sfm.matching.options import MatchOptions
from sfm.merge.options import ExtendOptions, MergeOptions
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
    "extend": (ExtendOptions, ExtractOptions, MatchOptions, ClusterOptions, MapperOptions, MergeOptions,
               ExecutionOptions, RecordingOptions),
    "demo": (DemoOptions, ExecutionOptions, RecordingOptions),
    "evaluate": (EvaluateOptions,),
    "export": (ExportOptions,),
    "info": (),
    "align": (AlignOptions,),
    "synth": (SynthOptions,),
}
# ``graphsfm merge`` offers the mapper's options that the refinement after merging reads; the
# others steer registration, which merging does not do.
ONLY_FIELDS: dict[tuple[str, type], tuple[str, ...]] = {
    ("merge", MapperOptions): ("min_num_matches", "max_reproj_error", "min_tri_angle", "intrinsics_refinement",
                               "refine_given_intrinsics", "loss", "loss_scale", "scale_weights",
                               "ba_max_observations", "min_model_size", "georegister", "gps_max_error", "seed"),
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
        limits = "" if choices else allowed(f)
        if limits and hasattr(parser, "allowed"):
            parser.allowed[flag] = limits
        if f.default is not None:  # an optional field's help says what its absence means
            help_text += f" (default: {f.default}" + (f"; allowed: {limits}" if limits else "") + ")"
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


def _print(obj, digits: int = 6) -> None:
    print(json.dumps(_rounded(obj, digits), indent=2, default=str))


def _image_dir(images: str) -> Path:
    path = Path(images)
    if path.exists() and not path.is_dir():
        raise InputError(f"--images: {images} is a file, not a folder of images")
    if not path.is_dir():
        raise InputError(f"--images: image folder not found: {images}")
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
    report = reconstruct(images, Path(args.workspace), _reconstruct_options(args), command=args.command_line)
    _print({k: report[k] for k in ("images", "registered", "points", "mean_track_length", "mean_reprojection_error_px",
                                   "num_clusters", "num_models", "georegistration", "times_s", "warnings")}
           | {"model": report["models"][0]["path"] if report["models"] else None,
              "report": str(Path(args.workspace).resolve() / "report.json")})
    return 0


def cmd_extend(args: argparse.Namespace) -> int:
    from sfm.stages.extend import ExtendRunOptions, extend

    images = _image_dir(args.images) if args.images is not None else None
    base = _reconstruct_options(args)
    options = ExtendRunOptions(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)},
                               extend=options_of(ExtendOptions, args))
    summary = extend(Path(args.workspace), images, options, command=args.command_line)
    _print(summary | {"report": str(Path(args.workspace).resolve() / "report.json")})
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from sfm.stages.demo import run_demo

    summary = run_demo(Path(args.workspace), options_of(DemoOptions, args), _reconstruct_options(args),
                       command=args.command_line)
    print(json.dumps(_rounded(summary, 4), indent=2))
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from sfm.evaluation.ground_truth import gt_from_reconstruction, read_gt_table
    from sfm.evaluation.metrics import evaluate
    from sfm.io.colmap_model import read_model

    options = options_of(EvaluateOptions, args)
    model, gt_path = Path(args.model), Path(args.gt)
    if not model.is_dir():
        raise InputError(f"model not found: {model}" if not model.exists() else f"{model} is a file, not a model folder")
    if not gt_path.exists():
        raise InputError(f"ground truth not found: {gt_path}")
    recon = read_model(model)
    gt = gt_from_reconstruction(read_model(gt_path)) if gt_path.is_dir() else read_gt_table(gt_path)
    result = evaluate(recon, gt, seed=options.seed)
    print(json.dumps(_rounded(result.to_dict(per_image=options.per_image)), indent=2))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from sfm.stages.model_tools import export

    images = _image_dir(args.images) if args.images is not None else None
    _print(export(args.model, args.out, images=images, options=options_of(ExportOptions, args)))
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from sfm.stages.model_tools import info

    _print(info(args.model), digits=10)
    return 0


def cmd_align(args: argparse.Namespace) -> int:
    from sfm.stages.model_tools import align

    if (args.gps is None) == (args.ref is None):
        raise InputError("align needs one of --gps SOURCE or --ref TABLE")
    _print(align(args.model, args.out, gps=args.gps, ref=args.ref, options=options_of(AlignOptions, args)), digits=10)
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from sfm.stages.synth import run_synth

    _print(run_synth(Path(args.workspace), options_of(SynthOptions, args)))
    return 0


# ------------------------------------------------------------------------------- parser
# name, help, function, positional or required arguments (flag, help), workspace role; in the
# order of a run (the stages, the whole run, then what comes after or stands beside it).
WORKSPACE_COMMANDS = {"extract", "match", "cluster", "map", "merge", "reconstruct", "extend", "demo", "synth"}
RESUMABLE = {"extract", "match", "cluster", "map", "merge", "reconstruct", "extend"}
REPORTS_ITSELF = {"reconstruct", "extend", "demo", "synth"}  # start and finish report.json in their stage code
COMMANDS: list[tuple[str, str, object, list[tuple[str, dict]]]] = [
    ("extract", "SIFT features of every image into WORK/database.db", cmd_extract,
     [("--images", {"required": True, "help": "image folder (searched recursively)"}),
      ("--workspace", {"required": True, "help": "output folder"})]),
    ("match", "select pairs, match descriptors, verify two-view geometry", cmd_match,
     [("--workspace", {"required": True, "help": "workspace with database.db"})]),
    ("cluster", "cut the image graph into overlapping clusters (WORK/clusters.json)", cmd_cluster,
     [("--workspace", {"required": True, "help": "workspace with database.db"})]),
    ("map", "incremental SfM of each cluster (or of all images) -> sparse/ or clusters/", cmd_map,
     [("--workspace", {"required": True, "help": "workspace with database.db (and clusters.json)"})]),
    ("merge", "merge the local models along the MinST into sparse/N, then refine", cmd_merge,
     [("--workspace", {"required": True, "help": "workspace with clusters/C<k>/<m> models"})]),
    ("reconstruct", "every stage: extract, match, cluster, map, merge", cmd_reconstruct,
     [("--images", {"help": "image folder (omit to start from an existing database.db)"}),
      ("--workspace", {"required": True, "help": "output folder"})]),
    ("extend", "add new photos to the finished model WORK/sparse/0 as new clusters merged into it", cmd_extend,
     [("--images", {"help": "folder of the new photos (omit: the database's images no model registers)"}),
      ("--workspace", {"required": True, "help": "workspace with a finished model (sparse/0) and its database.db"})]),
    ("demo", "render a small scene, reconstruct it clustered and merged, print its accuracy", cmd_demo,
     [("workspace", {"help": "output folder (new)"})]),
    ("evaluate", "compare a model with ground truth; prints JSON", cmd_evaluate,
     [("model", {"help": "COLMAP model folder (.bin or .txt)"}),
      ("--gt", {"required": True, "help": "GT table (cameras_gt_opencv.txt) or a COLMAP model folder"})]),
    ("export", "convert a model: COLMAP text or binary, PLY, undistorted images + PINHOLE model, nerfstudio "
     "transforms.json", cmd_export,
     [("model", {"help": "COLMAP model folder (.bin or .txt)"}),
      ("out", {"help": "output: a folder (txt, bin, undistorted, nerfstudio), a .ply or a .json file"}),
      ("--images", {"help": "the model's image folder (undistorted: required; nerfstudio: where frames point)"})]),
    ("info", "summarise a model: cameras, images, points, track length, reprojection error, georegistration",
     cmd_info, [("model", {"help": "COLMAP model folder (.bin or .txt)"})]),
    ("align", "move a model onto GPS positions (ENU, metres) or a table of reference centres", cmd_align,
     [("model", {"help": "COLMAP model folder (.bin or .txt)"}),
      ("out", {"help": "output model folder"}),
      ("--gps", {"metavar": "SOURCE", "help": "a database.db with GPS pose priors, or the image folder (EXIF); "
                 "one of --gps and --ref"}),
      ("--ref", {"metavar": "TABLE", "help": "text file of 'IMAGE_NAME X Y Z' reference camera centres"})]),
    ("synth", "make a scene with exact ground truth: a database of simulated matches, or images", cmd_synth,
     [("--workspace", {"required": True, "help": "output folder (new)"})]),
]


class ArgumentsError(Exception):
    """A bad command line: ``parser`` is the (sub)parser that found it."""

    def __init__(self, parser: argparse.ArgumentParser, message: str) -> None:
        super().__init__(message)
        self.parser = parser


def _suggest(word: str, known) -> str:
    close = difflib.get_close_matches(word, list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: what is wrong and what is allowed (``error`` raises
    :class:`ArgumentsError`; :func:`main` prints it with one short usage line)."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)  # --work is not --workspace nor --workers
        super().__init__(*args, **kwargs)
        self.allowed: dict[str, str] = {}  # flag -> what its option allows, in words

    def error(self, message: str):  # noqa: D102 - argparse's hook
        match = re.match(r"argument ([^:]+): (.*)", message)
        if match:
            name, rest = match.groups()
            flag = name.split("/")[-1]
            if re.match(r"invalid (int|float) value", rest):
                kind = "an integer" if "int" in rest.split()[1] else "a number"
                value = rest.split(":", 1)[1].strip()
                rest = f"{value} is not {kind}" + (f"; allowed: {self.allowed[flag]}" if self.allowed.get(flag) else "")
            elif rest == "expected one argument":
                rest = "needs a value" + (f" ({self.allowed[flag]})" if self.allowed.get(flag) else "")
            message = rest if name == "COMMAND" else f"{flag}: {rest}"
        elif message.startswith("the following arguments are required: COMMAND"):
            message = f"a command is needed: one of {', '.join(c[0] for c in COMMANDS)}"
        raise ArgumentsError(self, message)

    def _check_value(self, action, value):  # noqa: D102 - argparse's hook for choices
        if action.choices is None or value in action.choices:
            return
        if isinstance(action, argparse._SubParsersAction):
            raise argparse.ArgumentError(action, f"unknown command {value!r}{_suggest(value, action.choices)}; the "
                                                 f"commands: {', '.join(action.choices)}")
        raise argparse.ArgumentError(action, f"{value!r} is not allowed{_suggest(value, action.choices)}; one of "
                                             f"{', '.join(map(str, action.choices))}")

    def short_usage(self) -> str:
        """``usage: graphsfm map --workspace WORKSPACE [options]`` (the required arguments only)."""
        parts = []
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                parts.append("COMMAND [options]")
            elif not action.option_strings and action.dest != "help":
                parts.append(action.metavar or action.dest.upper())
            elif action.required:
                parts.append(f"{action.option_strings[-1]} {action.metavar or action.dest.upper()}")
        if not any(isinstance(a, argparse._SubParsersAction) for a in self._actions):
            parts.append("[options]")
        return f"usage: {self.prog} {' '.join(parts)}   ('{self.prog} --help' lists them)"


def _verbosity_flags(parser: argparse.ArgumentParser) -> None:
    """``-v``/``-q``, accepted before and after the command (the last one given wins)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("-v", "--verbose", dest="verbosity", action="store_const", const="debug",
                       default=argparse.SUPPRESS, help="debug messages on stderr and in WORK/log.txt")
    group.add_argument("-q", "--quiet", dest="verbosity", action="store_const", const="quiet",
                       default=argparse.SUPPRESS, help="warnings and errors only, no progress bars")


def _add_command_options(p: argparse.ArgumentParser, name: str) -> None:
    for cls in COMMAND_OPTIONS[name]:
        add_options(p, cls, only=ONLY_FIELDS.get((name, cls)))


def build_parser() -> argparse.ArgumentParser:
    from sfm import __version__

    parser = _Parser(prog="graphsfm", description="Graph-based parallel Structure-from-Motion (GraphSfM).")
    parser.add_argument("--version", action="version", version=f"graphsfm {__version__}")
    _verbosity_flags(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for name, help_text, func, arguments in COMMANDS:
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(func=func)
        for flag, kwargs in arguments:
            p.add_argument(flag, **kwargs)
        _verbosity_flags(p)
        _add_command_options(p, name)
    return parser


def parse(argv: list[str]) -> argparse.Namespace:
    """The parsed command line; a bad one raises :class:`ArgumentsError`."""
    parser = build_parser()
    args, extras = parser.parse_known_args(argv)
    if extras:
        sub = _subparsers(parser)[args.command]
        flags = [a for a in extras if a.startswith("-")]
        if flags:
            flag = flags[0].split("=")[0]
            raise ArgumentsError(sub, f"unknown option {flag!r}{_suggest(flag, sub._option_string_actions)}")
        raise ArgumentsError(sub, f"unexpected argument {extras[0]!r}")
    args.verbosity = getattr(args, "verbosity", "normal")
    args.command_line = "graphsfm " + shlex.join(argv)
    return args


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    [sub] = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


# ------------------------------------------------------------------------------- running
def _workspace_of(args: argparse.Namespace) -> Path | None:
    """The command's workspace folder, made if needed; refused when it is a file or cannot be
    written."""
    if args.command not in WORKSPACE_COMMANDS:
        return None
    workspace = Path(args.workspace)
    if workspace.exists() and not workspace.is_dir():
        raise InputError(f"--workspace: {workspace} is a file, not a folder")
    try:
        workspace.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot write to workspace {workspace}: {exc.strerror}") from exc
    if not os.access(workspace, os.W_OK | os.X_OK):
        raise InputError(f"cannot write to workspace {workspace}: permission denied")
    return workspace


def _one_line(exc: BaseException, workspace: Path | None) -> tuple[str, int]:
    """``(message, exit code)`` of an error that ended a command."""
    if isinstance(exc, GraphsfmError):
        return str(exc), exc.exit_code
    if type(exc) is sqlite3.DatabaseError and workspace is not None:  # damaged, not locked nor a constraint
        return str(damaged_database(workspace / "database.db", exc)), 2
    if isinstance(exc, OSError) and exc.strerror:
        where = exc.filename if exc.filename is not None else "a file"
        return f"cannot use {where}: {exc.strerror}", 2
    details = f"; details in {workspace / 'log.txt'}" if workspace else ""
    return f"internal error: {type(exc).__name__}: {exc}{details}", 1


def run(args: argparse.Namespace) -> int:
    """Run the parsed command here: workspace, lock, logging, the command; one line on error."""
    workspace = None
    try:
        workspace = _workspace_of(args)
        with WorkspaceLock(workspace, args.command_line) if workspace else contextlib.nullcontext():
            setup_logging(workspace, args.verbosity)
            reports_here = workspace is not None and args.command not in REPORTS_ITSELF
            if reports_here:
                start_run(workspace, args.command_line, fresh=False)
            code = args.func(args)
            if reports_here:
                finish_run(workspace, "finished")
            return code
    except KeyboardInterrupt:
        print(f"graphsfm {args.command}: stopped by Ctrl-C during {progress.where()}"
              + ("; rerun the same command to resume" if args.command in RESUMABLE else ""), file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the one place that turns a failure into one line
        message, code = _one_line(exc, workspace)
        if code == 1:
            logging.getLogger(DETAILS).info("unexpected error\n%s", traceback.format_exc())
        else:
            log.debug("error: %s", message)
        print(f"graphsfm {args.command}: error: {message}", file=sys.stderr)
        return code
    finally:
        teardown_logging()


def stopped(argv: list[str], signum: int, where: str) -> None:
    """The supervisor's line when a signal stopped the run of ``graphsfm argv``
    (``sfm.__main__``), and the same line in the workspace's log, its report finished as
    stopped and its lock freed."""
    name = "Ctrl-C (SIGINT)" if signum == signal.SIGINT else signal.Signals(signum).name
    try:
        args = parse(argv)
    except (ArgumentsError, SystemExit):  # stopped before the child could refuse the arguments
        print(f"graphsfm: stopped by {name} during {where}", file=sys.stderr, flush=True)
        return
    line = f"stopped by {name} during {where}"
    if args.command in RESUMABLE:
        line += "; rerun the same command to resume"
    print(f"graphsfm {args.command}: {line}", file=sys.stderr, flush=True)
    workspace = Path(args.workspace) if args.command in WORKSPACE_COMMANDS else None
    if workspace is not None and workspace.is_dir():
        with contextlib.suppress(Exception):  # the run's own files are what matters
            with open(workspace / "log.txt", "a") as f:
                f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} WARNING graphsfm: {line}\n")
            if (workspace / "report.json").exists():
                finish_run(workspace, "stopped")
            lock = workspace / "run.lock"
            if lock.read_text().startswith(f"pid {os.getpid()},"):  # the stopped run's: free
                lock.write_text("")


def main(argv: list[str] | None = None) -> int:
    """``graphsfm ARGS`` in this process (``argv``; default ``sys.argv[1:]``): the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = parse(argv)
    except ArgumentsError as exc:
        print(f"{exc.parser.prog}: error: {exc}", file=sys.stderr)
        print(exc.parser.short_usage(), file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help, --version
        return int(exc.code or 0)
    return run(args)


if __name__ == "__main__":  # ``python -m sfm.cli``: the program, as ``python -m sfm``
    import runpy

    runpy.run_module("sfm", run_name="__main__")
