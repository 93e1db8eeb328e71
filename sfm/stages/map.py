"""The ``map`` stage: local incremental SfM per cluster (paper section 3.2).

Without ``WORK/clusters.json`` every image is in one cluster and the models go to
``WORK/sparse/0``, ``WORK/sparse/1``, ... (largest first).  With it, cluster ``k``'s models go to
``WORK/clusters/C<k>/<m>/`` for the ``merge`` stage.  Each cluster is a self-contained
:class:`sfm.mapper.payload.MapperInput` built from the database and handed to an executor
(``sfm.execution.local``), so clusters run in parallel or on other machines.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from sfm.core import progress
from sfm.core.model import Reconstruction
from sfm.errors import GraphsfmError, InputError, NoModelError
from sfm.execution.local import LocalExecutor, TaskResult
from sfm.io.colmap_model import read_model, write_model
from sfm.io.ledger import Ledger, database_fingerprint, fingerprint, options_record
from sfm.io.report import model_facts, models_fields, update_report
from sfm.io.workspace import CLUSTERS, DATABASE, LOG, image_dir_of, read_georegistration, read_json, write_georegistration
from sfm.mapper.growth import Growth
from sfm.mapper.incremental import reconstruct_incremental
from sfm.mapper.options import MapperOptions
from sfm.mapper.payload import MapperInput
from sfm.stages.georegister import georegister_models
from sfm.stages.payloads import ClusterPayloads
from sfm.viz.mapping import log_cluster_error, log_growth, log_local_model
from sfm.viz.models import log_final_models
from sfm.viz.recorder import Recorder
from sfm.viz.tour import map_text

log = logging.getLogger(__name__)


def write_models(models: list[Reconstruction], folder: Path, registrations: list[dict | None] | None = None) -> list[dict]:
    """Models to ``folder/0``, ``folder/1``, ... (stale numbered folders removed first), each
    with its ``georegistration.json`` when ``registrations`` has one."""
    if folder.exists():
        for old in folder.iterdir():
            if old.is_dir() and old.name.isdigit():
                shutil.rmtree(old)
    out = []
    for m, model in enumerate(models):
        write_model(model, folder / str(m))
        registration = registrations[m] if registrations else None
        write_georegistration(folder / str(m), registration)
        out.append({"path": os.path.abspath(folder / str(m)), **model.summary(),
                    **({"georegistered": True} if registration else {})})
    return out


@dataclass(frozen=True)
class MapResult:
    num_images: int
    num_clusters: int
    models: list[dict]
    clusters: list[dict]
    time_s: float
    direct: bool  # models written to sparse/ (one cluster), not clusters/ for merging


def run_map(workspace: Path, options: MapperOptions, recorder: Recorder | None = None, executor=None) -> MapResult:
    """Incremental SfM of every cluster (or of all images) in ``workspace``, clusters in parallel
    (paper section 3.2).

    Clusters that an earlier run with the same options and input finished (``WORK/stages.json``)
    are reused, not recomputed, so a run killed during ``map`` loses only the clusters in flight."""
    recorder = recorder or Recorder.disabled()
    executor = executor or LocalExecutor()
    workspace = Path(workspace)
    t0 = time.perf_counter()
    db_path = workspace / DATABASE
    if not db_path.exists():
        raise InputError(f"no database at {db_path}: run extract and match (or synth) first")
    clusters, clusters_warnings = None, []
    if (workspace / CLUSTERS).exists():
        clusters_json = read_json(workspace / CLUSTERS)
        clusters = [c["members"] for c in clusters_json["clusters"]]
        clusters_warnings = clusters_json.get("warnings", [])
    # One cluster (all images fit): its models are final and go straight to sparse/.
    direct = clusters is None or len(clusters) == 1
    payloads = ClusterPayloads(db_path, clusters, fixed_intrinsics=not options.refine_given_intrinsics,
                               min_inliers=options.min_num_matches)
    ledger = Ledger(workspace)
    opts, input_fp = options_record(options), fingerprint(database_fingerprint(db_path), clusters)
    done = _finished_clusters(ledger, opts, input_fp, workspace, direct)
    if done is None:
        if ledger.record("map"):
            log.info("map: runs again: %s", ledger.why_stale("map", opts, input_fp))
        for stale in (workspace / "clusters", workspace / "sparse"):  # never mixed with new results
            shutil.rmtree(stale, ignore_errors=True)
        ledger.start("map", opts, input_fp, keep={"clusters": {}})
        done = {}
    recorder.stage("map")
    recorder.image_dir = recorder.image_dir or image_dir_of(workspace)
    per_cluster: list[dict] = [{} for _ in payloads.labels]
    for k, label in enumerate(payloads.labels):
        if label in done:
            per_cluster[k] = {**done[label], "reused": True}
            for m in range(len(done[label]["models"])) if recorder.enabled else ():
                log_local_model(recorder, label, m, read_model(_folder(workspace, direct, label) / str(m)))
    todo = [k for k, label in enumerate(payloads.labels) if label not in done]
    model_names: dict[str, set[str]] = {}  # registered image names of each model written now, by path
    if done:
        log.info("map: %d of %d clusters finished by an earlier run with the same options: skipped (%s)",
                 len(done), len(payloads), ", ".join(sorted(done)))
    max_points = recorder.options.record_points if recorder.enabled else 0
    unregistered: dict[str, int] = {}
    for k, res in map_clusters(payloads, todo, options.for_model(direct), executor, max_points):
        label = payloads.labels[k]
        models, growth = res.value or ([], None)
        registrations = georegister_models(models, db_path, options) if direct else None
        written = write_models(models, _folder(workspace, direct, label), registrations)
        model_names.update({w["path"]: {im.name for im in m.images.values()} for w, m in zip(written, models)})
        per_cluster[k] = {"cluster": label, "images": payloads.sizes[k], "worker": res.worker,
                          "models": written, "error": res.error, "left_out": growth.left_out() if growth else {},
                          "unjoined": growth.unjoined() if growth else []}
        if res.error is None:  # a failed cluster is tried again by the next run
            ledger.data["map"]["clusters"][label] = per_cluster[k]
            ledger.save()
        else:
            log.warning("cluster %s failed: %s", label, res.error)
            log_cluster_error(recorder, label, payloads.names[k], res.error)
        if growth is not None:
            unregistered[label] = log_growth(recorder, growth)
        for m, model in enumerate(models):
            log_local_model(recorder, label, m, model, growth_logged=growth is not None)
    flat = [m for c in per_cluster for m in c["models"]]
    elapsed = time.perf_counter() - t0
    num_images = len({n for names in payloads.names for n in names})  # clusters overlap
    fields = {"executor": executor.name, "scheduler": getattr(executor, "address", None),
              "workers": getattr(executor, "workers", None), "clusters": per_cluster, "num_clusters": len(payloads),
              "num_local_models": len(flat), "warnings": [],  # no stale warning of an earlier run
              "georegistration": read_georegistration(workspace / "sparse" / "0") if direct else None}
    if direct:
        flat.sort(key=lambda m: -m["registered"])
        fields.update(models_fields(flat), merged=False, merge_components=0)
        final_names = [model_names.get(m["path"]) or registered_names(Path(m["path"])) for m in flat]
        fields.update(model_facts(workspace, final_names, per_cluster))
        if len(flat) > 1:
            fields["warnings"] = [several_models_warning([m["registered"] for m in flat], final_names[1:],
                                                         per_cluster[0].get("left_out", {}),
                                                         per_cluster[0].get("unjoined", []))]
    failed = fields["failed_clusters"] = [c["cluster"] for c in per_cluster if c["error"]]
    if recorder.enabled:
        rows = [{**c, "unregistered": unregistered.get(c["cluster"], "?")} for c in per_cluster]
        recorder.tour("map", map_text(rows, num_images, direct, options))
        if direct and flat:
            recorder.stage("final")
            log_final_models(recorder, [read_model(m["path"]) for m in flat], num_images, options)
    if failed:
        fields["warnings"].append(failed_clusters_warning(failed))
    for warning in fields["warnings"]:
        log.warning("%s", warning)
    fields["warnings"] = clusters_warnings + fields["warnings"]  # the cluster stage logged its own
    update_report(workspace, fields, {"map": elapsed})
    ledger.finish("map", fingerprint(input_fp, opts, failed))
    if not flat and failed:  # the failure, not the photos, is why there is no model
        first = next(c for c in per_cluster if c["error"])
        raise GraphsfmError(f"no model could be made: {failed_clusters_warning(failed)}; cluster {first['cluster']}: "
                            f"{first['error']}; details in {workspace / LOG}")
    if not flat:
        raise NoModelError("no model could be made: no image pair could be reconstructed (too few inliers or too small baselines)")
    log.info("map: %d clusters, %d local models, %.1f s", len(payloads), len(flat), elapsed)
    return MapResult(num_images, len(payloads), flat, per_cluster, round(elapsed, 3), direct)


def several_models_warning(sizes: list[int], other_names: list[set[str]], left_out: dict[str, str],
                           unjoined: list[str] = (), shown: int = 3) -> str:
    """The warning of a cluster that gave several models (``sizes``, largest first): why the
    other models' images (``other_names``) are not in the largest, from its ``left_out``
    reasons (:meth:`sfm.mapper.growth.Growth.left_out`), ``shown`` of them by name, and why the
    other models did not join it as a whole (``unjoined``, :meth:`sfm.mapper.growth.Growth.unjoined`)."""
    text = (f"{len(sizes)} models: the images did not form one connected reconstruction "
            f"(sizes {', '.join(map(str, sizes))})")
    others = sorted(n for names in other_names for n in names if n in left_out)
    if others:
        why = ", ".join(f"{n} ({left_out[n]})" for n in others[:shown])
        more = f" and {len(others) - shown} more" if len(others) > shown else ""
        text += f"; not in the largest: {why}{more}"
    return "; ".join([text, *unjoined])


def map_cluster(task: tuple[MapperInput, MapperOptions]) -> list[Reconstruction]:
    """One cluster's payload -> its local models (paper section 3.2: "image clusters are
    distributed into servers"); safe in any worker process."""
    payload, options = task
    with progress.task(payload.label):
        return reconstruct_incremental(payload, options)


