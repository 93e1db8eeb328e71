"""``graphsfm extend``: new photos added to a finished model as one more cluster (or several).

The new images go through the pipeline on their own, and the finished model ``WORK/sparse/0``
is the anchor they are merged into (paper section 3.1 and 3.2, Alg. 1 and 2 with the anchor
given).  Steps, each recorded in the ledger's ``extend`` entry (``WORK/stages.json``):

1. ``extract``: the new images into the same database (``run_extract``, resuming per image).
   Image names are paths relative to the folder given, as for ``reconstruct``; a name already
   in the database that is not one of this extension's is refused (put the new photos in a
   folder of their own names, e.g. a subfolder).
2. ``match``: the pairs with at least one new image, new x old by retrieval among the old
   images (``sfm.stages.match.match_extension``), so the matching grows with the new images.
3. ``cluster``: the new images cut and expanded as Alg. 1 does, each cluster also given the
   images of the model it overlaps most (``graph.extension``) -> ``WORK/extend/clusters.json``.
4. ``map``: local SfM of each new cluster -> ``WORK/extend/clusters/E<k>/<m>`` (recorded per
   cluster, so a killed run keeps the clusters that were done).
5. ``merge``: the model and the new local models as one cluster graph, the model the fixed
   anchor (``sfm.merge.extension``); re-triangulation and a BA of the new images' region (the
   model's images far from it held; ``full_ba``: one global BA) -> ``WORK/extend/result/N``.
6. ``commit``: ``WORK/sparse`` replaced by the result by renaming folders (the ledger says a
   commit is under way; a rerun after a kill completes it), so ``WORK/sparse`` is always the
   old model or the new one.

``WORK/sparse/0`` stays the model, its images keep their names and ids; it is untouched (the
same bytes) when no new cluster could be aligned to it.  New images that see nothing of it form
models of their own, after the workspace's other models, and the report says so.  Without an
image folder, the new images are the database's images that no model of the workspace
registers, their features and matches already in the database (a database written by another
tool, or by ``synth``): extract and match are skipped.

The same input, options and seed give the same files; a rerun of a finished extension with
the same images and options is skipped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from graph.extension import cluster_extension
from graph.image_graph import build_image_graph
from sfm.core.model import Reconstruction
from sfm.errors import InputError
from sfm.execution.local import LocalExecutor
from sfm.execution.options import make_executor
from sfm.execution.process_pool import start_pool_server
from sfm.io.colmap_model import read_model, write_model
from sfm.io.database import Database
from sfm.io.image_files import find_images
from sfm.io.ledger import Ledger, changes, files_fingerprint, fingerprint, options_record
from sfm.io.report import finish_run, model_facts, models_fields, start_run, update_report
from sfm.io.workspace import (DATABASE, RECORDING, WorkspaceLock, numbered_folders, read_georegistration, read_json,
                               write_georegistration, write_json_atomic)
from sfm.merge.alignment import align_components, anchor_from_model, merged_poses
from sfm.merge.cluster_graph import LocalModel
from sfm.merge.extension import ANCHOR, extended_poses, extension_plans, plan_extension, refine_extension
from sfm.merge.options import ExtendOptions
from sfm.merge.refinement import refine_with_poses
from sfm.stages.extract import run_extract
from sfm.stages.extract_writer import extract_options_record
from sfm.stages.georegister import georegister_models
from sfm.stages.map import map_clusters, registered_names, write_models
from sfm.stages.match import match_extension
from sfm.stages.merge import bridge_parts
from sfm.stages.payloads import ClusterPayloads
from sfm.stages.reconstruct import ReconstructOptions
from sfm.viz.mapping import log_cluster_error, log_growth, log_local_model
from sfm.viz.merging import log_merge
from sfm.viz.models import log_model
from sfm.viz.recorder import Recorder
from sfm.viz.tour import extend_text

log = logging.getLogger(__name__)

EXTEND = "extend"  # the workspace folder of an extension in progress, and its ledger entry


@dataclass(frozen=True)
class ExtendRunOptions(ReconstructOptions):
    """The options of every stage the extension runs again on the new images, and its own."""

    extend: ExtendOptions = field(default_factory=ExtendOptions)


class _Extension:
    """One extension of ``WORK/sparse`` (module docstring): the ledger entry and the folders."""

    def __init__(self, workspace: Path, options: ExtendRunOptions, executor, recorder: Recorder) -> None:
        self.ws, self.options, self.executor, self.recorder = workspace, options, executor, recorder
        self.sparse, self.dir = workspace / "sparse", workspace / EXTEND
        self.result, self.old = self.dir / "result", self.dir / "sparse.old"
        self.ledger = Ledger(workspace)
        o = options
        self.opts = {"extract": extract_options_record(o.extract), "match": options_record(o.match),
                     "cluster": options_record(o.cluster), "mapper": options_record(o.mapper),
                     "merge": options_record(o.merge), "extend": options_record(o.extend)}
        self.times: dict[str, float] = {}

    # ------------------------------------------------------------------ ledger
    @property
    def rec(self) -> dict:
        return self.ledger.data[EXTEND]

    def step_done(self, step: str) -> bool:
        return bool(self.rec["steps"].get(step))

    def mark(self, step: str, value=True) -> None:
        self.rec["steps"][step] = value
        self.ledger.save()

    # ------------------------------------------------------------------ commit
    def complete_commit(self) -> None:
        """Finish a commit that a kill interrupted (module docstring, step 6): the renames
        still to do, then the ledger."""
        rec = self.ledger.record(EXTEND)
        if not rec or rec.get("done") or not rec.get("steps", {}).get("commit"):
            return
        log.info("extend: completing the replacement of %s that an earlier run started", self.sparse)
        self._swap()

    def _swap(self) -> None:
        if self.result.is_dir():
            if self.sparse.exists():
                shutil.rmtree(self.old, ignore_errors=True)
                self.sparse.rename(self.old)
            self.result.rename(self.sparse)
        shutil.rmtree(self.old, ignore_errors=True)
        self.ledger.finish(EXTEND, files_fingerprint(self.sparse))

    def commit(self) -> None:
        self.mark("commit")
        self._swap()


def run_extend(workspace: Path, images: Path | None, options: ExtendRunOptions = ExtendRunOptions(),
               executor=None, recorder: Recorder | None = None) -> dict:
    """Add the images of ``images`` (None: the database's images no model registers) to the
    model ``WORK/sparse/0`` (module docstring; paper sections 3.1-3.2, Alg. 1 and 2 with the
    model as the given anchor); returns the extension's summary (also in ``report.json``)."""
    workspace = Path(workspace)
    executor = executor or LocalExecutor()
    recorder = recorder or Recorder.disabled()
    ext = _Extension(workspace, options, executor, recorder)
    ext.complete_commit()
    if not (ext.sparse / "0" / "images.bin").exists():
        raise InputError(f"no model at {ext.sparse / '0'}: run `graphsfm reconstruct` first")
    if not (workspace / DATABASE).is_file():
        raise InputError(f"no database at {workspace / DATABASE}")
    names = None
    if images is not None:
        images = Path(images)
        if not images.is_dir():
            raise InputError(f"image folder not found: {images}")
        names = find_images(images)
        if not names:
            raise InputError(f"no images found in {images}")
    identity = {"images": None if images is None else str(images.resolve()), "names": names}
    old_fp = files_fingerprint(ext.sparse)
    rec = ext.ledger.record(EXTEND)
    if (rec and rec.get("done") and rec.get("output") == old_fp and rec.get("options") == ext.opts
            and rec.get("identity") == identity):
        log.info("extend: %s already holds this extension (same images, same options): skipped", ext.sparse)
        return rec["result"]
    input_fp = fingerprint(old_fp, identity)
    if rec and not rec.get("done") and rec.get("input") == input_fp and rec.get("options") == ext.opts:
        log.info("extend: resuming the extension an earlier run started (steps done: %s)",
                 ", ".join(s for s, v in rec.get("steps", {}).items() if v) or "none")
    else:
        if rec and not rec.get("done"):
            log.info("extend: starting afresh: %s", ext.ledger.why_stale(EXTEND, ext.opts, input_fp))
        new = _new_images(ext, names, rec)
        shutil.rmtree(ext.dir, ignore_errors=True)
        ext.ledger.start(EXTEND, ext.opts, input_fp, keep={"identity": identity, "new_images": new, "steps": {},
                                                           "clusters": {}})
    return _run_steps(ext, images)


def _new_images(ext: _Extension, names: list[str] | None, rec: dict | None) -> list[str]:
    """The names of the images to add: those of the folder (refusing a name the database holds
    for another image), or the database's images that no model of the workspace registers."""
    with Database(ext.ws / DATABASE, readonly=True) as db:
        in_db = {r.name for r in db.read_images().values()}
    if names is None:
        registered = {im.name for folder in numbered_folders(ext.sparse) for im in read_model(folder).images.values()}
        new = sorted(in_db - registered)
        if not new:
            raise InputError("every image of the database is in a model: nothing to add (give --images)")
        return new
    ours = set(rec.get("new_images", [])) if rec and not rec.get("done") else set()
    taken = sorted(n for n in names if n in in_db and n not in ours)
    if taken:
        raise InputError(f"{len(taken)} image name(s) of the new folder are already in the workspace "
                         f"({', '.join(taken[:3])}{' ...' if len(taken) > 3 else ''}): names are paths relative to "
                         "the image folder, so give new photos names of their own (e.g. put them in a subfolder)")
    extract_rec = ext.ledger.record("extract")
    diff = changes(extract_rec.get("options") if extract_rec else None, ext.opts["extract"])
    if diff:
        raise InputError("the new images must be extracted with the options the workspace's images were "
                         f"extracted with; these differ: {'; '.join(diff)}")
    return list(names)


def _run_steps(ext: _Extension, images: Path | None) -> dict:
    o, ws = ext.options, ext.ws
    new_names: list[str] = list(ext.rec["new_images"])
    t0 = time.perf_counter()
    if images is not None and not ext.step_done("extract"):
        result = run_extract(images, ws, o.extract, ext.executor)
        ext.rec["bad_files"] = [n for n, _ in result.bad_files]
        ext.mark("extract")
    bad = set(ext.rec.get("bad_files") or [])
    new_names = [n for n in new_names if n not in bad]
    t1 = time.perf_counter()
    if images is not None and not ext.step_done("match"):
        match_extension(ws, new_names, o.match, ext.executor)
        ext.mark("match")
    t2 = time.perf_counter()
    ext.times.update({"extract": t1 - t0, "match": t2 - t1})

    olds = [read_model(folder) for folder in numbered_folders(ext.sparse)]  # sparse/0, the anchor, first
    clusters = _cluster(ext, olds, new_names)
    t3 = time.perf_counter()
    models = _map(ext, clusters, {cam_id: cam.params for cam_id, cam in olds[0].cameras.items()})
    t4 = time.perf_counter()
    ext.times.update({"cluster": t3 - t2, "map": t4 - t3})
    if not ext.step_done("result"):
        summary = _merge(ext, olds, models, new_names, clusters)
        ext.rec["result"] = summary
        ext.mark("result", True)
    summary = ext.rec["result"]
    del olds, models
    for w in summary["warnings"]:
        log.warning("%s", w)
    ext.commit()
    _report(ext, summary, time.perf_counter() - t0)
    log.info("extend: %d new images, %d registered into sparse/0 (%d registered in all), %d model(s)",
             summary["new_images"], summary["new_registered_in_model"], summary["registered"], summary["num_models"])
    return summary


def _report(ext: _Extension, summary: dict, elapsed: float) -> None:
    """``report.json`` after the commit: the workspace's final models as they now are, the
    database's counts, the extension's summary with the time of each of its steps."""
    written = [{"path": str(folder.resolve()), **model.summary()}
               for folder in numbered_folders(ext.sparse) for model in [read_model(folder)]]
    names = [registered_names(Path(m["path"])) for m in written]
    fields = {**models_fields(written), **model_facts(ext.ws, names), "warnings": summary["warnings"],
              "extension": {**summary, "times_s": {k: round(v, 3) for k, v in ext.times.items()}}}
    update_report(ext.ws, fields, {"extend": elapsed})


def _cluster(ext: _Extension, olds: list[Reconstruction], new_names: list[str]) -> dict:
    """Step 3: the new images' clusters (``graph.extension``), with overlap into ``sparse/0`` and
    the workspace's other models -> ``WORK/extend/clusters.json``."""
    path = ext.dir / "clusters.json"
    if ext.step_done("cluster") and path.exists():
        return read_json(path)
    o = ext.options.cluster
    with Database(ext.ws / DATABASE, readonly=True) as db:
        images = db.read_images()
        id1, id2, weights = db.verified_pairs(min_inliers=o.min_inliers)
    ids = np.array(sorted(images), dtype=np.int64)
    names = [images[i].name for i in ids]
    node = {n: k for k, n in enumerate(names)}
    pos = {int(i): k for k, i in enumerate(ids)}
    graph = build_image_graph(len(ids), [pos[int(i)] for i in id1], [pos[int(j)] for j in id2],
                              weights.astype(np.float64))
    given = [np.array(sorted(node[im.name] for im in m.images.values()), dtype=np.int64) for m in olds]
    new_nodes = np.array(sorted(node[n] for n in new_names if n in node), dtype=np.int64)
    res = cluster_extension(graph, new_nodes, given[0], o.max_cluster_size, o.completeness, o.max_overlap, o.seed,
                            other_nodes=given[1:])
    out = {
        "clusters": [{"id": f"E{k}", "core": [names[i] for i in core], "members": [names[i] for i in members],
                      "anchor_overlap": [names[i] for i in overlap]}
                     for k, (core, members, overlap) in enumerate(zip(res.cores, res.clusters, res.anchor_overlap))],
        "isolated_images": [names[i] for i in res.isolated],
        "options": dataclasses.asdict(o),
    }
    ext.dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, out)
    ext.mark("cluster", fingerprint(out["clusters"]))
    return out


