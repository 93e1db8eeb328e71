# %% [markdown]
# # GraphSfM, stage by stage
#
# A walk through graphsfm's Python API on the demo scene: a textured facade rendered from 30
# cameras on an arc (so every answer can be checked against the exact ground truth), cut into
# clusters of at most 12 images, each reconstructed on its own and merged.  Each cell calls one
# stage, prints what it did in numbers and draws a figure, saved beside the workspace
# (`<workspace>_figures/`); each says which part of the paper (Chen et al., "Graph-Based
# Parallel Large Scale Structure from Motion", sections 3.1 and 3.2) it implements.
#
# Run it as a script (`python tools/walkthrough.py [--workspace W] [--num-images N]
# [--max-cluster-size S]`) or open it as a notebook (Jupyter, VS Code: the `# %%` cells).
# The same run's Rerun recording (`graphsfm demo W`, then `rerun W/recording.rrd`) shows the
# same stages interactively.

# %%
from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path

import __main__
import matplotlib

# The parallel stages' worker processes start by running the caller's main script again
# (multiprocessing's rule for scripts, hence the usual ``if __name__ == "__main__":`` guard).
# This script does its work cell by cell at the top level, as a notebook does, so it tells
# multiprocessing there is no script to run again (a notebook kernel has none either).
if __name__ == "__main__" and hasattr(__main__, "__file__"):
    del __main__.__file__

matplotlib.use("Agg")  # figures go to files; a notebook shows them with display() or plt.show()
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import sfm  # noqa: E402
from sfm.evaluation.ground_truth import read_gt_table  # noqa: E402
from sfm.evaluation.metrics import evaluate  # noqa: E402
from sfm.execution.local import LocalExecutor  # noqa: E402
from sfm.io.database import Database  # noqa: E402
from sfm.io.image_files import read_rgb  # noqa: E402
from sfm.synthetic.options import DemoOptions, RenderOptions  # noqa: E402
from sfm.synthetic.rendered import write_rendered_scene  # noqa: E402
from sfm.viz.graphs import graph_layout  # noqa: E402
from sfm.viz.palette import cluster_color  # noqa: E402

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("--workspace", type=Path, default=Path("walkthrough_ws"))
parser.add_argument("--num-images", type=int, default=DemoOptions().num_images)
parser.add_argument("--max-cluster-size", type=int, default=DemoOptions().max_cluster_size)
parser.add_argument("--workers", type=int, default=0)
args, _ = parser.parse_known_args()  # a notebook kernel passes arguments of its own

WORK = args.workspace
FIGURES = WORK.parent / f"{WORK.name}_figures"
EXECUTOR = LocalExecutor(args.workers)  # 0: a worker process per core
shutil.rmtree(WORK, ignore_errors=True)  # a fresh run each time
FIGURES.mkdir(parents=True, exist_ok=True)


def color(k: int):
    """The recording's colour of cluster k, for matplotlib."""
    return np.array(cluster_color(k)) / 255.0


def save(fig, name: str) -> Path:
    path = FIGURES / name
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    print(f"figure: {path}")
    return path


scene = write_rendered_scene(WORK / "scene", RenderOptions(num_images=args.num_images, seed=0))
IMAGES, GT = Path(scene["image_dir"]), read_gt_table(Path(scene["gt_table"]))
print(f"{args.num_images} rendered images in {IMAGES}")

# %% [markdown]
# ## 1. Extract: keypoints
#
# SIFT keypoints and RootSIFT descriptors of every image, with COLMAP's default thresholds, and
# the colour of each keypoint.  Not the paper's contribution (its experiments use VLFeat's SIFT,
# section 4.1), but every later stage is built on these features.

# %%
extract = sfm.run_extract(IMAGES, WORK, sfm.ExtractOptions(), EXECUTOR)
print(f"{extract.num_extracted} images, {extract.mean_keypoints:.0f} keypoints per image on average, "
      f"{extract.num_cameras} camera(s)")
with Database(WORK / "database.db", readonly=True) as db:
    images = db.read_images()
    first = min(images, key=lambda i: images[i].name)
    keypoints = db.read_keypoints(first)
fig, ax = plt.subplots(figsize=(8, 6))
ax.imshow(read_rgb((IMAGES / images[first].name).read_bytes()))
scales = keypoints[:, 2]
dots = ax.scatter(keypoints[:, 0], keypoints[:, 1], s=4 * scales, c=np.log2(scales), cmap="jet", alpha=0.6,
                  linewidths=0)
fig.colorbar(dots, ax=ax, label="log2 of the keypoint's scale (px)")
ax.set_title(f"{images[first].name}: {len(keypoints)} SIFT keypoints, disc size and colour = scale")
ax.axis("off")
save(fig, "1_keypoints.png")

