"""The guided tour: for each stage a short markdown text that says what the stage does, which
part of the paper it implements (section, equation, Algorithm line), what happened in this run
in numbers, and where to look in the recording.  The stages log it with
:meth:`sfm.viz.recorder.Recorder.tour`; these functions only write text.

Paper references follow the paper's numbering (``help(sfm)``): Eq. 1-2 relative scale, Eq. 3-6
rotation and translation, Eq. 7-9 the MinST as the most probable spanning tree, Eq. 10 the MSE
and Eq. 11 the MSD; Alg. 1 (image clustering) lines 1-2 the partition, 3-5 lost edges, cluster
graph and MaxST, 6-9 expansion along the MaxST, 10-12 random edges until completeness; Alg. 2
(merging) lines 1-2 the cluster graph and its MinST, 3-12 the minimum height tree.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def _spread(values: Sequence[float] | np.ndarray, fmt: str = "{:.0f}") -> str:
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 0:
        return "none"
    return f"{fmt.format(v.min())} / {fmt.format(np.median(v))} / {fmt.format(v.max())} (min / median / max)"


def extract_text(counts: np.ndarray, num_cameras: int, options, bad: list[tuple[str, str]]) -> str:
    """Stage 1: SIFT keypoints and descriptors, keypoint colours."""
    bad_line = f"{len(bad)} file(s) could not be used (e.g. {bad[0][0]}: {bad[0][1]})." if bad else "Every file could be read."
    return f"""## 1. Extract: the keypoints of every image

**What it does.** Finds SIFT keypoints in each image (OpenCV, COLMAP's default thresholds) and
describes each by a RootSIFT vector; reads each keypoint's colour from the colour image; gives
each image a camera with a focal-length prior from its EXIF data.

**Paper.** Not the paper's contribution: its experiments (section 4.1) extract SIFT with VLFeat.
These keypoints' matches make the image graph of section 3.1.1.

**This run.** {len(counts)} images, {num_cameras} camera(s). Keypoints per image: {_spread(counts)};
at most {options.max_num_features} locations per image, each with up to two orientations; images
shrunk to at most {options.max_image_size} px before SIFT. {bad_line}

**In the recording.** `images/<name>`: each image with its keypoints (`…/keypoints`) drawn as
discs of their scale, blue (1 px) to red (32 px).
"""


def match_text(num_images: int, num_pairs: int, num_verified: int, inliers: np.ndarray, min_inliers: int,
               options, drawn: int) -> str:
    """Stage 2: pairs, matching, geometric verification: the image graph."""
    density = 2 * num_verified / max(num_images * (num_images - 1), 1)
    return f"""## 2. Match: the image graph

**What it does.** Chooses image pairs ({options.pairs}), matches their descriptors (ratio test
{options.max_ratio}, mutual check) and keeps the matches that one geometry explains (essential,
fundamental or homography matrix by RANSAC): the verified inliers.

**Paper.** Section 3.1.1: the image graph, one node per image and one edge per overlapping pair,
weighted by its number of verified inlier matches; every later stage works on it.

**This run.** {num_pairs} pairs matched, {num_verified} verified with at least {min_inliers}
inliers: the image graph has {num_images} nodes and {num_verified} edges ({100 * density:.0f}% of
all pairs). Inliers per edge: {_spread(inliers)}.

**In the recording.** `graph/images`: the image graph; an edge's width, colour (blue few, red
many) and label give its inliers. `matches/<a> ~ <b>`: the two images side by side with a line
per inlier match, for {drawn} pairs spread from the strongest to the weakest
(`--record-pairs 0` draws every pair).
"""


def cluster_text(data: dict, cut_fraction: float, num_images: int) -> str:
    """Stage 3: NCut and the MaxST expansion (Alg. 1)."""
    clusters = data["clusters"]
    s_max = data["max_cluster_size"]
    k = len(clusters)
    comps = data.get("num_components", 1)
    k_expected = math.ceil((num_images - len(data.get("isolated_images", []))) / s_max)
    maxst = data.get("maxst", [])
    extra = data.get("extra_edges", [])
    rows = "\n".join(f"| C{c['id']} | {c['core_size']} | {c['size']} | {c['size'] - c['core_size']} | {c['completeness']:.2f} |"
                     for c in clusters)
    if k == 1:
        why = (f"All {num_images} images fit in one cluster (S_max = {s_max}), so nothing is cut: "
               "the map stage reconstructs them at once and there is nothing to merge.")
    else:
        why = (f"K = ceil(n / S_max) = ceil({num_images - len(data.get('isolated_images', []))} / {s_max}) = {k_expected} "
               f"per connected part (the paper's Alg. 1 line 1 writes floor, which makes the mean cluster larger "
               f"than S_max); {comps} connected part(s); parts still above S_max are cut in two again: {k} cores. "
               f"The cut removed {100 * cut_fraction:.1f}% of the edge weight (the inliers of pairs whose images "
               f"ended in different cores); the remaining {100 * (1 - cut_fraction):.1f}% stays inside cores.")
    maxst_line = ", ".join(f"C{a}-C{b} ({w} lost edges)" for a, b, w in maxst) or "none"
    extra_line = ", ".join(f"C{a}-C{b}" for a, b, _ in extra) or "none"
    return f"""## 3. Cluster: cut the image graph, then let neighbours overlap