def _map(ext: _Extension, clusters: dict, calibration: dict[int, np.ndarray]) -> list[LocalModel]:
    """Step 4: local SfM of every new cluster -> ``WORK/extend/clusters/E<k>/<m>``, each cluster
    recorded as it finishes (a rerun keeps them).  A camera the finished model calibrated
    (``calibration``: its parameters there) is the new clusters' prior: they start from it and
    free its principal point and distortion only where their own photos call for it, as a
    cluster does of the database's values.  From the nominal values instead, a new cluster that
    cannot determine them (half the scene, or less) holds them there, and its poses absorb the
    difference: merged into the model, its points would reproject off by it."""
    o = ext.options.mapper
    members = [c["members"] for c in clusters["clusters"]]
    labels = [c["id"] for c in clusters["clusters"]]
    root = ext.dir / "clusters"
    done = ext.rec["clusters"]
    if members:
        payloads = ClusterPayloads(ext.ws / DATABASE, members, fixed_intrinsics=not o.refine_given_intrinsics,
                                   min_inliers=o.min_num_matches, labels=labels, calibration=calibration)
        todo = [k for k, label in enumerate(labels) if label not in done]
        max_points = ext.recorder.options.record_points if ext.recorder.enabled else 0
        for k, res in map_clusters(payloads, todo, o.for_model(False), ext.executor, max_points):
            local_models, growth = res.value or ([], None)
            written = write_models(local_models, root / labels[k])
            if res.error is not None:
                log.warning("new cluster %s failed: %s", labels[k], res.error)
                log_cluster_error(ext.recorder, labels[k], payloads.names[k], res.error)
            if growth is not None:
                log_growth(ext.recorder, growth)
            for m, model in enumerate(local_models):
                log_local_model(ext.recorder, labels[k], m, model, growth_logged=growth is not None)
            done[labels[k]] = {"images": payloads.sizes[k], "models": len(written), "error": res.error}
            ext.ledger.save()
    models = []
    for label in labels:
        for m in range(done[label]["models"]):
            models.append(LocalModel(f"{label}/{m}", read_model(root / label / str(m))))
    return models