# %% [markdown]
# ## 2. Match: the image graph (section 3.1.1)
#
# Pairs are matched (ratio test, mutual nearest neighbours) and verified by a two-view
# geometry.  The image graph has one node per image and one edge per verified pair, weighted by
# its number of inlier matches: the graph that Alg. 1 cuts.

# %%
match = sfm.run_match(WORK, sfm.MatchOptions(), EXECUTOR)
with Database(WORK / "database.db", readonly=True) as db:
    ids = sorted(db.read_images())
    names = [images[i].name for i in ids]
    node = {image_id: k for k, image_id in enumerate(ids)}
    id1, id2, weights = db.verified_pairs(15)
ei = np.array([node[int(a)] for a in id1])
ej = np.array([node[int(b)] for b in id2])
positions = graph_layout(len(names), ei, ej, weights)  # the recording's layout
print(f"{match.num_pairs_considered} pairs matched, {match.num_verified} verified; "
      f"inliers per edge: median {np.median(weights):.0f}, min {weights.min()}, max {weights.max()}")


def draw_edges(ax, colors=None, widths=None):
    for k, (a, b) in enumerate(zip(ei, ej)):
        strength = weights[k] / weights.max()
        ax.plot(*positions[[a, b]].T, color="0.6" if colors is None else colors[k], alpha=0.2 + 0.8 * strength,
                lw=0.3 + 2.5 * strength if widths is None else widths[k], zorder=1)


def label_edge(ax, pos, a, b, text):
    """An edge's label a third of the way from its first node: crossing edges' labels part."""
    ax.annotate(text, pos[a] + 0.35 * (pos[b] - pos[a]), fontsize=8, ha="center", va="center",
                bbox=dict(boxstyle="round", fc="white", ec="none"))


fig, ax = plt.subplots(figsize=(8, 8))
draw_edges(ax, colors=plt.cm.viridis(weights / weights.max()))
ax.scatter(*positions.T, s=80, c="white", edgecolors="black", zorder=2)
for k, name in enumerate(names):
    ax.annotate(name.split(".")[0], positions[k], fontsize=6, ha="center", va="bottom")
ax.set_title(f"Image graph: {len(names)} images, {len(weights)} verified pairs\n"
             "edge width and colour = verified inliers (section 3.1.1)")
ax.invert_yaxis()
ax.axis("off")
save(fig, "2_image_graph.png")

# %% [markdown]
# ## 3. Cluster: NCut, then expansion along the maximum spanning tree (Alg. 1)
#
# Lines 1-2: K clusters by normalized cuts (graphsfm uses K = ceil(n / S_max), not the paper's
# floor, so that the mean cluster stays within S_max).  Lines 3-5: the image edges the cut lost
# weigh a cluster graph; its maximum spanning tree (Kruskal).  Lines 6-10: along each MaxST
# edge the strongest lost edges are added to both clusters (the overlap images); lines 11-14:
# random non-tree edges until every cluster's completeness reaches C.

# %%
cluster = sfm.run_cluster(WORK, sfm.ClusterOptions(max_cluster_size=args.max_cluster_size))
data = json.loads((WORK / "clusters.json").read_text())
n, s_max = len(names), data["max_cluster_size"]
print(f"K = ceil(n / S_max) = ceil({n} / {s_max}) = {math.ceil(n / s_max)}; NCut made {cluster.num_clusters} "
      f"clusters (a part above S_max is cut in two again)")
print(f"the cut removed {100 * cluster.cut_fraction:.1f}% of the edge weight; MaxST edges "
      f"(cluster pair, lost image edges): {data['maxst']}")
for c in data["clusters"]:
    print(f"  C{c['id']}: core {c['core_size']}, with overlap {c['size']}, completeness {c['completeness']:.2f}")
core_of = np.full(n, -1)
for c in data["clusters"]:
    core_of[[names.index(x) for x in c["core"]]] = c["id"]
fig, ax = plt.subplots(figsize=(8, 8))
same = core_of[ei] == core_of[ej]
draw_edges(ax, colors=[color(core_of[a]) if s else "0.85" for a, s in zip(ei, same)],
           widths=[1.5 if s else 0.3 for s in same])
copies: dict[int, list[int]] = {}  # overlap: image -> the clusters it was copied into
for c in data["clusters"]:
    for x in sorted(set(c["members"]) - set(c["core"])):
        copies.setdefault(names.index(x), []).append(c["id"])
for k, others in copies.items():  # a ring per cluster it joined, in that cluster's colour
    for r, cid in enumerate(others):
        ax.scatter(*positions[k], s=300 + 220 * r, facecolors="none", edgecolors=[color(cid)], lw=2.5, zorder=2)
