"""Stage functions that tie the library together: ``merge`` and ``reconstruct``.

``run_merge`` implements the paper's merging (Alg. 2) and global refinement on the local models
``map`` left in ``WORK/clusters``; ``run_reconstruct`` runs every stage in order (extract and
match only when an image folder is given; a workspace whose database came from ``synth`` or
from COLMAP starts at ``cluster``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from backend.memory import return_freed_memory
from sfm.errors import NoModelError
from sfm.mapper.incremental import refine_with_poses
from sfm.mapper.payload import MapperOptions
from sfm.stages.map import ClusterPayloads, failed_clusters_warning, write_models
from sfm.merge.cluster_graph import (
    MergeOptions,
    anchor_from_model,
    build_cluster_graph,
    load_local_models,
    merge_json,
    merged_poses,
    plan_components,
)
from sfm.viz.recorder import Recorder, log_model
from sfm.io.ledger import Ledger, fingerprint, options_record
from sfm.io.workspace import CLUSTERS, DATABASE, MERGE, REPORT, read_json, update_report, write_json_atomic

log = logging.getLogger(__name__)


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
    largest first) and write ``WORK/merge.json``."""
    recorder = recorder or Recorder.disabled()
    workspace = Path(workspace)
    t0 = time.perf_counter()
    ledger = Ledger(workspace)
    opts = {"mapper": options_record(mapper_options), "merge": options_record(options)}
    input_fp = _local_models_fingerprint(workspace)
    if ledger.is_current("merge", opts, input_fp) and (workspace / "sparse" / "0" / "images.bin").exists():
        log.info("merge: %s is current (same options, same local models): skipped", workspace / "sparse")
        return MergeResult(**ledger.record("merge")["result"])
    if ledger.record("merge"):
        log.info("merge: runs again: %s", ledger.why_stale("merge", opts, input_fp))
    ledger.start("merge", opts, input_fp)
    models = load_local_models(workspace)
    if not models:
        raise NoModelError("no local model to merge: every cluster failed to reconstruct")
    edges = build_cluster_graph(models, options, seed=mapper_options.seed)
    plans = plan_components(models, edges)
    write_json_atomic(workspace / MERGE, merge_json(models, edges, plans))
    recorder.stage("merge")
    components = []
    for c, plan in enumerate(plans):
        sims = anchor_from_model(plan, edges)
        recorder.log_cluster_graph([len(m.model.images) for m in models], [(a, b) for a, b, _ in plan.edges],
                                   anchor=plan.anchor, entity=f"graph/clusters/merge{c}" if c else "graph/clusters/merge")
        for node in plan.clusters if recorder.enabled else ():
            recorder.set_time("merge_layer", plan.layer[node])
            moved = models[node].model.copy()
            moved.transform(sims[node])
            log_model(recorder, f"merge/{models[node].label.replace('/', '_')}", moved)
        poses, params = merged_poses(models, plan, sims)
        components.append((plan, poses, params))
    t_merge = time.perf_counter() - t0
    num_local, num_edges = len(models), len(edges)
    del models, edges  # their Python point objects: ~1.7 KB per local point, not needed any more
    return_freed_memory()

    recorder.stage("refine")
    finals = []
    payloads = ClusterPayloads(workspace / DATABASE, [sorted(p) for _, p, _ in components],
                               fixed_intrinsics=not mapper_options.refine_given_intrinsics,
                               min_inliers=mapper_options.min_num_matches, labels=[f"M{c}" for c in range(len(components))])
    for k, (plan, poses, params) in enumerate(components):
        final = refine_with_poses(payloads[k], mapper_options, poses, params)  # read here, held by it alone
        if len(final.images) >= mapper_options.smallest_model(payloads.sizes[k]):
            finals.append(final)
    finals.sort(key=lambda m: -len(m.images))
    written = write_models(finals, workspace / "sparse")
    for k, final in enumerate(finals):
        log_model(recorder, "world" if k == 0 else f"world/model{k}", final)
    t_ba = time.perf_counter() - t0 - t_merge
    fields = {"num_models": len(finals), "num_local_models": num_local, "merge_components": len(plans), "models": written}
    if written:
        fields.update({k: written[0][k] for k in ("registered", "points", "mean_track_length", "mean_reprojection_error")})
    failed = read_json(workspace / REPORT).get("failed_clusters", []) if (workspace / REPORT).exists() else []
    clusters_warnings = read_json(workspace / CLUSTERS).get("warnings", []) if (workspace / CLUSTERS).exists() else []
    fields["warnings"] = clusters_warnings + ([failed_clusters_warning(failed)] if failed else [])  # map's still hold
    if len(finals) > 1:
        msg = (f"{len(finals)} models: the scene splits into {len(finals)} parts that share no aligned cluster pair "
               f"(sizes {', '.join(str(len(f.images)) for f in finals)})")
        log.warning("%s", msg)
        fields["warnings"].append(msg)
    update_report(workspace, fields, {"T_merge": t_merge, "T_BA": t_ba})
    if not finals:
        raise NoModelError("merging left no model")
    log.info("merge: %d local models -> %d models (largest %d images), merge %.1f s, final BA %.1f s",
             num_local, len(finals), len(finals[0].images), t_merge, t_ba)
    result = MergeResult(num_local, num_edges, len(finals), written, round(t_merge, 3), round(t_ba, 3))
    ledger.finish("merge", fingerprint([m["path"] for m in written]), result=asdict(result))
    return result


