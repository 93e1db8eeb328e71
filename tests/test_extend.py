"""``graphsfm extend``: new photos added to a finished model, as a user runs it.

The rendered facade (16 images, exact GT): the first 10 views are reconstructed, the last 6 added
by ``extend``; the result is compared with one ``reconstruct`` of all 16, with the GT, and with
the old model (names, ids and poses of the images far from the new ones).  Photos of another
scene leave the model's files as they were and become a model of their own.  A run killed
(SIGKILL) while extracting, while mapping and between the two renames of the commit finishes
with the same files as the uninterrupted run.  The library parts (the merge plan with the anchor
given, the extension's pairs and clusters) are tested on small known inputs.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from graph.extension import cluster_extension
from graph.image_graph import build_image_graph
from graph.merge_plan import plan_merges
from sfm.evaluation.ground_truth import read_gt_table
from sfm.evaluation.metrics import evaluate
from sfm.io.colmap_model import read_model
from sfm.mapper.bundle_adjuster import BundleAdjuster
from sfm.mapper.options import MapperOptions
from sfm.mapper.state import MapperState
from sfm.matching.pairs import extension_pairs
from sfm.merge.extension import FULL_BA_REGION_SHARE, refine_extension
from sfm.stages.payloads import ClusterPayloads
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import RenderOptions, SynthOptions
from sfm.synthetic.rendered import write_rendered_scene
from sfm.synthetic.scenes import gt_reconstruction, make_scene

NUM_OLD, NUM_NEW = 10, 6
ARGS = ["--seed", "0", "--no-recording"]


# ------------------------------------------------------------------------------ library parts
def test_plan_with_the_anchor_given_roots_its_tree_there():
    # chain 0-1-2-3 (MinST), and 4-5 apart; the MHT centre of the chain would be 1 or 2
    weights = {(0, 1): 1.0, (1, 2): 1.0, (2, 3): 1.0, (0, 2): 5.0, (4, 5): 1.0}
    sizes = {0: 10, 1: 5, 2: 5, 3: 5, 4: 50, 5: 50}
    plans = plan_merges(range(6), sizes, weights, anchor=0)
    main, other = plans
    assert main.anchor == 0 and main.clusters == (0, 1, 2, 3)  # first although smaller than 4-5
    assert main.parent == {0: None, 1: 0, 2: 1, 3: 2}
    assert main.path[3] == (3, 2, 1, 0)
    assert main.layer == {3: 1, 2: 2, 1: 3, 0: 3} and main.num_layers == 3
    assert main.merge_order == ((3, 2), (2, 1), (1, 0))
    assert other.clusters == (4, 5) and other.anchor == 4
    assert plan_merges(range(6), sizes, weights)[0].anchor == 4  # without it: the larger component first
    with pytest.raises(ValueError):
        plan_merges(range(3), {0: 1, 1: 1, 2: 1}, {}, anchor=7)


def test_extension_pairs_all_have_a_new_image():
    new, old = [11, 12, 13], [1, 2, 3, 4, 5]
    exhaustive = extension_pairs(new, old, "exhaustive")
    assert len(exhaustive) == 3 + 3 * 5
    assert all(a in new or b in new for a, b in exhaustive)
    # Retrieval: each new image has descriptors drawn around a centre shared with one old image.
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(5, 128)) * 4
    partner = {11: 1, 12: 3, 13: 5}

    def descriptors(i: int) -> np.ndarray:
        c = centres[(partner.get(i, i)) - 1]
        r = np.random.default_rng(i)
        return np.abs(c + r.normal(size=(300, 128)))

    pairs = extension_pairs(new, old, "retrieval", top_k=1, load_descriptors=descriptors)
    across = {(int(a), int(b)) for a, b in pairs if (a in new) != (b in new)}
    assert across == {(1, 11), (3, 12), (5, 13)}
    assert not any(a in old and b in old for a, b in pairs)


def test_cluster_extension_overlaps_the_anchor_where_it_can():
    # anchor 0-4; new 5-8 see the anchor (5, 6 directly), new 9-10 see only each other; 11 nothing
    edges = [(0, 1, 100), (1, 2, 100), (2, 3, 100), (3, 4, 100), (5, 6, 80), (6, 7, 80), (7, 8, 80), (5, 8, 40),
             (5, 3, 60), (6, 4, 50), (6, 3, 30), (9, 10, 90)]
    i, j, w = (np.array(c) for c in zip(*edges))
    graph = build_image_graph(12, i, j, w.astype(float))
    res = cluster_extension(graph, np.arange(5, 12), np.arange(5), max_cluster_size=4, max_overlap=2)
    assert [c.tolist() for c in res.cores] == [[5, 6, 7, 8], [9, 10]]
    assert res.anchor_overlap[0].tolist() == [3, 4]  # ends of the two strongest edges (60, 50)
    assert res.anchor_overlap[1].size == 0
    assert res.clusters[0].tolist() == [3, 4, 5, 6, 7, 8] and res.clusters[1].tolist() == [9, 10]
    assert res.isolated.tolist() == [11]


# ------------------------------------------------------------------------------ the command
def cli(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "sfm", *args, *ARGS], capture_output=True, text=True,
                          timeout=600, check=False)
    if check:
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "Traceback" not in proc.stderr
    return proc


def files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def links(names: list[str], source: Path, out: Path) -> Path:
    for n in names:
        (out / n).parent.mkdir(parents=True, exist_ok=True)
        (out / n).symlink_to(source / Path(n).name)
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("extend")
    info = write_rendered_scene(root / "scene", RenderOptions(num_images=NUM_OLD + NUM_NEW, seed=3))
    images = Path(info["image_dir"])
    names = sorted(p.name for p in images.iterdir())
    old = links(names[:NUM_OLD], images, root / "old")
    new = links(names[NUM_OLD:], images, root / "new")
    base = root / "base"
    cli("reconstruct", "--images", str(old), "--workspace", str(base))
    extended = root / "extended"
    shutil.copytree(base, extended)
    log = cli("extend", "--images", str(new), "--workspace", str(extended)).stderr
    return {"root": root, "images": images, "old": old, "new": new, "base": base, "extended": extended, "log": log,
            "gt": read_gt_table(info["gt_table"]), "names": names}


def test_extend_registers_every_new_image_as_accurately_as_one_reconstruct(scene):
    full = scene["root"] / "full"
    cli("reconstruct", "--images", str(scene["images"]), "--workspace", str(full))
    model = read_model(scene["extended"] / "sparse" / "0")
    assert sorted(im.name for im in model.images.values()) == scene["names"]
    ours, reference = evaluate(model, scene["gt"]), evaluate(read_model(full / "sparse" / "0"), scene["gt"])
    assert ours.num_registered == reference.num_registered == NUM_OLD + NUM_NEW
    for t in (1.0, 5.0):
        assert ours.auc[t] >= reference.auc[t] - 0.01
    assert ours.median_rotation_error_deg < 0.1
    # The old images keep their names and ids; the extension went through its own steps.
    old = read_model(scene["base"] / "sparse" / "0")
    assert {i: im.name for i, im in old.images.items()} == {i: model.images[i].name for i in old.images}
    assert "6 new and 10 old images" in scene["log"] and "6 registered into sparse/0" in scene["log"]
    report = json.loads((scene["extended"] / "report.json").read_text())
    assert report["extension"]["new_registered_in_model"] == NUM_NEW and report["extension"]["own_models"] == 0
    assert report["registered"] == NUM_OLD + NUM_NEW and report["num_models"] == 1
    ledger = json.loads((scene["extended"] / "stages.json").read_text())
    assert ledger["extend"]["done"] and ledger["extend"]["new_images"] == scene["names"][NUM_OLD:]
    assert not (scene["extended"] / "extend" / "result").exists()


def test_a_finished_extension_is_not_run_again(scene):
    ws = scene["root"] / "again"
    shutil.copytree(scene["extended"], ws)
    before = files(ws / "sparse")
    log = cli("extend", "--images", str(scene["new"]), "--workspace", str(ws)).stderr
    assert "already holds this extension (same images, same options): skipped" in log
    assert files(ws / "sparse") == before


def test_names_already_in_the_workspace_are_refused(scene):
    ws = scene["root"] / "taken"
    shutil.copytree(scene["base"], ws)
    proc = cli("extend", "--images", str(scene["old"]), "--workspace", str(ws), check=False)
    assert proc.returncode == 2
    assert "10 image name(s) of the new folder are already in the workspace (view_000.png" in proc.stderr


def test_photos_of_another_scene_leave_the_model_and_become_a_model_of_their_own(scene):
    other = scene["root"] / "other_scene"
    info = write_rendered_scene(other, RenderOptions(num_images=8, seed=11))
    folder = links([f"other/{p.name}" for p in sorted(Path(info["image_dir"]).iterdir())], Path(info["image_dir"]),
                   scene["root"] / "other_folder")
    ws = scene["root"] / "unrelated"
    shutil.copytree(scene["base"], ws)
    before = files(ws / "sparse" / "0")
    log = cli("extend", "--images", str(folder), "--workspace", str(ws)).stderr
    assert files(ws / "sparse" / "0") == before
    second = read_model(ws / "sparse" / "1")
    assert len(second.images) == 8 and all(im.name.startswith("other/") for im in second.images.values())
    assert "8 new image(s) share nothing that aligns with sparse/0 and form 1 model(s) of their own: sparse/1" in log
    # why the bridge failed: no pair between the two scenes' photos holds PnP's inlier count
    assert ("sparse/1 did not join it as one rigid body: no image pair across them has 30+ verified matches"
            in log), log
    report = json.loads((ws / "report.json").read_text())
    assert report["num_models"] == 2 and report["extension"]["new_registered_own_models"] == 8


def _ledger(ws: Path) -> dict:
    try:
        return json.loads((ws / "stages.json").read_text()).get("extend", {})
    except (OSError, ValueError):
        return {}


def _keypoint_rows(ws: Path) -> int:
    import sqlite3

    try:
        conn = sqlite3.connect(f"{(ws / 'database.db').resolve().as_uri()}?mode=ro", uri=True, timeout=0.05)
        try:
            return conn.execute("SELECT COUNT(*) FROM keypoints").fetchone()[0]
        finally:
            conn.close()
    except sqlite3.Error:
        return -1


def _run_and_kill(args: list[str], during) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "sfm", *args, *ARGS], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    deadline = time.time() + 300
    while proc.poll() is None and time.time() < deadline:
        if during():
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
            reader.join(5)
            return
        time.sleep(0.005)
    proc.kill()
    reader.join(5)
    pytest.fail(f"the run ended before it could be killed: {''.join(lines)[-2000:]}")


def test_killed_extension_resumes_to_the_same_model(scene):
    ws = scene["root"] / "killed"
    shutil.copytree(scene["base"], ws)
    args = ["extend", "--images", str(scene["new"]), "--workspace", str(ws)]
    _run_and_kill([*args, "--workers", "1"], lambda: NUM_OLD < _keypoint_rows(ws) < NUM_OLD + NUM_NEW)
    _run_and_kill(args, lambda: bool(_ledger(ws).get("steps", {}).get("cluster")))
    assert not _ledger(ws).get("done") and files(ws / "sparse") == files(scene["base"] / "sparse")
    log = cli(*args).stderr
    assert "resuming the extension an earlier run started (steps done: extract, match, cluster" in log
    assert files(ws / "sparse") == files(scene["extended"] / "sparse")


def test_a_commit_cut_between_its_renames_is_completed(scene):
    ws = scene["root"] / "cut"
    shutil.copytree(scene["extended"], ws)
    # the state a kill leaves between the two renames: no WORK/sparse, the result complete
    (ws / "sparse").rename(ws / "extend" / "result")
    ledger = json.loads((ws / "stages.json").read_text())
    ledger["extend"]["done"] = False
    (ws / "stages.json").write_text(json.dumps(ledger))
    log = cli("extend", "--images", str(scene["new"]), "--workspace", str(ws)).stderr
    assert "completing the replacement" in log and "skipped" in log
    assert files(ws / "sparse") == files(scene["extended"] / "sparse")


def _street_extension(tmp_path: Path, num_new: int) -> tuple:
    """``refine_extension`` on a 60-image street with exact poses (as if merged), its last
    ``num_new`` images new: the refined model, the poses and the names in the new images' region."""
    opts = SynthOptions(scene="street", num_images=60, observations_per_image=400, seed=2)
    scene = make_scene(opts)
    write_database(scene, simulate_matching(scene, opts), tmp_path / "database.db", camera_model="SIMPLE_RADIAL")
    truth = gt_reconstruction(scene)
    poses = {im.name: (im.cam_from_world_rotation, im.cam_from_world_translation) for im in truth.images.values()}
    new = sorted(poses)[len(poses) - num_new:]
    [payload] = ClusterPayloads(tmp_path / "database.db", [sorted(poses)], fixed_intrinsics=False, min_inliers=15)
    state = MapperState(payload, MapperOptions())
    state.set_poses(poses)
    state.retriangulate()
    region = {state.names[i] for i in BundleAdjuster(state).region_images(
        np.array([i for i, n in enumerate(state.names) if n in new]))}
    params = {cam_id: np.asarray(cam.params, float) for cam_id, cam in truth.cameras.items()}
    recon = refine_extension(payload, MapperOptions(), poses, params, set(new))
    return recon, poses, region


@pytest.mark.parametrize("num_new, global_ba", [(3, False), (24, True)])
def test_an_extension_bundle_adjusts_its_region_or_when_that_is_most_of_the_model_all_of_it(
        tmp_path, num_new, global_ba):
    """A street of 60 images extended at its end: 3 new images free a region of a few images
    and the images beyond it keep their poses exactly; 24 free a region of at least
    ``FULL_BA_REGION_SHARE`` of the model, and the global BA moves every image."""
    recon, poses, region = _street_extension(tmp_path, num_new)
    assert (len(region) >= FULL_BA_REGION_SHARE * 60) == global_ba
    assert len(recon.registered_image_ids) == 60
    moved = {im.name for im in recon.images.values()
             if not np.array_equal(im.cam_from_world_translation, poses[im.name][1])}
    if global_ba:
        assert moved == set(poses)
    else:
        assert moved <= region and len(region) < 30
