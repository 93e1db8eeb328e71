"""``graphsfm extend`` against one ``reconstruct`` over all the images, side by side.

Real photos (``--real``): each set is split into two halves by name order and by viewpoint (the
GT camera centres on either side of the plane through their centroid normal to their principal
axis); the first half is reconstructed, the second added by ``extend`` from an image folder of its
own, and the result is compared with one ``reconstruct`` over all the images (registered images,
AUC@1, AUC@5 of the relative poses against the GT table).

Synthetic aerial scene (``--aerial N``): ``graphsfm synth --scene aerial`` writes N images with
every pair already matched; the old workspace is that database without the last 10% of the images
(their rows deleted), reconstructed; then, timed in one run, ``extend`` (the full database copied
back in, as the extension's extract and match would have written it; new images taken from the
database) and ``reconstruct`` of the full database from scratch, and ``extend --full-ba``; all of
it once per ``--seeds`` value (the synthetic draw), because a nadir block's calibration and tilt
trade along a flat valley and each draw's estimates land at their own point of it.  Each model is also scored on the
old model's images alone: extend keeps the old model's error there, and cannot remove it.

Prints the tables and refreshes the ``extend`` section of ``tools/BENCHMARKS.md``.
"""

from __future__ import annotations

import argparse
import shutil
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_page import add_page_arguments, markdown_table, publish, run_context  # noqa: E402

from sfm.evaluation.ground_truth import read_gt_table  # noqa: E402
from sfm.evaluation.metrics import evaluate  # noqa: E402
from sfm.io.colmap_model import read_model  # noqa: E402
from sfm.stages.extend import ExtendRunOptions, extend  # noqa: E402
from sfm.stages.reconstruct import ReconstructOptions, reconstruct  # noqa: E402
from sfm.stages.synth import run_synth  # noqa: E402
from sfm.synthetic.options import SynthOptions  # noqa: E402

DATA = Path("/work/shared/data")
PAIR_ID_BASE = 2147483647  # COLMAP's pair_id = id1 * 2147483647 + id2


def folder_of(names: list[str], images: Path, out: Path) -> Path:
    """A folder of symbolic links to ``names`` under ``images``."""
    out.mkdir(parents=True, exist_ok=True)
    for n in names:
        (out / n).parent.mkdir(parents=True, exist_ok=True)
        (out / n).symlink_to((images / n).resolve())
    return out


def viewpoint_halves(gt: dict, names: list[str]) -> tuple[list[str], list[str]]:
    """The images on either side of the plane through the camera centres' centroid, normal to
    their principal axis (the GT centres; the larger projections second)."""
    centres = np.array([gt[n].center for n in names])
    d = centres - centres.mean(axis=0)
    axis = np.linalg.svd(d, full_matrices=False)[2][0]
    proj = d @ axis
    order = np.argsort(proj, kind="stable")
    half = len(names) // 2
    first = sorted(names[i] for i in order[:half])
    return first, sorted(set(names) - set(first))


def scores(model_dir: Path, gt: dict) -> dict:
    res = evaluate(read_model(model_dir), gt).to_dict(per_image=False)
    return {"registered": f"{res['num_registered']}/{res['num_gt_images']}", "AUC@1": round(res["auc@1"], 4),
            "AUC@5": round(res["auc@5"], 4)}


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def real_rows(name: str, out: Path, options: dict) -> list[dict]:
    images = DATA / name / "images"
    gt = read_gt_table(DATA / name / "gt" / "cameras_gt_opencv.txt")
    names = sorted(p.name for p in images.iterdir() if p.name in gt)
    rec = ReconstructOptions.from_values(options)
    ext = ExtendRunOptions.from_values(options)
    whole = out / name / "all"
    _, t_all = timed(lambda: reconstruct(folder_of(names, images, whole / "images"), whole / "ws", rec))
    rows = [{"set": name, "split": "none: reconstruct all", "old": 0, "new": len(names), **scores(whole / "ws" / "sparse" / "0", gt),
             "time_s": round(t_all, 1)}]
    half = len(names) // 2
    for split, (a, b) in (("name order", (names[:half], names[half:])), ("viewpoint", viewpoint_halves(gt, names))):
        where = out / name / split.replace(" ", "_")
        _, t_old = timed(lambda: reconstruct(folder_of(a, images, where / "old"), where / "ws", rec))
        summary, t_ext = timed(lambda: extend(where / "ws", folder_of(b, images, where / "new"), ext))
        rows.append({"set": name, "split": split, "old": len(a), "new": len(b),
                     **scores(where / "ws" / "sparse" / "0", gt), "time_s": round(t_ext, 1),
                     "reconstruct_old_s": round(t_old, 1), "own_models": summary["own_models"]})
    return rows


def drop_images(db_path: Path, image_ids: list[int]) -> None:
    """Delete the images' rows (and their pairs) from a COLMAP database."""
    conn = sqlite3.connect(db_path)
    ids = ",".join(str(int(i)) for i in image_ids)
    with conn:
        conn.execute(f"DELETE FROM pose_priors WHERE corr_data_id IN ({ids})")
        for table in ("keypoints", "descriptors", "images"):
            conn.execute(f"DELETE FROM {table} WHERE image_id IN ({ids})")
        for table in ("matches", "two_view_geometries"):
            conn.execute(f"DELETE FROM {table} WHERE pair_id % {PAIR_ID_BASE} IN ({ids}) "
                         f"OR pair_id / {PAIR_ID_BASE} IN ({ids})")
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if "frame_data" in tables:
            conn.execute(f"DELETE FROM frame_data WHERE data_id IN ({ids})")
    conn.execute("VACUUM")
    conn.close()


