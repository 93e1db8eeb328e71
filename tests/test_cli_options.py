"""One options story: every flag of every command is the options field of the same name, and a
bad value is refused, naming the flag or field, before any stage runs (CLI and Python API)."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

import sfm.cli as cli
from sfm.core.options import OptionError, option_fields
from sfm.mapper.options import MapperOptions

# Arguments that are paths or logging switches, not options.
ARGUMENTS = {"help", "workspace", "images", "model", "out", "gt", "gps", "ref", "verbosity"}


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    [sub] = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


@pytest.mark.parametrize("command", list(cli.COMMAND_OPTIONS))
def test_every_flag_is_the_options_field_of_the_same_name(command):
    parser = _subparsers(cli.build_parser())[command]
    fields = {}
    for cls in cli.COMMAND_OPTIONS[command]:
        only = cli.ONLY_FIELDS.get((command, cls))
        fields.update({f.name: cls for f in option_fields(cls) if only is None or f.name in only})
    flags = {}
    for action in parser._actions:
        if action.dest in ARGUMENTS or not action.option_strings:
            continue
        flags[action.dest] = action.option_strings
    assert set(flags) == set(fields), (set(flags) ^ set(fields))
    for name, strings in flags.items():
        dashed = "--" + name.replace("_", "-")
        assert dashed in strings and all(s in (dashed, "--no-" + dashed[2:]) for s in strings), (name, strings)
        field = next(f for f in option_fields(fields[name]) if f.name == name)
        assert field.metadata["help"] and len(field.metadata["help"]) < 260  # one or two sentences


@pytest.fixture
def no_stage_runs(monkeypatch):
    """Every stage function fails the test if it is called."""
    import sfm.stages.cluster
    import sfm.stages.demo
    import sfm.stages.extract
    import sfm.stages.map
    import sfm.stages.match
    import sfm.stages.merge
    import sfm.stages.reconstruct
    import sfm.stages.synth

    def forbidden(*args, **kwargs):
        raise AssertionError("a stage ran although an option was bad")

    for module, name in [(sfm.stages.extract, "run_extract"), (sfm.stages.match, "run_match"),
                         (sfm.stages.cluster, "run_cluster"), (sfm.stages.map, "run_map"),
                         (sfm.stages.merge, "run_merge"), (sfm.stages.reconstruct, "reconstruct"),
                         (sfm.stages.demo, "run_demo"), (sfm.stages.synth, "run_synth")]:
        monkeypatch.setattr(module, name, forbidden)


@pytest.mark.parametrize("argv, flag", [
    (["reconstruct", "--workspace", "{ws}", "--max-cluster-size", "1"], "--max-cluster-size"),
    (["reconstruct", "--workspace", "{ws}", "--workers", "-3"], "--workers"),
    (["reconstruct", "--workspace", "{ws}", "--completeness", "1.5"], "--completeness"),
    (["map", "--workspace", "{ws}", "--max-reproj-error", "0"], "--max-reproj-error"),
    (["merge", "--workspace", "{ws}", "--max-msd", "-1"], "--max-msd"),
    (["extract", "--images", "{ws}", "--workspace", "{ws}", "--max-num-features", "0"], "--max-num-features"),
    (["match", "--workspace", "{ws}", "--max-ratio", "1.2"], "--max-ratio"),
    (["cluster", "--workspace", "{ws}", "--max-overlap", "0"], "--max-overlap"),
    (["demo", "{ws}", "--num-images", "2"], "--num-images"),
    (["synth", "--workspace", "{ws}", "--outlier-ratio", "1.5"], "--outlier-ratio"),
    (["reconstruct", "--workspace", "{ws}", "--scheduler", "tcp://h:1"], "--scheduler"),
])
def test_a_bad_value_stops_the_command_before_any_stage(tmp_path, capsys, no_stage_runs, argv, flag):
    argv = [a.replace("{ws}", str(tmp_path)) for a in argv]
    assert cli.main(argv) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("graphsfm")]
    assert len(lines) == 1 and (f"error: {flag}: must" in lines[0] or f"error: {flag}: needs" in lines[0]), lines


@pytest.mark.parametrize("argv", [["map", "--workspace", "w", "--loss", "hubr"],
                                  ["extract", "--images", "i", "--workspace", "w", "--camera-mode", "foo"]])
def test_a_bad_choice_is_refused_by_the_parser(argv, capsys, no_stage_runs):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and "is not allowed" in err[0] and err[1].startswith("usage: ")


def test_the_python_api_refuses_bad_values_and_unknown_names_when_options_are_built():
    import sfm

    with pytest.raises(OptionError, match=r"loss: must be one of huber, cauchy, none; got 'hubr'") as err:
        sfm.make_options(loss="hubr")
    assert err.value.field == "loss"
    with pytest.raises(OptionError, match=r"min_num_matches: must be >= 1; got -2"):
        MapperOptions(min_num_matches=-2)
    with pytest.raises(OptionError, match=r"max_image_size: must be an integer, got 3200.5"):
        sfm.make_options(max_image_size=3200.5)
    with pytest.raises(OptionError, match=r"unknown option 'loss_scal' \(did you mean 'loss_scale'\?\)"):
        sfm.make_options(loss_scal=2.0)
    built = sfm.make_options(seed=7, intrinsics="K.txt", workers=3)
    assert built.match.seed == built.cluster.seed == built.mapper.seed == 7  # a shared name goes to each
    assert built.extract.intrinsics.name == "K.txt" and built.execution.workers == 3
    assert dataclasses.replace(built.mapper, loss="cauchy").loss == "cauchy"
    with pytest.raises(OptionError):
        dataclasses.replace(built.mapper, loss="l2")  # replace builds again, and checks again