**What it does.** Cuts the image graph into cores of at most S_max = {s_max} images by
normalized cuts, then copies images across the cut so that neighbouring clusters share images,
which the merge needs to align their models.

**Paper.** Section 3.1, Alg. 1: lines 1-2 the number of clusters K and the NCut partition;
lines 3-5 the lost edges (image edges between two cores), the cluster graph they weigh (one node
per core, an edge's weight = its number of lost image edges) and its maximum spanning tree
(Kruskal); lines 6-9 the strongest lost edges of each MaxST edge added to both clusters (at most
O_max = {data['max_overlap']} per pair); lines 10-12 random non-tree cluster edges added the same way
until every cluster's completeness (its images shared with other clusters / its size) reaches
C = {data['completeness_ratio']}.

**This run.** {why}
MaxST edges: {maxst_line}. Random edges added for completeness: {extra_line}.

| cluster | core | images | copied in (overlap) | completeness |
|---|---|---|---|---|
{rows}

**In the recording.** `graph/images` again, each image coloured by its core's cluster; a ring
around an image in another cluster's colour marks a copy into that cluster (an overlap image);
edges the cut removed are grey. `graph/clusters`: the cluster graph, labelled with each cluster's
size and completeness; edges labelled with their lost edges; the MaxST's edges thick.
"""


def map_text(results: list[dict], num_images: int, direct: bool, options) -> str:
    """Stage 4: incremental SfM of every cluster."""
    rows = []
    for r in results:
        models = r.get("models", [])
        sizes = ", ".join(str(m["registered"]) for m in models) or "none"
        err = f" failed: {r['error']}" if r.get("error") else ""
        rows.append(f"| {r['cluster']} | {r['images']} | {sizes} | "
                    f"{sum(m.get('points', 0) for m in models)} | {r.get('unregistered', 0)}{err} |")
    workers = len({r.get("worker") for r in results if r.get("worker")})
    where = ("one cluster: its models are the final ones (`sparse/`), nothing is merged" if direct
             else f"{len(results)} clusters, run by {workers} worker process(es) in parallel")
    apart = [f"- {r['cluster']}: {line}" for r in results for line in r.get("unjoined", [])]
    apart_text = ("\n\nModels that did not join their cluster's largest as one rigid body "
                  "(`sfm.mapper.joining`), and the step that fell short:\n\n" + "\n".join(apart)) if apart else ""
    return f"""## 4. Map: a local model per cluster, image by image

**What it does.** Incremental SfM in each cluster, as COLMAP does: an initial pair reconstructed
from its essential matrix, then image after image registered by PnP RANSAC, its new tracks
triangulated (a match no third image confirms only in the initial pair), bundle adjustment
(local, and global whenever the model grew by
{round(100 * (options.global_ba_ratio - 1))}%); images that cannot be registered may start a second model.

**Paper.** Section 3.2: "each cluster can be reconstructed using a local SfM approach ... we
choose incremental SfM", in parallel; bounded clusters keep every bundle adjustment small.

**This run.** {num_images} images, {where}.

| cluster | images | registered per model | points | unregistered |
|---|---|---|---|---|
{chr(10).join(rows)}{apart_text}

**In the recording.** On the `registration` timeline, `clusters/<C>/model<m>/`: the cameras as
frustums with their images (`cams/<name>`), a sample of the points (`points`) and the RMS
reprojection error after each bundle adjustment (`ba_rms_px`), one step per registered image;
`clusters/<C>/model<m>/calibration` what the final bundle adjustments refined of each camera (the
distortion and the principal point only where the photos determine them) and why;
`clusters/<C>/model<m>/joins` and `…/unjoined` the earlier models that joined it as one rigid
body, or did not and why; `clusters/<C>/unregistered` lists the images left out and why.
"""


def _edge_words(edge: dict, weight: float) -> str:
    """A merge-tree edge in words: its MSD, or a bridge's inlier rays (``sfm.merge.bridging``)."""
    if edge.get("bridge"):
        return f"bridge: {edge['inliers']} of {edge['rays']} rays"
    return f"MSD {weight:.2g}"


def merge_text(nodes: list[str], edges: dict, plans, options) -> str:
    """Stage 5: cluster graph, MinST, MHT anchor, similarity transforms (Alg. 2)."""
    used = [(u, v, e) for (u, v), e in sorted(edges.items()) if e["used"]]
    dropped = [(u, v, e) for (u, v), e in sorted(edges.items()) if not e["used"]]
    parts = []
    for c, plan in enumerate(plans):
        height = max((len(p) - 1 for p in plan.path.values()), default=0)
        layers = "; ".join(f"layer {layer}: " + ", ".join(nodes[n] for n in plan.clusters
                                                          if plan.layer[n] == layer and n != plan.anchor)
                           for layer in range(1, plan.num_layers + 1))
        minst = ", ".join(f"{nodes[a]}-{nodes[b]} ({_edge_words(edges[(min(a, b), max(a, b))], w)})"
                          for a, b, w in plan.edges) or "none"
        parts.append(f"- Part {c}: {len(plan.clusters)} local model(s); MinST {minst}; anchor "
                     f"**{nodes[plan.anchor]}**; {plan.num_layers} peeling layer(s) ({layers or 'none'}); "
                     f"tree height from the anchor {height}.")
    dropped_line = (", ".join(f"{nodes[u]}-{nodes[v]} (MSD {e['msd']:.2g})" for u, v, e in dropped)
                    if dropped else "none")
    bridges = [(u, v, e) for u, v, e in used if e.get("bridge")]
    bridge_text = ("\n\n**Bridges.** Where the cluster graph fell into parts that no common cameras align, "
                   "a part joins another as one rigid body where its photos see the other's points, on "
                   "PnP's terms (the rotation from a matched pair's essential matrix, the scale and "
                   "translation from the rays; `sfm.merge.bridging`): "
                   + ", ".join(f"{nodes[u]}-{nodes[v]} ({e['inliers']} of {e['rays']} rays)" for u, v, e in bridges)
                   + ". A bridge joins the parts' anchors; the tree takes one only where no common cameras do."
                   if bridges else "")
    return f"""## 5. Merge: every local model into one frame

**What it does.** Aligns every pair of local models that share at least
{options.min_common_cameras} cameras by a similarity transform, weighs the pair by how well the
transform maps their common 3D points, keeps the most accurate tree of alignments and moves every
model along it into the frame of one anchor model.

**Paper.** Section 3.2.1, Eq. 1-6: the relative scale as the median of camera-distance ratios,
then rotation and translation by RANSAC. Section 3.2.2: the cluster graph (Alg. 2 line 1), each
edge weighted by the MSD (Eq. 11: of the two directions' errors of the transformed common 3D
points, Eq. 10, the larger); its minimum spanning tree (Alg. 2 line 2) maximises the probability that every
alignment is right (Eq. 7-9). Section 3.2.3, Alg. 2 lines 3-12: leaves are peeled layer by layer,
each merging into its neighbour, and the last node (or the larger of the last two) is the anchor:
the centre of a minimum height tree, so no model's transform is chained along a long path.

**This run.** {len(nodes)} local models, {len(used)} alignable pairs (edges), {len(dropped)} dropped
above the MSD bound {options.max_msd:g}: {dropped_line}.{bridge_text}
{chr(10).join(parts)}

**In the recording.** `graph/merge`: the cluster graph of the local models, edges labelled
with their MSD (a bridge with its inlier rays), the MinST thick, the anchor large, each node labelled with its layer. On the
`merge_layer` timeline, `merge/<model>`: each local model (its cameras and a sample of its
points, in its cluster's colour) in its own frame at layer 0, moved into the anchor's frame at
the layer it merges in.
"""


def refine_text(models: list[dict], before_points: int, calibration: list[str] = ()) -> str:
    """Stage 6: re-triangulation and the final bundle adjustment of the merged model;
    ``calibration``: what it refined of each camera (``sfm.mapper.self_calibration.SelfCalibration.report``)."""
    first = models[0] if models else {}
    cameras = "".join(f"\n- {line}" for line in calibration)
    cameras = (f"\n\nOf each camera the bundle adjustments refined the focal length, and the distortion and "
               f"the principal point only where the photos determine them:{cameras}" if cameras else "")
    return f"""## 6. Refine: one bundle adjustment over the merged model

**What it does.** With every camera in the anchor's frame, each track starts from its point in
the local model where the most of its observations saw it, moved with that model (a local
model's points fit its own calibration, which the merged camera averages), the other tracks are
triangulated, and a global bundle adjustment refines all cameras and points; bundle adjustment
and re-triangulation alternate until re-triangulation changes almost nothing (COLMAP's global
refinement).

**Paper.** Figure 1's last step: after merging, a final bundle adjustment ("in practice, it is
enough to perform them once").

**This run.** The local models held {before_points} points together (shared ones counted once per
model); the refined model has {first.get('registered', 0)} registered images, {first.get('points', 0)} points,
mean reprojection error {first.get('mean_reprojection_error', float('nan')):.3f} px,
mean track length {first.get('mean_track_length', float('nan')):.2f}.{cameras}
"""


def final_text(models: list[dict], num_images: int, errors: np.ndarray, max_error: float) -> str:
    """Stage 7: the final model(s)."""
    first = models[0] if models else {}
    others = (f" and {len(models) - 1} smaller model(s) ({', '.join(str(m['registered']) for m in models[1:])} images)"
              if len(models) > 1 else "")
    pct = np.percentile(errors, [50, 90]) if len(errors) else [float("nan")] * 2
    ba = first.get("final_ba")
    ba_text = (f"""Its last bundle adjustment: {ba['observations']} observations{f" in {ba['parts']} parts" if ba['parts'] > 1 else ""},
RMS reprojection error {ba['rms_before_px']:.3f} -> {ba['rms_after_px']:.3f} px in {ba['iterations']} iterations
of Levenberg-Marquardt, stopped because: {ba['stopped']}.
""" if ba else "")
    return f"""## 7. The final model

**This run.** {first.get('registered', 0)} of {num_images} images registered in the largest model{others},
{first.get('points', 0)} points, mean reprojection error {first.get('mean_reprojection_error', float('nan')):.3f} px
(per point: median {pct[0]:.2f} px, 90th percentile {pct[1]:.2f} px). Written to `sparse/0` in
COLMAP's format; each point's colour is the mean colour of the keypoints that observe it.
{ba_text}
**In the recording.** `world/points`: the points in their colours; `world/points_error`: the same
points coloured by their mean reprojection error, blue 0 px to red {max_error:g} px (the mapper's
bound); `world/cams/<name>`: each camera's frustum with its image. Drag the `stage` timeline back
to 1 to follow the run from the start.
"""


def extend_text(summary: dict) -> str:
    """``graphsfm extend``: new photos merged into the finished model."""
    return f"""## 8. Extend: new photos merged into the finished model

**What it does.** The new photos are extracted and matched (with one another, and with their most
similar old photos), cut into clusters that overlap the model, reconstructed, and merged into the
model as the fixed anchor; the region of the new photos is then refined, the rest held.

**Paper.** Section 3.1 (Alg. 1: clusters with overlap) and 3.2 (Alg. 2 with the anchor given: the
finished model is the root of every merge path, so its frame and images do not move).

**This run.** {summary.get('new_images', 0)} new images in {summary.get('new_clusters', 0)} cluster(s),
{summary.get('new_registered_in_model', 0)} registered into `sparse/0`
({summary.get('registered', 0)} images, {summary.get('points', 0)} points now),
{summary.get('own_models', 0)} model(s) of their own.

**In the recording.** `graph/extend`: the model (anchor) and the new local models with their MSD
edges; `extend/<model>`: each new local model moved into the model's frame; `world/...`: the
extended model.
"""
