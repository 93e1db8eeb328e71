"""Options of the ``cluster`` stage (paper section 3.1, Alg. 1)."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option


@dataclass(frozen=True)
class ClusterOptions(Options):
    """Options of the ``cluster`` stage (``graphsfm cluster``); defaults from the authors' code."""

    max_cluster_size: int = option(
        100, "S_max of Alg. 1: the most images in one cluster after expansion, shared images included (what "
        "one local SfM holds); the cores are cut smaller to leave the expansion room.", min=2)
    completeness: float = option(
        0.5, "C of Alg. 1: the completeness eta(i) = sum_j |Ci and Cj| / |Ci| that expansion aims for in "
        "every cluster; a cluster that reaches it takes no more images.", min=0, max=1)
    max_overlap: int = option(50, "O_max of Alg. 1: the most images added between two clusters.", min=1)
    min_overlap: int = option(
        6, "Common images every maximum-spanning-tree edge gets first, so the merge can align its two models "
        "(2 fix a similarity; twice 3 survives half failing to register).", min=2)
    min_inliers: int = option(15, "A pair is an image-graph edge from this many verified inliers.", min=1)
    seed: int = option(0, "Seed of the spectral partition and of the random expansion edges.", min=0)
