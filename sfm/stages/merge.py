"""The ``merge`` stage: ``WORK/clusters/C<k>/<m>`` -> ``WORK/sparse/N`` and ``WORK/merge.json``.

The paper's merging (section 3.2, Alg. 2) and global refinement (Figure 1) on the local models
``map`` left in ``WORK/clusters``: the cluster graph and its merge plan
(``sfm.merge.cluster_graph``), every model moved into its anchor's frame
(``sfm.merge.alignment``) with its points, then the merged model bundle-adjusted and
re-triangulated in turn (``sfm.merge.refinement``).  One model per merge component, largest
first.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from backend.memory import return_freed_memory
from graph.merge_plan import MergePlan
from backend.geometry import rotation_to_quaternion
from sfm.core import progress
from sfm.errors import InputError, NoModelError
from sfm.io.colmap_model import read_model
from sfm.io.database import Database
from sfm.io.ledger import Ledger, files_fingerprint, fingerprint, options_record
from sfm.io.report import model_facts, models_fields, read_report, update_report
from sfm.io.workspace import CLUSTERS, DATABASE, MERGE, image_dir_of, numbered_folders, read_json, write_json_atomic
from sfm.mapper.options import MapperOptions
from sfm.merge.alignment import align_components
from sfm.merge.bridging import bridge_edges, find_bridges
from sfm.merge.cluster_graph import LocalModel, build_cluster_graph, plan_components, unjoined_parts
from sfm.merge.options import MergeOptions
from sfm.merge.refinement import left_out_by_component, refine_with_poses
from sfm.stages.georegister import georegister_models
from sfm.stages.map import failed_clusters_warning, registered_names, write_models
from sfm.stages.payloads import ClusterPayloads
from sfm.viz.merging import log_merge
from sfm.viz.models import log_final_models
from sfm.viz.recorder import Recorder
from sfm.viz.tour import merge_text, refine_text

log = logging.getLogger(__name__)


def load_local_models(workspace: Path) -> list[LocalModel]:
    """Every ``clusters/C<k>/<m>`` model of the workspace, in (k, m) order."""
    root = Path(workspace) / "clusters"
    if not root.is_dir():
        raise InputError(f"no local models in {root}: run cluster and map first")
    out = []
    for cdir in sorted((d for d in root.iterdir() if d.is_dir() and d.name[1:].isdigit()), key=lambda d: int(d.name[1:])):
        for mdir in numbered_folders(cdir):
            out.append(LocalModel(f"{cdir.name}/{mdir.name}", read_model(mdir)))
    return out


def merge_json(models: list[LocalModel], edges: dict, plans: list[MergePlan], options: MergeOptions,
               bridge_failures: dict[tuple[frozenset, frozenset], str] | None = None) -> dict:
    """The content of ``WORK/merge.json``: the cluster graph's nodes and edges (bridges among
    them), each merge component's MinST, anchor and layers, and why the components after the
    first stayed apart (the merge tried to bridge every part; ``bridge_failures`` as
    :func:`bridge_parts` gives them)."""
    return {
        "nodes": [{"id": k, "label": m.label, "images": len(m.model.images), "points": len(m.model.points3D)} for k, m in enumerate(models)],
        "edges": [
            {"a": u, "b": v, "scale": e["sim"].scale, "rotation_qvec": rotation_to_quaternion(e["sim"].rotation).tolist(),
             "translation": e["sim"].translation.tolist(), "msd": e["msd"], "inliers": e["inliers"],
             "common_cameras": e["common_cameras"], "common_points": e["common_points"], "used": e["used"],
             **({"bridge": True, "rays": e["rays"]} if e.get("bridge") else {})}
            for (u, v), e in sorted(edges.items())
        ],
        "components": [
            {"anchor": p.anchor, "clusters": list(p.clusters), "minst": [list(e) for e in p.edges],
             "layers": {str(k): v for k, v in p.layer.items()}, "parent": {str(k): v for k, v in p.parent.items()},
             "path": {str(k): list(v) for k, v in p.path.items()}, "num_layers": p.num_layers}
            for p in plans
        ],
        "unjoined": unjoined_parts(models, edges, plans, options, bridge_failures or {}),
    }


def bridge_parts(database: Path, mapper_options: MapperOptions, options: MergeOptions, plans: list[MergePlan],
                 components: list, finished: list[bool] | None = None,
                 why_not: dict[tuple[frozenset, frozenset], str] | None = None) -> dict:
    """The cluster-graph edges that bridge merge plans no common cameras align, where their
    photos see each other's points (``sfm.merge.bridging``): ``components`` are the plans'
    ``(plan, poses, camera parameters, points)`` in their anchors' frames
    (``sfm.merge.alignment.align_components``), ``finished`` as ``find_bridges`` takes it.
    ``why_not``: receives why each pair of parts tried did not join, by the local models (node
    ids) of each side."""
    progress.stage("merge", f"bridge {len(plans)} parts")
    union = ClusterPayloads(database, [sorted(set().union(*(poses for _, poses, _, _ in components)))],
                            fixed_intrinsics=not mapper_options.refine_given_intrinsics,
                            min_inliers=mapper_options.min_num_matches, labels=["parts"])[0]
    failures: dict[tuple[frozenset, frozenset], str] = {}
    bridges = find_bridges(union, mapper_options, [c[1:] for c in components], seed=mapper_options.seed,
                           finished=finished, why_not=failures)
    if why_not is not None:
        def nodes(parts: frozenset) -> frozenset:
            return frozenset(node for k in parts for node in plans[k].clusters)
        why_not.update({(nodes(a), nodes(b)): why for (a, b), why in failures.items()})
    return bridge_edges(plans, bridges, options.max_msd)


def left_out_names(database: Path, registered: list, min_inliers: int) -> list[list[str]]:
    """For each merge component (``registered``: its image names), the images of the database
    no component holds that its refinement tries to register
    (``sfm.merge.refinement.left_out_by_component``, on the pairs of ``min_inliers`` verified
    inliers or more)."""
    with Database(database, readonly=True) as db:
        images = db.read_images()
        first, second, inliers = db.verified_pairs(min_inliers)
    ids = np.array(sorted(images), np.int64)
    names = [images[i].name for i in ids.tolist()]
    index = {name: k for k, name in enumerate(names)}
    component = np.full(len(ids), -1, np.int64)
    for k, held in enumerate(registered):
        component[[index[name] for name in held]] = k
    taken = left_out_by_component(component, np.searchsorted(ids, first), np.searchsorted(ids, second), inliers,
                                  len(registered))
    return [[names[i] for i in images_of] for images_of in taken]


@dataclass(frozen=True)
class MergeResult:
    num_local_models: int
    num_edges: int
    num_models: int
    models: list[dict]
    time_merge_s: float
    time_ba_s: float


def run_merge(workspace: Path, mapper_options: MapperOptions, options: MergeOptions,
              recorder: Recorder | None = None) -> MergeResult:
    """Merge ``WORK/clusters/C<k>/<m>`` into ``WORK/sparse/N`` (one model per merge component,
    largest first) and write ``WORK/merge.json`` (paper section 3.2, Alg. 2, then Figure 1's
    re-triangulation and final bundle adjustment)."""
    recorder = recorder or Recorder.disabled()
    workspace = Path(workspace)
    t0 = time.perf_counter()
    progress.stage("merge")
    ledger = Ledger(workspace)
    opts = {"mapper": options_record(mapper_options), "merge": options_record(options)}
    input_fp = _local_models_fingerprint(workspace)
    if ledger.is_current("merge", opts, input_fp) and (workspace / "sparse" / "0" / "images.bin").exists():
        log.info("merge: %s is current (same options, same local models): skipped", workspace / "sparse")
        result = MergeResult(**ledger.record("merge")["result"])
        components = len(read_json(workspace / MERGE)["components"]) if (workspace / MERGE).exists() else 1
        update_report(workspace, _report_fields(workspace, result.num_local_models, components, result.models,
                                                [registered_names(Path(m["path"])) for m in result.models]),
                      {"merge": 0.0, "final_ba": 0.0})
        if recorder.enabled:  # the recording of this run still shows the merged model
            recorder.tour("merge", "## 5. Merge\n\nThe merged models in `sparse/` are current (same options, same "
                                   "local models): the merge was not run again; `merge.json` holds its plan.")
            recorder.image_dir = recorder.image_dir or image_dir_of(workspace)
            finals = [read_model(m["path"]) for m in result.models]
            with Database(workspace / DATABASE, readonly=True) as db:
                num_images = db.num_images()
            log_final_models(recorder, finals, num_images, mapper_options)
        return result
    if ledger.record("merge"):
        log.info("merge: runs again: %s", ledger.why_stale("merge", opts, input_fp))
    ledger.start("merge", opts, input_fp)
    models = load_local_models(workspace)
    if not models:
        raise NoModelError("no local model to merge: every cluster failed to reconstruct")
    with progress.bar_for("model_pairs", "merge: align local models", "pair"):
        edges = build_cluster_graph(models, options, seed=mapper_options.seed)
    plans = plan_components(models, edges)
    with Database(workspace / DATABASE, readonly=True) as db:
        nominal = {cam_id: cam.params for cam_id, cam in db.read_cameras().items()}
    components, all_sims = align_components(models, plans, edges, nominal)
    bridge_failures: dict[tuple[frozenset, frozenset], str] = {}
    if len(plans) > 1:
        found = bridge_parts(workspace / DATABASE, mapper_options, options, plans, components, why_not=bridge_failures)
        if found:
            edges.update(found)
            plans = plan_components(models, edges)
            components, all_sims = align_components(models, plans, edges, nominal)
    write_json_atomic(workspace / MERGE, merge_json(models, edges, plans, options, bridge_failures))
    labels = [m.label for m in models]
    local_points = sum(len(m.model.points3D) for m in models)
    if recorder.enabled:
        log_merge(recorder, labels, [m.model for m in models], edges, plans, all_sims)
        recorder.tour("merge", merge_text(labels, edges, plans, options))
    t_merge = time.perf_counter() - t0
    num_local, num_edges = len(models), len(edges)
    del models, edges  # their Python point objects (one per local point): not needed any more
    return_freed_memory()

    recorder.stage("refine")
    finals, calibrations = [], []
    left_out = left_out_names(workspace / DATABASE, [poses for _, poses, _, _ in components], mapper_options.min_num_matches)
    payloads = ClusterPayloads(workspace / DATABASE, [sorted(p) + extra for (_, p, _, _), extra in zip(components, left_out)],
                               fixed_intrinsics=not mapper_options.refine_given_intrinsics,
                               min_inliers=mapper_options.min_num_matches, labels=[f"M{c}" for c in range(len(components))])
    for k, (plan, poses, params, points) in enumerate(components):
        progress.stage("merge", f"final BA of model {k + 1} of {len(components)}")
        with progress.bar_for("final_ba", f"final BA ({len(poses)} images)", "it"):
            calibration: list[str] = []
            final = refine_with_poses(payloads[k], mapper_options, poses, params, calibration, points)  # read here, held by it alone
        if len(final.images) >= mapper_options.smallest_model(payloads.sizes[k]):
            finals.append(final)
            calibrations.append(calibration)
    order = sorted(range(len(finals)), key=lambda k: -len(finals[k].images))
    finals, calibrations = [finals[k] for k in order], [calibrations[k] for k in order]
    registrations = georegister_models(finals, workspace / DATABASE, mapper_options)
    written = write_models(finals, workspace / "sparse", registrations)
    if recorder.enabled:
        recorder.tour("refine", refine_text(written, local_points, calibrations[0] if calibrations else []))
        recorder.image_dir = recorder.image_dir or image_dir_of(workspace)
        log_final_models(recorder, finals, len(payloads.images), mapper_options)
    t_ba = time.perf_counter() - t0 - t_merge
    fields = _report_fields(workspace, num_local, len(plans), written, [{im.name for im in f.images.values()} for f in finals])
    fields["georegistration"] = registrations[0] if registrations else None
    update_report(workspace, fields, {"merge": t_merge, "final_ba": t_ba})
    if not finals:
        raise NoModelError("merging left no model")
    log.info("merge: %d local models -> %d models (largest %d images), merge %.1f s, final BA %.1f s",
             num_local, len(finals), len(finals[0].images), t_merge, t_ba)
    result = MergeResult(num_local, num_edges, len(finals), written, round(t_merge, 3), round(t_ba, 3))
    ledger.finish("merge", fingerprint([m["path"] for m in written]), result=asdict(result))
    return result


def _report_fields(workspace: Path, num_local: int, num_components: int, written: list[dict],
                   final_names: list[set[str]]) -> dict:
    """The report's merge and final-model keys, with the warnings that still hold."""
    fields = {"num_local_models": num_local, "merged": True, "merge_components": num_components,
              **models_fields(written), **model_facts(workspace, final_names)}
    failed = read_report(workspace)["failed_clusters"]
    clusters = read_json(workspace / CLUSTERS) if (workspace / CLUSTERS).exists() else {}
    fields["warnings"] = clusters.get("warnings", []) + ([failed_clusters_warning(failed)] if failed else [])  # still hold
    if len(written) > 1:
        msg = (f"{len(written)} models: the scene splits into {len(written)} parts that share no aligned cluster pair "
               f"(sizes {', '.join(str(m['registered']) for m in written)})")
        log.warning("%s", msg)
        fields["warnings"].append(msg)
    unjoined = read_json(workspace / MERGE).get("unjoined", []) if (workspace / MERGE).exists() else []
    for part in unjoined:  # why each part the merge could not join stayed apart
        msg = f"local models {', '.join(part['models'])} join no other: {part['reason']}"
        log.warning("%s", msg)
        fields["warnings"].append(msg)
    return fields


def _local_models_fingerprint(workspace: Path) -> str:
    """SHA-256 of every file of ``WORK/clusters/C<k>/<m>/``: what ``merge`` reads."""
    return files_fingerprint(workspace / "clusters", "C*/*/*")