def _local_models_fingerprint(workspace: Path) -> str:
    """SHA-256 of every file of ``WORK/clusters/C<k>/<m>/``: what ``merge`` reads."""
    root = workspace / "clusters"
    files = sorted(p for p in root.glob("C*/*/*") if p.is_file()) if root.is_dir() else []
    return fingerprint(*[x for p in files for x in (str(p.relative_to(root)), p.read_bytes())])


@dataclass(frozen=True)
class ReconstructOptions:
    """The options of every stage, for ``graphsfm reconstruct`` and :func:`sfm.reconstruct`."""

    extract: object = None
    match: object = None
    cluster: object = None
    mapper: MapperOptions = MapperOptions()
    merge: MergeOptions = MergeOptions()


def run_reconstruct(workspace: Path, images: Path | None, options: ReconstructOptions,
                    executor=None, recorder: Recorder | None = None) -> dict:
    """Every stage in order; returns the report.  Extract and match run when ``images`` is
    given; clustering is skipped (one cluster) when all images fit in one cluster."""
    from sfm.stages.cluster import ClusterOptions, run_cluster
    from sfm.stages.map import run_map

    workspace = Path(workspace)
    recorder = recorder or Recorder.disabled()
    if images is not None:
        from sfm.stages.extract import ExtractOptions, run_extract
        from sfm.stages.match import MatchOptions, run_match

        remote = executor if hasattr(executor, "imap") else None  # Dask: features and matches too
        t0 = time.perf_counter()
        run_extract(Path(images), workspace, options.extract or ExtractOptions(), remote)
        t1 = time.perf_counter()
        run_match(workspace, options.match or MatchOptions(), remote)
        update_report(workspace, {"image_dir": str(images)}, {"T_feat": t1 - t0, "T_match": time.perf_counter() - t1})
    t0 = time.perf_counter()
    cluster_result = run_cluster(workspace, options.cluster or ClusterOptions(), recorder)
    update_report(workspace, {"num_clusters": cluster_result.num_clusters}, {"T_GC": time.perf_counter() - t0})
    map_result = run_map(workspace, options.mapper, recorder, executor)
    if map_result.direct:  # one cluster: its models are the final ones, nothing to merge
        update_report(workspace, {}, {"T_merge": 0.0, "T_BA": 0.0})
    else:
        run_merge(workspace, options.mapper, options.merge, recorder)
    return read_json(workspace / REPORT)
