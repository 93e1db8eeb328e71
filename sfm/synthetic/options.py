"""Options of the synthetic scenes (``graphsfm synth``) and of the rendered demo scene."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option

SCENES = ("orbit", "street", "aerial")


@dataclass(frozen=True)
class SynthOptions(Options):
    """Options of ``graphsfm synth``: a scene with exact ground truth."""

    scene: str = option(
        "orbit", "orbit, street, aerial: cameras around an object, between two facades, over hills, as a "
        "database of simulated matches; rendered: PNG photos of a facade; survey: JPEG photos of a drone "
        "survey of a town, with EXIF focal length and GPS.", choices=(*SCENES, "rendered", "survey"))
    num_images: int = option(100, "Number of cameras.", min=2)
    observations_per_image: int = option(2000, "Average number of 3D points an image sees.", min=10)
    pixel_noise: float = option(0.5, "Standard deviation of the keypoint noise in pixels per axis.", min=0)
    outlier_ratio: float = option(0.0, "Share of wrong matches among a pair's raw matches.", min=0, max=0.99)
    verified_outlier_ratio: float = option(
        0.03, "Share of wrong matches that survive verification; they lie within 2 px of the epipolar "
        "line, like real RANSAC survivors.", min=0, max=0.49)
    recall_min: float = option(0.80, "Lowest per-pair share of true matches that verification keeps.",
                               above=0, max=1)
    recall_max: float = option(0.95, "Highest such share (each pair draws its recall in between).", above=0, max=1)
    distractor_ratio: float = option(0.2, "Unmatched keypoints per image, relative to its observations.", min=0)
    min_inliers: int = option(15, "A pair with fewer verified inliers gets no two-view geometry.", min=1)
    width: int = option(1280, "Image width in pixels (survey: 1600 x 1200 when width and height are left at "
                        "1280 x 960).", min=16)
    height: int = option(960, "Image height in pixels.", min=16)
    focal: float | None = option(None, "Focal length in pixels (default: the image width).", above=0)
    seed: int = option(0, "The only source of randomness.", min=0)
    twins: int = option(0, "Survey: building designs that stand, identical, in two or three places; street: "
                        "facade stretches that stand, identical, at two places along the street (repeated "
                        "structures); 0: every building unique.", min=0)
    gps_noise_m: float = option(3.0, "Survey: standard deviation in metres of the EXIF GPS position per "
                                "axis.", min=0)
    workers: int = option(0, "Survey: processes that render the photos (0: one per core).", min=0)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.recall_min > self.recall_max:
            raise ValueError(f"recall_min ({self.recall_min}) must not exceed recall_max ({self.recall_max})")


@dataclass(frozen=True)
class RenderOptions:
    """The rendered facade scene (``sfm.synthetic.rendered``): cameras on the arc, image size in
    pixels, focal length in pixels, side of each plane's texture in pixels, and the seed."""

    num_images: int = 24
    width: int = 640
    height: int = 480
    focal: float = 560.0
    texture_size: int = 1024
    seed: int = 0


@dataclass(frozen=True)
class DemoOptions(Options):
    """Options of ``graphsfm demo``: the rendered scene and how finely it is clustered."""

    num_images: int = option(30, "Rendered views of the facade.", min=6)
    max_cluster_size: int = option(12, "S_max of the clustering: small enough that the scene is cut into "
                                   "several clusters and merged.", min=2)
    seed: int = option(0, "Seed of the scene and of every stage.", min=0)