ax.scatter(*positions.T, s=90, c=[color(k) for k in core_of], edgecolors="black", zorder=3)
handles = [plt.Line2D([], [], marker="o", ls="", color=color(c["id"]), label=f"C{c['id']} core") for c in data["clusters"]]
handles.append(plt.Line2D([], [], marker="o", ls="", mfc="none", color="black", ms=14,
                          label="ring: copied into that cluster (overlap)"))
ax.legend(handles=handles, loc="lower left", fontsize=8)
ax.set_title(f"Clusters: NCut cores of at most {s_max} images (Alg. 1, lines 1-2),\n"
             "grey edges were cut; rings mark overlap images added by the expansion (lines 6-14)")
ax.invert_yaxis()
ax.axis("off")
save(fig, "3_clusters.png")

lost = np.array(data["lost_edges"]).reshape(-1, 3)
centres = graph_layout(len(data["clusters"]), lost[:, 0], lost[:, 1], lost[:, 2])
maxst = {(a, b) for a, b, _ in data["maxst"]}
fig, ax = plt.subplots(figsize=(7, 7))
for a, b, lost in data["lost_edges"]:
    tree = (a, b) in maxst
    ax.plot(*centres[[a, b]].T, color="orange" if tree else "0.7", lw=5 if tree else 1, ls="-" if tree else "--", zorder=1)
    label_edge(ax, centres, a, b, f"{lost}")
for c in data["clusters"]:
    ax.scatter(*centres[c["id"]], s=60 * c["size"], color=color(c["id"]), edgecolors="black", zorder=2)
    ax.annotate(f"C{c['id']}\n{c['core_size']}+{c['size'] - c['core_size']}", centres[c["id"]], ha="center",
                va="center", fontsize=8, zorder=3)
ax.set_title("Cluster graph: edge = lost image edges between two cores (Alg. 1, lines 3-4);\n"
             "thick orange = maximum spanning tree (line 5); node: core + copied images")
ax.invert_yaxis()
ax.axis("off")
save(fig, "4_cluster_graph_maxst.png")

# %% [markdown]
# ## 4. Map: incremental SfM in every cluster (section 3.2)
#
# Each cluster is reconstructed on its own, in parallel worker processes: initial pair, then
# image after image by PnP, triangulation and bundle adjustment.  Every local model has its own
# frame (its own origin, rotation and scale).

# %%
mapped = sfm.run_map(WORK, sfm.MapperOptions(), executor=EXECUTOR)
for c in mapped.clusters:
    print(f"  {c['cluster']}: {c['images']} images -> models of {[m['registered'] for m in c['models']]} images, "
          f"{sum(m['points'] for m in c['models'])} points")
local = {c["cluster"]: sfm.read_model(c["models"][0]["path"]) for c in mapped.clusters if c["models"]}
fig, axes = plt.subplots(1, len(local), figsize=(4 * len(local), 4), squeeze=False)
for ax, (label, model) in zip(axes[0], local.items()):
    xyz = np.array([p.xyz for p in model.points3D.values()])
    rgb = np.array([p.color for p in model.points3D.values()]) / 255.0
    cams = np.array([im.center for im in model.images.values()])
    ax.scatter(xyz[:, 0], xyz[:, 2], s=0.5, c=rgb)
    ax.scatter(cams[:, 0], cams[:, 2], s=25, marker="^", color=color(int(label[1:])), edgecolors="black")
    lo = np.minimum(np.percentile(xyz, 1, axis=0), cams.min(axis=0))[[0, 2]] - 0.3
    hi = np.maximum(np.percentile(xyz, 99, axis=0), cams.max(axis=0))[[0, 2]] + 0.3
    ax.set_xlim(lo[0], hi[0])  # the 1% farthest points left out of the frame
    ax.set_ylim(lo[1], hi[1])
    ax.set_title(f"{label}: {len(model.images)} cameras, {len(model.points3D)} points\n(its own frame, x-z)", fontsize=9)
    ax.set_aspect("equal")
fig.suptitle("Local models, each in its own frame (section 3.2): points in their colours, cameras as triangles",
             y=1.06)
save(fig, "5_local_models.png")

# %% [markdown]
# ## 5. Merge: cluster graph, MinST, anchor (Alg. 2)
#
# Every pair of local models with common cameras gets a similarity transform (Eq. 1-6) and an
# edge weight, the MSD of their common points after the transform (Eq. 10-11).  The minimum
# spanning tree keeps the most accurate alignments (Eq. 7-9, Alg. 2 lines 1-2); peeling its
# leaves layer by layer finds the anchor, the centre of a minimum height tree (lines 3-14),
# and every model is moved into the anchor's frame along its tree path.  Then one bundle
# adjustment refines the merged model (Figure 1).

# %%
if mapped.direct:
    print("one cluster: nothing to merge")
