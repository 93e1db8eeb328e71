"""Rerun views of the merge stage (paper section 3.2, Alg. 2): the cluster graph of the local
models weighted by MSD, its MinST, the minimum-height-tree anchor and layers, and every local
model moving into the anchor's frame."""

from __future__ import annotations

import numpy as np

from sfm.viz.frontend import even_sample
from sfm.viz.graphs import draw_graph, graph_layout
from sfm.viz.palette import GREY, cluster_color
from sfm.viz.recorder import Recorder, entity_part

MINST_COLOR = (255, 200, 0)  # Alg. 2 line 2: the MinST's edges
DROPPED_COLOR = (220, 60, 60)  # edges above --max-msd (the paper's dotted edges, Figure 4)


def model_color(label: str) -> tuple[int, int, int]:
    """The colour of cluster ``k`` for local model ``C<k>/<m>``."""
    head = label.split("/")[0]
    return cluster_color(int(head[1:])) if head[1:].isdigit() else GREY


def log_merge(recorder: Recorder, labels: list[str], models: list, edges: dict, plans: list, sims: list[dict],
              stage: str = "merge") -> None:
    """At stage ``stage`` (``merge``; ``extend`` for ``graphsfm extend``, whose anchor is the
    finished model): ``graph/<stage>`` (one node per local model labelled with its layer or
    "anchor", an edge per aligned pair labelled with its MSD, Eq. 11; the MinST's edges thick
    and gold, edges above the MSD bound red) and, on the ``merge_layer`` timeline,
    ``merge/<model>``: each model's points (an even sample, in its cluster's colour) and camera
    centres in its own frame at layer 0, moved by its similarity into the anchor's frame at the
    layer it merges in (Alg. 2 lines 4-11: leaves first, the anchor last); ``<stage>/<model>`` for
    ``extend``."""
    if not recorder.enabled:
        return
    import rerun as rr

    recorder.stage(stage)
    n = len(labels)
    pairs = sorted(edges)
    positions = graph_layout(n, np.array([u for u, _ in pairs], dtype=np.int64),
                             np.array([v for _, v in pairs], dtype=np.int64), np.full(len(pairs), 100.0))
    tree = {(a, b) for plan in plans for a, b, _ in plan.edges}
    layer_label, anchors = {}, set()
    for plan in plans:
        anchors.add(plan.anchor)
        for node in plan.clusters:
            layer_label[node] = "anchor" if node == plan.anchor else f"layer {plan.layer[node]}"
    draw_graph(recorder, f"graph/{stage}", positions, [f"{labels[k]}: {layer_label.get(k, '')}" for k in range(n)],
               node_colors=[model_color(label) for label in labels],
               node_radii=[22.0 if k in anchors else 10.0 for k in range(n)],
               edges=pairs,
               edge_colors=[MINST_COLOR if p in tree else GREY if edges[p]["used"] else DROPPED_COLOR for p in pairs],
               edge_widths=[8.0 if p in tree else 1.5 for p in pairs],
               edge_labels=[f"bridge, {edges[p]['inliers']} rays" if edges[p].get("bridge") else f"MSD {edges[p]['msd']:.2g}"
                            for p in pairs])
    budget = recorder.options.record_points
    for plan, sim in zip(plans, sims):
        for node in plan.clusters:
            label, model = labels[node], models[node]
            entity = f"{stage}/{entity_part(label)}"
            color = model_color(label)
            recorder.set_time("merge_layer", 0)
            recorder.log(entity, rr.Transform3D(translation=[0.0, 0.0, 0.0], mat3x3=np.eye(3)))
            ids = sorted(model.points3D)
            ids = [ids[k] for k in even_sample(len(ids), budget)]
            xyz = np.array([model.points3D[i].xyz for i in ids]).reshape(-1, 3)
            recorder.log(f"{entity}/points", rr.Points3D(xyz, colors=color))
            centres = np.array([im.center for im in model.images.values()]).reshape(-1, 3)
            recorder.log(f"{entity}/cameras", rr.Points3D(centres, colors=color, radii=-4.0))
            if node != plan.anchor:
                s = sim[node]
                recorder.set_time("merge_layer", plan.layer[node])
                recorder.log(entity, rr.Transform3D(translation=s.translation, mat3x3=s.scale * s.rotation))
    recorder.clear_time("merge_layer")
