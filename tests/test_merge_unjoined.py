"""Why merge components stay apart (``sfm.merge.cluster_graph.unjoined_parts``): the report must
name the local models that joined no other and the step that stopped them."""

from __future__ import annotations

from sfm.core.model import Image, Reconstruction
from sfm.merge.cluster_graph import LocalModel, plan_components, unjoined_parts
from sfm.merge.options import MergeOptions


def _model(label: str, names: str) -> LocalModel:
    recon = Reconstruction()
    for k, name in enumerate(names):
        recon.images[k + 1] = Image(image_id=k + 1, name=name, camera_id=1)
    return LocalModel(label, recon)


def _edge(msd: float, used: bool) -> dict:
    return {"msd": msd, "used": used}


def test_each_part_after_the_first_names_its_nearest_model_and_why():
    options = MergeOptions()
    models = [
        _model("C0/0", "abcdef"),   # joined to C1/0 through an edge the plan uses
        _model("C1/0", "defghi"),
        _model("C2/0", "ijk"),      # one image in common with C1/0: below min_common_cameras
        _model("C3/0", "mnopq"),    # shares q with C4/0 alone
        _model("C4/0", "qrstu"),    # shares q with C3/0 only; C5/0 shares r, s, t but its MSD is too large
        _model("C5/0", "rstvw"),
    ]
    edges = {(0, 1): _edge(0.01, True), (4, 5): _edge(0.9, False)}
    plans = plan_components(models, edges)
    assert [sorted(p.clusters) for p in plans][0] == [0, 1]
    parts = {tuple(p["models"]): p for p in unjoined_parts(models, edges, plans, options)}
    assert set(parts) == {("C2/0",), ("C3/0",), ("C4/0",), ("C5/0",)}
    assert parts[("C2/0",)]["nearest"] == "C1/0" and parts[("C2/0",)]["common_images"] == 1
    assert parts[("C2/0",)]["reason"] == ("C2/0 and C1/0 share 1 registered images, fewer than "
                                          f"--min-common-cameras {options.min_common_cameras}")
    assert parts[("C3/0",)]["reason"].startswith("C3/0 and C4/0 share 1 registered images")
    assert parts[("C4/0",)]["nearest"] == "C5/0" and parts[("C4/0",)]["common_images"] == 3
    assert parts[("C4/0",)]["reason"] == f"C4/0 and C5/0 align with an MSD of 0.9, above --max-msd {options.max_msd:g}"
    assert parts[("C5/0",)]["reason"] == f"C5/0 and C4/0 align with an MSD of 0.9, above --max-msd {options.max_msd:g}"


def test_common_images_without_a_similarity_and_with_none_at_all():
    options = MergeOptions()
    models = [_model("C0/0", "abcd"), _model("C1/0", "bcde"), _model("C2/0", "xyz")]
    plans = plan_components(models, {})  # C0/0 and C1/0 share 3 images, yet no edge was found
    parts = unjoined_parts(models, {}, plans, options)
    reasons = {tuple(p["models"]): p["reason"] for p in parts}
    assert [models[k].label for k in plans[0].clusters] == ["C0/0"]
    assert reasons == {("C1/0",): "C1/0 and C0/0 share 3 registered images but no similarity fits them "
                                  "(RANSAC found no consensus)",
                       ("C2/0",): "shares no registered image with any other local model"}


def test_a_part_the_merge_could_not_bridge_says_why_the_rays_did_not_join_it():
    """With the bridging's failures (by the local models of each side, either side first), each
    part's reason ends with why the rays between it and the first part did not join it; a part
    no failure names says only that they did not."""
    options = MergeOptions()
    models = [_model("C0/0", "abcd"), _model("C1/0", "cdef"), _model("C2/0", "xyz"), _model("C3/0", "uvw")]
    edges = {(0, 1): _edge(0.01, True)}
    plans = plan_components(models, edges)
    assert sorted(plans[0].clusters) == [0, 1]
    failures = {(frozenset({0, 1}), frozenset({2})): "too few rays", (frozenset({3}), frozenset({2})): "not this one"}
    reasons = {tuple(p["models"]): p["reason"] for p in unjoined_parts(models, edges, plans, options, failures)}
    rays = "; nor did the rays between its photos and the first part's points join it as one rigid body"
    assert reasons == {("C2/0",): f"shares no registered image with any other local model{rays}: too few rays",
                       ("C3/0",): f"shares no registered image with any other local model{rays}"}
    failures = {(frozenset({3}), frozenset({0, 1})): "no pair"}  # the part received the first's rays
    reasons = {tuple(p["models"]): p["reason"] for p in unjoined_parts(models, edges, plans, options, failures)}
    assert reasons[("C3/0",)].endswith(f"{rays}: no pair")