else:
    merge = sfm.run_merge(WORK, sfm.MapperOptions(), sfm.MergeOptions())
    plan = json.loads((WORK / "merge.json").read_text())
    comp = plan["components"][0]
    print(f"{merge.num_local_models} local models, {merge.num_edges} alignable pairs; anchor "
          f"{plan['nodes'][comp['anchor']]['label']}, {comp['num_layers']} layer(s), MinST {comp['minst']}")
    labels = [x["label"] for x in plan["nodes"]]
    edges = [(e["a"], e["b"]) for e in plan["edges"]]
    pos = graph_layout(len(labels), np.array([a for a, _ in edges]), np.array([b for _, b in edges]),
                       np.full(len(edges), 100.0))
    tree = {(min(a, b), max(a, b)) for a, b, _ in comp["minst"]}
    fig, ax = plt.subplots(figsize=(7, 7))
    for e in plan["edges"]:
        a, b = e["a"], e["b"]
        in_tree = (min(a, b), max(a, b)) in tree
        ax.plot(*pos[[a, b]].T, color="orange" if in_tree else ("0.7" if e["used"] else "red"),
                lw=5 if in_tree else 1, ls="-" if in_tree else "--", zorder=1)
        label_edge(ax, pos, a, b, f"{e['msd']:.1e}")
    for k, label in enumerate(labels):
        anchor = k == comp["anchor"]
        layer = "anchor" if anchor else f"layer {comp['layers'].get(str(k), '?')}"
        ax.scatter(*pos[k], s=900 if anchor else 300, marker="*" if anchor else "o",
                   color=color(int(label.split("/")[0][1:])), edgecolors="black", zorder=2)
        ax.annotate(f"{label}\n{layer}", pos[k], xytext=(0, -28), textcoords="offset points", ha="center", fontsize=8)
    ax.set_title("Merge: edge = MSD of the aligned common points (Eq. 10-11);\nthick orange = MinST (Alg. 2, line 2); "
                 "star = anchor of the minimum height tree (lines 3-14)")
    ax.invert_yaxis()
    ax.axis("off")
    save(fig, "6_minst_anchor.png")

# %% [markdown]
# ## 6. The final model, against the ground truth
#
# The merged, refined model (`sparse/0`, COLMAP's format): its reprojection errors, and its
# cameras against the rendered scene's exact poses after a similarity alignment.

# %%
model = sfm.read_model(WORK / "sparse" / "0")
result = evaluate(model, GT)
errors = np.array([p.error for p in model.points3D.values()])
rot = np.array(list(result.rotation_errors_deg.values()))
print(f"{result.num_registered}/{result.num_gt_images} registered, {len(model.points3D)} points, mean reprojection "
      f"error {model.mean_reprojection_error():.3f} px; median rotation error {result.median_rotation_error_deg:.4f} deg; "
      f"AUC@1/5/10 {result.auc[1]:.3f} / {result.auc[5]:.3f} / {result.auc[10]:.3f}")
xyz = np.array([p.xyz for p in model.points3D.values()])
rgb = np.array([p.color for p in model.points3D.values()]) / 255.0
fig, ax = plt.subplots(figsize=(8, 6))
aligned = result.alignment.apply(xyz)
centres = result.alignment.apply(np.array([im.center for im in model.images.values()]))
ax.scatter(aligned[:, 0], aligned[:, 1], s=1, c=rgb)
ax.scatter(centres[:, 0], centres[:, 1], s=30, marker="^", color="black", label="cameras")
lo = np.minimum(np.percentile(aligned[:, :2], 1, axis=0), centres[:, :2].min(axis=0)) - 0.5
hi = np.maximum(np.percentile(aligned[:, :2], 99, axis=0), centres[:, :2].max(axis=0)) + 0.5
ax.set_xlim(lo[0], hi[0])  # the 1% farthest points (badly triangulated ones) left out of the frame
ax.set_ylim(lo[1], hi[1])
ax.set_aspect("equal")
ax.set_xlabel("x (m)")
ax.set_ylabel("y (m, towards the cameras)")
ax.legend()
ax.set_title(f"Final model seen from above (aligned to the ground truth): {len(xyz)} points in their colours")
save(fig, "7_final_model.png")

fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
a1.hist(errors, bins=50, color="tab:blue")
a1.axvline(np.median(errors), color="black", ls="--", label=f"median {np.median(errors):.2f} px")
a1.set_xlabel("mean reprojection error of a point (px)")
a1.set_ylabel("points")
a1.legend()
a2.hist(rot, bins=max(5, min(30, len(rot) // 2)), color="tab:orange")
a2.axvline(np.median(rot), color="black", ls="--", label=f"median {np.median(rot):.3f} deg")
a2.set_xlabel("rotation error of a camera against the ground truth (deg)")
a2.set_ylabel("cameras")
a2.legend()
fig.suptitle("Errors of the final model")
save(fig, "8_error_histograms.png")
print(f"figures in {FIGURES}")