def _merge(ext: _Extension, olds: list[Reconstruction], models: list[LocalModel], new_names: list[str],
           clusters: dict) -> dict:
    """Step 5: the new local models merged into ``sparse/0`` as the fixed anchor (with the
    workspace's other models that they join to it), refined, and written with the remaining
    models to ``WORK/extend/result/N``."""
    t0 = time.perf_counter()
    o = ext.options
    nodes = [LocalModel(f"sparse/{k}", m) for k, m in enumerate(olds)] + models
    num_old = len(olds)
    edges, plans = plan_extension(nodes, o.merge, seed=o.mapper.seed)
    with Database(ext.ws / DATABASE, readonly=True) as database:
        nominal = {cam_id: cam.params for cam_id, cam in database.read_cameras().items()}
    finished = [all(n < num_old for n in p.clusters) for p in plans]
    bridge_failures: dict[tuple[frozenset, frozenset], str] = {}  # why parts did not join, by their nodes
    if not all(finished[1:]):  # new models no common cameras align: bridged where their photos see the others' points
        parts, _ = align_components(nodes, plans, edges, nominal)
        found = bridge_parts(ext.ws / DATABASE, o.mapper, o.merge, plans, parts, finished=finished,
                             why_not=bridge_failures)
        if found:
            edges.update(found)
            plans = extension_plans(nodes, edges)
    main = plans[0]
    new_set = set(new_names)
    untouched = [p.anchor for p in plans[1:] if len(p.clusters) == 1 and p.anchor < num_old]
    components = []  # (plan, poses, params) of the other plans with a new model: models of their own
    for plan in plans[1:]:
        if not (len(plan.clusters) == 1 and plan.anchor < num_old):
            sims = anchor_from_model(plan, edges)
            components.append((plan, *merged_poses(nodes, plan, sims, nominal)))
    t_merge = time.perf_counter() - t0

    db = ext.ws / DATABASE
    mapper = o.mapper
    merged_in = [n for n in main.clusters if n != ANCHOR]
    extended = None
    if merged_in:
        poses, params, pooled, sims = extended_poses(nodes, main, edges, nominal)
        log_merge(ext.recorder, [n.label for n in nodes], [n.model for n in nodes], edges, [main], [sims], stage="extend")
        anchor_names = {im.name for im in olds[0].images.values()}
        payloads = ClusterPayloads(db, [sorted(poses)], fixed_intrinsics=not mapper.refine_given_intrinsics,
                                   min_inliers=mapper.min_num_matches, labels=["extended"])
        extended = refine_extension(payloads[0], mapper, poses, params, set(poses) - anchor_names,
                                    full_ba=o.extend.full_ba, pooled_params=pooled)
    others = []  # (model, holds an old model's images, why no bridge joined it to the main plan)
    for plan, poses, params in components:
        payloads = ClusterPayloads(db, [sorted(poses)], fixed_intrinsics=not mapper.refine_given_intrinsics,
                                   min_inliers=mapper.min_num_matches, labels=[f"N{plan.anchor}"])
        model = refine_with_poses(payloads[0], mapper, poses, params)
        if len(model.images) >= mapper.smallest_model(payloads.sizes[0]):
            apart = (frozenset(main.clusters), frozenset(plan.clusters))
            why = bridge_failures.get(apart) or bridge_failures.get(apart[::-1], "")
            others.append((model, any(n < num_old for n in plan.clusters), why))
    others.sort(key=lambda x: (not x[1], -len(x[0].images)))
    t_ba = time.perf_counter() - t0 - t_merge

    # The result: sparse/0 (extended, or the same files), the workspace's other models that
    # nothing joined, as they were, the other models that new images extended, then the new
    # images' models of their own.
    shutil.rmtree(ext.result, ignore_errors=True)
    ext.result.mkdir(parents=True)
    old_folders = numbered_folders(ext.sparse)
    if extended is None:
        shutil.copytree(old_folders[0], ext.result / "0")
    else:
        write_models([extended], ext.result)
        registration = read_georegistration(old_folders[0])  # the model's frame did not move
        if registration is not None:
            shutil.copy2(old_folders[0] / "georegistration.json", ext.result / "0" / "georegistration.json")
    for k, n in enumerate([n for n in untouched if n != ANCHOR], start=1):
        shutil.copytree(old_folders[n], ext.result / str(k))
    first_own = 1 + len(untouched)
    registrations = georegister_models([m for m, _, _ in others], db, mapper)
    for k, ((model, _, _), registration) in enumerate(zip(others, registrations), start=first_own):
        write_model(model, ext.result / str(k))
        write_georegistration(ext.result / str(k), registration)
    if extended is not None and ext.recorder.enabled:
        ext.recorder.stage("extend")
        log_model(ext.recorder, "world", extended, max_points=ext.recorder.options.record_points)
    num_models = first_own + len(others)
    anchor = olds[0]
    own = [(k, m, why) for k, (m, has_old, why) in enumerate(others, start=first_own) if not has_old]
    others = [m for m, _, _ in others]

    final0 = extended if extended is not None else anchor
    registered_new = sorted(im.name for im in final0.images.values() if im.name in new_set)
    own_new = sorted(im.name for m in others for im in m.images.values() if im.name in new_set)
    warnings = []
    if own:
        where = ", ".join(f"sparse/{k} ({len(m.images)} images)" for k, m, _ in own)
        num = sum(1 for _, m, _ in own for im in m.images.values() if im.name in new_set)
        reasons = "".join(f"; sparse/{k} did not join it as one rigid body: {why}" for k, _, why in own if why)
        warnings.append(f"{num} new image(s) share nothing that aligns with sparse/0 and form "
                        f"{len(own)} model(s) of their own: {where}{reasons}")
    left = len(new_names) - len(registered_new) - len(own_new)
    if left:
        warnings.append(f"{left} new image(s) are in no model")
    summary = {
        "new_images": len(new_names),
        "new_clusters": len(clusters["clusters"]),
        "new_local_models": len(models),
        "merged_into_model": len(merged_in),
        "new_registered_in_model": len(registered_new),
        "new_registered_own_models": len(own_new),
        "old_models_joined": sum(1 for n in main.clusters if 0 < n < num_old),
        "own_models": len(own),
        "num_models": num_models,
        "full_ba": o.extend.full_ba,
        **{k: v for k, v in final0.summary().items()},
        "time_merge_s": round(t_merge, 3), "time_ba_s": round(t_ba, 3),
        "warnings": warnings,
    }
    ext.times.update({"merge": t_merge, "final_ba": t_ba})
    write_json_atomic(ext.dir / "merge.json", {
        "nodes": [{"id": k, "label": n.label, "images": len(n.model.images)} for k, n in enumerate(nodes)],
        "edges": [{"a": u, "b": v, "msd": e["msd"], "common_cameras": e["common_cameras"], "used": e["used"],
                   **({"bridge": True, "inliers": e["inliers"], "rays": e["rays"]} if e.get("bridge") else {})}
                  for (u, v), e in sorted(edges.items())],
        "components": [{"anchor": p.anchor, "clusters": list(p.clusters), "minst": [list(e) for e in p.edges]}
                       for p in plans],
    })
    if extended is None and not others:
        log.warning("extend: no new image could be added to any model")
    ext.recorder.tour("extend", extend_text(summary))
    return summary


def extend(workspace: Path, images: Path | None, options: ExtendRunOptions, command: str | None = None) -> dict:
    """The whole extension as the command line starts it: the workspace taken
    (``WORK/run.lock``), the executor and the recording (``WORK/recording-extend.rrd``) opened,
    :func:`run_extend`, both closed; ``report.json`` says how it ended."""
    workspace = Path(workspace)
    with WorkspaceLock(workspace, command or "sfm.extend"):
        if options.execution.executor == "local":
            start_pool_server()
        start_run(workspace, command, fresh=False)
        rec = options.recording
        recorder = (Recorder(workspace / RECORDING.replace(".rrd", "-extend.rrd"), workspace, rec.spawn, rec)
                    if rec.recording else Recorder.disabled())
        try:
            with recorder, make_executor(options.execution) as executor:
                summary = run_extend(workspace, images, options, executor, recorder)
        except BaseException:
            with contextlib.suppress(Exception):  # the error that stopped the run is the one to report
                finish_run(workspace, "failed")
            raise
        finish_run(workspace, "finished")
        return summary