def map_cluster_growth(task: tuple[MapperInput, MapperOptions, int]) -> tuple[list[Reconstruction], Growth]:
    """The ``map`` stage's task: :func:`map_cluster`, and with ``max_points > 0`` how the
    models grew (``sfm.mapper.growth``, at most that many points per step) for the recording,
    which this process cannot write; with ``max_points`` 0, only why images were left out."""
    payload, options, max_points = task
    growth = Growth(payload.label, list(payload.names), max(max_points, 0))
    with progress.task(payload.label):
        return reconstruct_incremental(payload, options, growth), growth


def map_clusters(payloads: ClusterPayloads, todo: list[int], options: MapperOptions, executor,
                 max_points: int) -> Iterator[tuple[int, TaskResult]]:
    """``(cluster index, result)`` of every cluster in ``todo`` as it finishes.  The largest go
    first, so the pool is not left waiting on one big straggler; each payload is read only when
    a worker is about to take it.  Results are :func:`map_cluster_growth`'s, wherever the
    cluster ran."""
    order = sorted(todo, key=lambda k: -payloads.sizes[k])
    items = ((payloads[k], options, max_points) for k in order)
    display = MapProgress({payloads.labels[k]: payloads.sizes[k] for k in order})
    with display, progress.listen(display.event):
        for res in executor.map(map_cluster_growth, items, num_items=len(order), ordered=False, errors="return"):
            display.finished(payloads.labels[order[res.index]])
            yield order[res.index], res


