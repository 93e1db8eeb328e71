"""Each command-line mistake a new user makes: exit code 2 and one line saying what is wrong and
what is allowed (then at most one short usage line), a close match for a typo, ``--version``,
``-v``/``-q`` anywhere, and the workspace's own faults (a file for a folder, an existing
output, a damaged database, a workspace another run holds) as one line, never a traceback."""

from __future__ import annotations

import importlib.metadata
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import sfm
import sfm.cli as cli
from sfm.io.image_files import find_images
from sfm.io.workspace import WorkspaceLock
from sfm.errors import WorkspaceBusyError

ROOT = Path(__file__).resolve().parents[1]


def run_main(capsys, *argv: str) -> tuple[int, list[str]]:
    code = cli.main(list(argv))
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    return code, err


def graphsfm(*argv: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    proc = subprocess.run([sys.executable, "-m", "sfm", *argv], capture_output=True, text=True, timeout=timeout,
                          env=env)
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    return proc


@pytest.mark.parametrize("argv, line", [
    (["extract", "--images", "i", "--workspace", "w", "--camera-mode", "foo"],
     "graphsfm extract: error: --camera-mode: 'foo' is not allowed; one of auto, single, per-folder, per-image"),
    (["map", "--workspace", "w", "--loss", "hubr"],
     "graphsfm map: error: --loss: 'hubr' is not allowed (did you mean 'huber'?); one of huber, cauchy, none"),
    (["reconstruct", "--workspace", "w", "--max-clustr-size", "5"],
     "graphsfm reconstruct: error: unknown option '--max-clustr-size' (did you mean '--max-cluster-size'?)"),
    (["reconstrct", "--workspace", "w"],
     "graphsfm: error: unknown command 'reconstrct' (did you mean 'reconstruct'?); the commands: extract, match, "
     "cluster, map, merge, reconstruct, extend, demo, evaluate, export, info, align, synth"),
    (["synth", "--workspace", "w", "--images", "5"],
     "graphsfm synth: error: unknown option '--images' (did you mean '--num-images'?)"),
    (["reconstruct", "--workspace", "w", "--workers", "x"],
     "graphsfm reconstruct: error: --workers: 'x' is not an integer; allowed: >= 0"),
    (["reconstruct", "--workspace", "w", "--workers"], "graphsfm reconstruct: error: --workers: needs a value (>= 0)"),
    (["map"], "graphsfm map: error: the following arguments are required: --workspace"),
    ([], "graphsfm: error: a command is needed: one of extract, match, cluster, map, merge, reconstruct, extend, "
         "demo, evaluate, export, info, align, synth"),
])
def test_a_parser_error_is_one_line_then_a_short_usage_line(capsys, argv, line):
    code, err = run_main(capsys, *argv)
    assert code == 2 and len(err) == 2, err
    assert err[0] == line
    command = argv[0] if argv and argv[0] in dict((c[0], 1) for c in cli.COMMANDS) else None
    prog = f"graphsfm {command}" if command else "graphsfm"
    assert err[1].startswith(f"usage: {prog} ") and err[1].endswith(f"('{prog} --help' lists them)")


@pytest.mark.parametrize("argv, line", [
    (["reconstruct", "--workspace", "{tmp}/w", "--workers", "-3"], "--workers: must be >= 0; got -3"),
    (["reconstruct", "--workspace", "{tmp}/w", "--max-cluster-size", "1"], "--max-cluster-size: must be >= 2; got 1"),
    (["demo", "{tmp}/w", "--num-images", "2"], "--num-images: must be >= 6; got 2"),
])
def test_a_value_out_of_range_is_one_line(tmp_path, capsys, argv, line):
    code, err = run_main(capsys, *[a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert code == 2 and err == [f"graphsfm {argv[0]}: error: {line}"]


def test_version_is_pyprojects():
    pyproject = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    assert sfm.__version__ == pyproject == importlib.metadata.version("graphsfm")
    proc = graphsfm("--version")
    assert proc.returncode == 0 and proc.stdout.strip() == f"graphsfm {pyproject}"


@pytest.mark.parametrize("argv, verbosity", [
    (["-v", "map", "--workspace", "w"], "debug"), (["map", "--workspace", "w", "-v"], "debug"),
    (["-q", "map", "--workspace", "w"], "quiet"), (["map", "-q", "--workspace", "w"], "quiet"),
    (["map", "--workspace", "w"], "normal"),
])
def test_verbose_and_quiet_go_anywhere(argv, verbosity):
    assert cli.parse(argv).verbosity == verbosity


def test_the_help_lists_the_commands_in_pipeline_order_and_the_demo_promises_no_count(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    positions = [out.index(f"\n    {name} ") for name in ("extract", "match", "cluster", "map", "merge", "reconstruct")]
    assert positions == sorted(positions)
    assert cli.main(["demo", "--help"]) == 0
    assert not re.search(r"\d+ clusters", capsys.readouterr().out)  # how many depends on the scene


def test_images_that_is_a_file_and_a_workspace_that_is_a_file(tmp_path, capsys):
    a_file = tmp_path / "photo.jpg"
    a_file.write_bytes(b"\xff\xd8")
    code, err = run_main(capsys, "reconstruct", "--images", str(a_file), "--workspace", str(tmp_path / "w"))
    assert code == 2 and err == [f"graphsfm reconstruct: error: --images: {a_file} is a file, not a folder of images"]
    code, err = run_main(capsys, "reconstruct", "--images", str(tmp_path), "--workspace", str(a_file))
    assert code == 2 and err == [f"graphsfm reconstruct: error: --workspace: {a_file} is a file, not a folder"]
    code, err = run_main(capsys, "extract", "--images", str(tmp_path / "none"), "--workspace", str(tmp_path / "w"))
    assert code == 2 and err == [f"graphsfm extract: error: --images: image folder not found: {tmp_path / 'none'}"]


def test_export_onto_an_existing_output_is_refused(tmp_path, capsys):
    from sfm.stages.synth import run_synth
    from sfm.synthetic.options import SynthOptions

    run_synth(tmp_path, SynthOptions(num_images=6, observations_per_image=100, seed=1))
    model = tmp_path / "gt" / "model"
    (tmp_path / "points.ply").write_text("mine")
    code, err = run_main(capsys, "export", str(model), str(tmp_path / "points.ply"), "--to", "ply")
    assert code == 2 and err == [f"graphsfm export: error: {tmp_path / 'points.ply'} exists; choose another output "
                                 "or pass --overwrite to replace it"]
    assert (tmp_path / "points.ply").read_text() == "mine"
    assert run_main(capsys, "export", str(model), str(tmp_path / "txt"), "--to", "txt")[0] == 0
    assert run_main(capsys, "export", str(model), str(tmp_path / "txt"), "--to", "txt")[0] == 2


def test_a_damaged_database_or_workspace_file_is_named_with_what_to_do(tmp_path, capsys):
    ws = tmp_path / "w"
    ws.mkdir()
    (ws / "database.db").write_bytes(b"SQLite format 3\x00" + os.urandom(4096))
    code, err = run_main(capsys, "reconstruct", "--workspace", str(ws))
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"graphsfm reconstruct: error: {ws / 'database.db'} is damaged (")
    assert err[0].endswith("delete it (and database.db-wal, -shm if there) and rerun with --images: the features are "
                           "extracted and matched again")
    from sfm.stages.synth import run_synth
    from sfm.synthetic.options import SynthOptions

    ws2 = tmp_path / "w2"
    run_synth(ws2, SynthOptions(num_images=16, observations_per_image=400, seed=2))
    assert run_main(capsys, "reconstruct", "--workspace", str(ws2), "-q", "--no-recording")[0] == 0
    (ws2 / "clusters.json").write_text('{"clusters": ')  # cut short
    code, err = run_main(capsys, "reconstruct", "--workspace", str(ws2), "-q", "--no-recording")
    assert code == 2 and err == [f"graphsfm reconstruct: error: {ws2 / 'clusters.json'} is damaged (not valid JSON: "
                                 "Expecting value: line 1 column 14 (char 13)): delete it and rerun: the stage that "
                                 "writes it runs again"]


def test_image_discovery_visits_each_real_folder_and_file_once(tmp_path, caplog):
    d = tmp_path / "images"
    (d / "sub").mkdir(parents=True)
    for name in ("a.jpg", "b.png", "sub/c.jpg"):
        (d / name).write_bytes(b"x")
    (d / "loop").symlink_to(d, target_is_directory=True)  # a link back to the folder itself
    (d / "sub" / "up").symlink_to(d, target_is_directory=True)
    (d / "twin.jpg").symlink_to(d / "a.jpg")  # the same file under a second name
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "e.jpg").write_bytes(b"x")
    (d / "more").symlink_to(tmp_path / "elsewhere", target_is_directory=True)  # a real folder, once
    with caplog.at_level("WARNING"):
        assert find_images(d) == ["a.jpg", "b.png", "more/e.jpg", "sub/c.jpg"]
    [warning] = [r.getMessage() for r in caplog.records]
    assert warning.startswith("3 link(s) in ") and "loop/" in warning and "twin.jpg" in warning


def test_a_workspace_in_use_is_refused_at_once_and_a_dead_owners_lock_is_taken_over(tmp_path):
    ws = tmp_path / "w"
    ws.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; sys.path.insert(0, sys.argv[1]); from sfm.io.workspace import WorkspaceLock\n"
        "with WorkspaceLock(sys.argv[2], 'graphsfm reconstruct --workspace w'):\n"
        "    print('held', flush=True); time.sleep(60)"), str(ROOT), str(ws)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        proc = graphsfm("reconstruct", "--workspace", str(ws), timeout=120)  # refused, not waiting for the lock
        code, err = proc.returncode, [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert code == 2 and len(err) == 1
        assert err[0].startswith(f"graphsfm reconstruct: error: workspace {ws} is in use by another run "
                                 f"(pid {holder.pid}, graphsfm reconstruct --workspace w, since ")
        assert err[0].endswith("): wait for it to end, or stop it")
        assert not (ws / "report.json").exists()
    finally:
        holder.kill()
        holder.wait()
    # The holder is gone (killed: its lock file still names it): the next run takes the lock over.
    assert f"pid {holder.pid}," in (ws / "run.lock").read_text()
    with WorkspaceLock(ws, "mine"):
        assert (ws / "run.lock").read_text().startswith(f"pid {os.getpid()}, mine, since ")
        with WorkspaceLock(ws, "nested"):  # the same process again (CLI, then reconstruct())
            pass
        other = subprocess.run([sys.executable, "-c", (
            "import sys; sys.path.insert(0, sys.argv[1]); from sfm.io.workspace import WorkspaceLock\n"
            "from sfm.errors import WorkspaceBusyError\n"
            "try:\n    WorkspaceLock(sys.argv[2]).__enter__()\nexcept WorkspaceBusyError:\n    sys.exit(7)"),
            str(ROOT), str(ws)])
        assert other.returncode == 7
    assert (ws / "run.lock").read_text() == ""
    assert issubclass(WorkspaceBusyError, sfm.errors.InputError)


def test_a_cluster_that_fails_is_the_error_and_its_traceback_is_in_the_log(tmp_path, capsys, monkeypatch):
    """A map whose only cluster raised says so (exit 1, the exception in the one line), not
    that the photos gave no image pair; the traceback is in WORK/log.txt at the default
    verbosity and not on the terminal."""
    import sfm.mapper.incremental as incremental
    from sfm.stages.synth import run_synth
    from sfm.synthetic.options import SynthOptions

    run_synth(tmp_path, SynthOptions(num_images=8, observations_per_image=200, seed=4))

    def broken(state, adjuster):
        raise TypeError("a bug in the final BA")

    monkeypatch.setattr(incremental, "final_refinement", broken)
    capsys.readouterr()
    assert cli.main(["map", "--workspace", str(tmp_path), "--workers", "1", "--no-recording"]) == 1
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (f"graphsfm map: error: no model could be made: 1 cluster(s) failed and are left "
                                    f"out: C0; cluster C0: TypeError: a bug in the final BA; details in "
                                    f"{tmp_path / 'log.txt'}")
    assert "Traceback" not in err
    log = (tmp_path / "log.txt").read_text()
    assert "Traceback" in log and 'raise TypeError("a bug in the final BA")' in log