def aerial_rows(num_images: int, out: Path, options: dict, seeds: list[int]) -> tuple[list[dict], str]:
    rows, notes = [], []
    for seed in seeds:
        where = out / f"seed{seed}"
        data, old, full = where / "aerial_data", where / "aerial_old", where / "aerial_full"
        run_synth(data, SynthOptions(scene="aerial", num_images=num_images, outlier_ratio=0.2, seed=seed))
        gt = read_gt_table(data / "gt" / "cameras_gt_opencv.txt")
        conn = sqlite3.connect(data / "database.db")
        ids = [r[0] for r in conn.execute("SELECT image_id FROM images ORDER BY image_id")]
        conn.close()
        num_new = num_images // 10
        old_n = num_images - num_new
        old.mkdir(parents=True)
        full.mkdir(parents=True)
        shutil.copy2(data / "database.db", old / "database.db")
        drop_images(old / "database.db", ids[-num_new:])
        shutil.copy2(data / "database.db", full / "database.db")
        rec = ReconstructOptions.from_values(options)
        _, t_old = timed(lambda: reconstruct(None, old, rec))
        old_gt = {name: gt[name] for name in (im.name for im in read_model(old / "sparse" / "0").images.values())}
        for variant in ("extend", "extend_full_ba"):  # the extension's extract and match, as written
            shutil.copytree(old, where / variant)
            shutil.copy2(data / "database.db", where / variant / "database.db")
        ext = ExtendRunOptions.from_values(options)
        ext_full = ExtendRunOptions.from_values({**options, "full_ba": True})
        s1, t_ext = timed(lambda: extend(where / "extend", None, ext))
        _, t_full = timed(lambda: reconstruct(None, full, rec))
        _, t_ext_full = timed(lambda: extend(where / "extend_full_ba", None, ext_full))

        def row(run: str, model: Path, seconds: float, ratio: float | None) -> dict:
            on_old = scores(model, old_gt)
            return {"seed": seed, "run": run, **scores(model, gt), f"AUC@1 of the {old_n} old": on_old["AUC@1"],
                    "time_s": round(seconds, 1), "ratio_to_full": "" if ratio is None else round(ratio, 3)}

        rows += [
            row(f"reconstruct {old_n} (the old model)", old / "sparse" / "0", t_old, None),
            row(f"extend {old_n} + {num_new}", where / "extend" / "sparse" / "0", t_ext, t_ext / t_full),
            row(f"extend {old_n} + {num_new} --full-ba", where / "extend_full_ba" / "sparse" / "0", t_ext_full,
                t_ext_full / t_full),
            row(f"reconstruct all {num_images}", full / "sparse" / "0", t_full, 1.0),
        ]
        notes.append(f"seed {seed}: extend / full reconstruct {t_ext / t_full:.3f} (region BA), "
                     f"{t_ext_full / t_full:.3f} (--full-ba); extend's stages: "
                     f"{', '.join(f'{k} {v:.1f}s' for k, v in s1.items() if k.startswith('time_'))}")
    return rows, "\n".join(f"- {n}" for n in notes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--real", nargs="*", default=[], help="data sets under /work/shared/data (lund_door temple_ring)")
    parser.add_argument("--aerial", type=int, default=0, help="images of the synthetic aerial scene (0: none)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0],
                        help="seeds of the synthetic aerial scene (its cameras, points and noise): each gives its old "
                             "model, extend and full reconstruct, so the spread between draws is seen (default 0)")
    parser.add_argument("--out", type=Path, help="output folder (default: a new temporary folder)")
    add_page_arguments(parser)
    args = parser.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="graphsfm_bench_extend_"))
    options = {"seed": 0, "recording": False}
    context = run_context()
    if args.real:
        rows = [r | context for name in args.real for r in real_rows(name, out, options)]
        text = ("Real photos: the first half reconstructed, the second added by `extend`, against one "
                    "`reconstruct` of all (AUC of the relative poses against the GT table; time_s: the extend, "
                    "or the whole reconstruct)\n\n" + markdown_table(rows))
        print(f"## extend, real photos (workspaces in {out})\n\n{text}")
        publish(args, "extend-real", "Adding photos to a finished model (extend): real photos", text)
    if args.aerial:
        rows, note = aerial_rows(args.aerial, out, options, args.seeds)
        rows = [r | context for r in rows]
        text = (f"Synthetic aerial scene, {args.aerial} images (outlier ratio 0.2), one synthetic "
                f"draw per seed; the last 10% added by `extend` from the database; per draw: the old model, extend and the full "
                f"reconstruct timed in one run; AUC over all images and over the old model's images\n\n"
                f"{markdown_table(rows)}\n\n{note}")
        print(f"## extend, synthetic aerial scene (workspaces in {out})\n\n{text}")
        publish(args, "extend-aerial", "Adding photos to a finished model (extend): synthetic aerial scene", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