class MapProgress:
    """The map stage's progress bar: images registered over all clusters (a finished cluster
    counts all its images), the clusters running with their own count, and the iterations and
    cost of a final BA; events come from the workers (``sfm.core.progress``)."""

    def __init__(self, sizes: dict[str, int]) -> None:
        self.sizes, self.registered, self.done = sizes, dict.fromkeys(sizes, 0), set()
        self.note: dict[str, str] = {}
        self.lock = threading.Lock()
        self.bar = progress.bar(total=sum(sizes.values()), desc="map", unit="img")
        progress.stage("map", f"0 of {len(sizes)} clusters finished")

    def event(self, event: dict, task: str) -> None:
        with self.lock:
            if task not in self.sizes or task in self.done:
                return
            if event["kind"] == "registered":
                self.registered[task] = min(int(event["done"]), self.sizes[task])
                self.note[task] = f"{task} {self.registered[task]}/{self.sizes[task]}"
            elif event["kind"] == "final_ba":
                self.note[task] = f"{task} final BA it {event['done']} cost {event['cost']:.4g}"
            self._show()

    def finished(self, label: str) -> None:
        with self.lock:
            self.done.add(label)
            self.registered[label] = self.sizes[label]
            self.note.pop(label, None)
            progress.stage("map", f"{len(self.done)} of {len(self.sizes)} clusters finished")
            self._show()

    def _show(self) -> None:
        self.bar.n = sum(self.registered.values())
        running = ", ".join(self.note[k] for k in sorted(self.note))
        self.bar.set_postfix_str(f"clusters {len(self.done)}/{len(self.sizes)}" + (f" | {running}" if running else ""),
                                 refresh=False)
        self.bar.refresh()

    def __enter__(self) -> MapProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.bar.close()


def registered_names(folder: Path) -> set[str]:
    """The names of the registered images of the model in ``folder``."""
    return {im.name for im in read_model(folder).images.values()}


def failed_clusters_warning(failed: list[str]) -> str:
    return f"{len(failed)} cluster(s) failed and are left out: {', '.join(failed)}"


def _folder(workspace: Path, direct: bool, label: str) -> Path:
    return workspace / "sparse" if direct else workspace / "clusters" / label


def _finished_clusters(ledger: Ledger, opts: dict, input_fp: str, workspace: Path, direct: bool) -> dict | None:
    """The clusters an earlier ``map`` with these options and this input finished, whose models
    are still on disk (``None``: no such run, start afresh)."""
    rec = ledger.record("map")
    if not rec or rec.get("options") != opts or rec.get("input") != input_fp:
        return None
    out = {}
    for label, entry in (rec.get("clusters") or {}).items():
        folder = _folder(workspace, direct, label)
        if all((folder / str(m) / "images.bin").exists() for m in range(len(entry.get("models", [])))):
            out[label] = entry
    return out
