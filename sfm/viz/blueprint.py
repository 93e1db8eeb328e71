"""The recording's default layout: the guided tour beside the views of every stage.

Sent by :meth:`sfm.viz.recorder.Recorder.close` for what was logged, so opening a recording
shows, without any clicking: on the left the tour (``tour``: each stage's text, what it does,
the paper's section, equation or Algorithm line, this run's numbers); top right the 3D views
(the final model in its colours, the same coloured by reprojection error, the local models
moving into the anchor's frame, each cluster's model growing); bottom right the 2D views (the
image graph, the cluster graph with its MaxST, the merge tree with its MinST and anchor, the
bundle adjustments' RMS error, images with keypoints, inlier matches of pairs).  The time panel
shows the ``stage`` timeline: dragging it replays the run stage by stage.
"""

from __future__ import annotations

from sfm.viz.entities import entity_part

MAX_TABS = 8  # images, pairs or clusters given a view of their own


def default_blueprint(recorder):
    """The layout (module docstring) for the images, pairs, clusters and models a
    :class:`sfm.viz.recorder.Recorder` logged."""
    import rerun.blueprint as rrb

    views3d = []
    if recorder.views["world"]:
        views3d += [
            rrb.Spatial3DView(origin="/world", contents=["+ $origin/**", "- /world/points_error"],
                              name="Final model"),
            rrb.Spatial3DView(origin="/world", contents=["+ $origin/**", "- /world/points"],
                              name="Final model: reprojection error per point"),
        ]
    if "merge" in recorder.texts:
        views3d.append(rrb.Spatial3DView(origin="/merge", name="Merge: local models into the anchor's frame"))
    views3d += [rrb.Spatial3DView(origin=f"/clusters/{label}", name=f"{label}: local model growing")
                for label in recorder.views["clusters"][:MAX_TABS]]
    views2d = [rrb.Spatial2DView(origin="/graph/images", name="Image graph")]
    if "cluster" in recorder.texts:
        views2d.append(rrb.Spatial2DView(origin="/graph/clusters", name="Cluster graph and MaxST"))
    if "merge" in recorder.texts:
        views2d.append(rrb.Spatial2DView(origin="/graph/merge", name="Merge: MSD, MinST, anchor"))
    if recorder.views["clusters"]:
        views2d.append(rrb.TimeSeriesView(origin="/clusters", name="Bundle adjustment RMS (px)"))
    images = recorder.views["images"][:MAX_TABS]
    if images:
        views2d.append(rrb.Grid(*[rrb.Spatial2DView(origin=f"/images/{entity_part(n)}", name=n) for n in images],
                                name="Images and keypoints"))
    pairs = recorder.views["pairs"][:MAX_TABS]
    if pairs:
        views2d.append(rrb.Grid(*[rrb.Spatial2DView(origin=f"/{p}", name=p.split("/", 1)[1]) for p in pairs],
                                name="Inlier matches"))
    right = [rrb.Tabs(*views3d, active_tab=0)] if views3d else []
    right.append(rrb.Tabs(*views2d, active_tab=0))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.TextDocumentView(origin="/tour", contents="$origin", name="Guided tour"),
            rrb.Vertical(*right, row_shares=[3, 2] if len(right) == 2 else None),
            column_shares=[1, 2],
        ),
        rrb.TimePanel(timeline="stage", expanded=True),
    )
