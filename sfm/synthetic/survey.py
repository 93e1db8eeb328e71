"""A drone survey over a town on gentle hills, rendered as JPEG photos with exact ground truth.

The survey stands in for the large aerial captures of section 4: as many photos as asked for,
nadir and oblique, with the EXIF a drone writes (focal length, GPS), over terrain with
buildings.  Nothing scene-sized is ever held: the flight plan is a formula of the image index,
the terrain a sum of sinusoids and a building a function of its grid cell, so any photo is
rendered on its own from ``(options, index)`` alone, by any worker, in any order, in memory
that does not grow with the number of photos.

World frame: x east, y north, z up, metres; its origin is :data:`ORIGIN_WGS84` on WGS84, the
origin of the GPS positions (``sfm.core.geodesy``).  Camera poses are ``cam_from_world``
(``x_cam = R X + t``), OpenCV axes and pixels (centres at integers, principal point at
``((W - 1) / 2, (H - 1) / 2)``), no distortion.

Design:

- Flight plan (:func:`camera_pose`): a rig of two cameras flown in boustrophedon strips east
  and west over a rectangle centred on the origin, :data:`ALTITUDE_M` above the terrain's mean
  level.  At every station the nadir camera (image top along the heading) and the oblique
  camera fire; the oblique camera is tilted :data:`OBLIQUE_TILT_DEG` from nadir and its gimbal
  turns through north, east, south and west at successive stations, so four stations make one
  Maltese cross.  Image ``2 s`` is station ``s``'s nadir photo and ``2 s + 1`` its oblique one.
  Stations are spaced for :data:`FORWARD_OVERLAP` and strips for :data:`SIDE_OVERLAP` of the
  nadir footprint, and the rectangle holds as many stations as the photos need, about as wide
  as long.  Each photo's position and attitude are perturbed (:data:`POSITION_JITTER_M`,
  :data:`ATTITUDE_JITTER_DEG`) by a generator seeded with ``(seed, index)``.
- Terrain (:class:`Terrain`): ``z = h(x, y)``, a sum of four sinusoids of wavelengths 130-520 m
  and a few metres amplitude; its slope is bounded (:data:`SLOPE_BOUND`), so a ray more than
  ten degrees below the horizon meets it once and Newton's method finds that point.
- Buildings (:func:`building_in_cell`): the plane is cut into square cells of
  :data:`CELL_M`; a generator seeded with ``(seed, cell)`` says whether the cell holds a
  building and draws its design (:class:`Design`: footprint, height, flat or gabled roof,
  orientation, colours, texture offsets) and its place in the cell, always inside it, so
  buildings never overlap and the ones a camera may see come from the cells its frustum
  crosses.  Walls reach below the terrain (:data:`BURY_M`) so no gap shows at their foot.
  With ``twins`` designs for a repeated-structures study, each twin design stands, identical
  in its own frame (same geometry, orientation and texture), in two or three cells drawn from
  the survey area (:func:`twin_cells`, a table of at most ``3 * twins`` cells).
- Ray casting (:func:`trace`): for every pixel its ray, the terrain point by Newton's method
  (exact on a grid of rays :data:`GROUND_GRID_RAD` apart; between them the inverse depth, an
  almost affine function of the pixel, is interpolated, off by under a millimetre), then the
  buildings' faces drawn in a z-buffer: each face that looks at the camera is clipped to the
  near plane, projected, and wins the pixels whose rays pass through it (an exact
  point-in-polygon test on the pixel centres) where the ray-plane intersection is nearer.  So
  every pixel shows the surface point its ray meets first: the ground truth is exact.
- Texture (:func:`shade`): surfaces carry one texture, the sum of :data:`OCTAVE_TEXEL_M`'s
  octaves.  Each octave is a seamless tile (:func:`octave_tile`: colour noise, blobs, polygons
  and strokes, blurred below two texels) looked up with bilinear interpolation at surface
  coordinates scaled to its texel size and rotated by its own angle; the scales are not
  commensurate, so the sum does not repeat.  The ground's coordinates are world (x, y); walls
  are indexed by (distance around the building, height), roofs by the building's own (x, y),
  and every design shifts each octave by its own offset.  Anti-aliasing: an octave fades to
  its mean, as a camera's blur would average it, where the pixel's footprint on the surface
  (depth / focal / cos(incidence)) grows from one to two of its texels; so a point looks the
  same, but for the blur its distance brings, in every photo that sees it.
- Shading: a constant sun (:data:`SUN_DIRECTION`) darkens each surface by its normal, the same
  in every photo (no view-dependent effect); a little Gaussian pixel noise, seeded per photo,
  and JPEG quality :data:`JPEG_QUALITY` finish the photo.
- EXIF (:func:`exif_bytes`): Make and Model, the focal length in mm with the focal plane
  resolution of a sensor of :data:`PIXEL_PITCH_MM` pixels (so ``sfm.io.exif`` reads back the
  focal length in pixels exactly), the image size, and the GPS position of the camera centre
  plus Gaussian noise of ``gps_noise_m`` per axis, seeded per photo.

Options (``SynthOptions``): ``num_images``, ``width`` x ``height`` (1600 x 1200 when left at
the database scenes' 1280 x 960), ``focal`` (default: the width, a 53-degree field of view),
``seed``, ``twins`` and ``gps_noise_m``.  Everything else is fixed above, so two runs with the
same options give byte-identical photos.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from functools import lru_cache

import cv2
import numpy as np
from PIL import Image

from backend.geometry import look_at, rotation_from_rotvec, rotation_to_quaternion
from sfm.core.geodesy import wgs84_from_enu
from sfm.synthetic.options import SynthOptions

ORIGIN_WGS84 = (47.0, 8.0, 400.0)  # latitude, longitude (degrees), altitude (m) of the world origin
SURVEY_SIZE = (1600, 1200)  # width, height when SynthOptions' width and height are left at their defaults
ALTITUDE_M = 75.0  # flight height above z = 0, the terrain's mean level
FORWARD_OVERLAP, SIDE_OVERLAP = 0.8, 0.7  # of the nadir footprint, along and across the strips
OBLIQUE_TILT_DEG = 40.0
OBLIQUE_DIRECTIONS = ((0.0, 1.0, "north"), (1.0, 0.0, "east"), (0.0, -1.0, "south"), (-1.0, 0.0, "west"))
POSITION_JITTER_M, ATTITUDE_JITTER_DEG = 0.5, 1.5  # standard deviations per axis

TERRAIN_WAVES = ((520.0, 3.0), (310.0, 1.8), (190.0, 1.0), (130.0, 0.5))  # wavelength, amplitude (m)
SLOPE_BOUND = sum(2 * math.pi * a / lam for lam, a in TERRAIN_WAVES)  # |grad h| never exceeds it
TERRAIN_BOUND = sum(a for _, a in TERRAIN_WAVES)  # |h| never exceeds it
MIN_DEPRESSION_DEG = 10.0  # rays less steep than this below the horizon see the sky

CELL_M = 32.0  # side of a building cell
BUILDING_PROBABILITY = 0.7
FOOTPRINT_M = (7.0, 16.0)  # range of a building's width and depth
HEIGHT_M = (4.0, 25.0)  # range of its wall height
RIDGE_M = (2.0, 4.0)  # height of a gabled roof's ridge above the walls
MAX_HALF_DIAGONAL_M = math.hypot(FOOTPRINT_M[1], FOOTPRINT_M[1]) / 2
BURY_M = SLOPE_BOUND * MAX_HALF_DIAGONAL_M + 0.5  # walls reach this far below the terrain at the centre
MAX_TOP_M = TERRAIN_BOUND + HEIGHT_M[1] + RIDGE_M[1]  # no building is higher
NEAR_M = 0.05  # faces are clipped to this depth in front of the camera
MAX_DEPTH_M = 1500.0  # buildings are looked for up to this depth

TILE = 2048  # side of an octave tile in texels (a power of two)
OCTAVE_TEXEL_M = tuple(0.05 * 2.17**k for k in range(6))  # texel size of each octave
OCTAVE_ANGLE_RAD = tuple(math.radians(137.508 * k + 11.0) for k in range(6))  # golden-angle steps
DETAIL_GAIN = 0.45  # contrast of the summed octaves around a surface's base colour
# Colour directions of the texture's chroma, unit-free RGB: green against purple, ochre against blue.
CHROMA_AXES = np.array([[-0.35, 0.55, -0.25], [0.45, 0.15, -0.55]], np.float32)
SUN_DIRECTION = np.array([0.48, -0.48, 0.735]) / np.linalg.norm([0.48, -0.48, 0.735])  # from the south-east
AMBIENT = 0.45  # shade of a surface facing away from the sun (1 = facing it)
SKY_RGB = (190.0, 205.0, 225.0)
GROUND_RGB = (108.0, 116.0, 84.0)
SURFACE_GAIN = {"ground": 1.0, "sky": 0.0, "walls": 0.6, "roof": 0.8}  # texture contrast by kind of surface
PIXEL_NOISE = 2.0  # standard deviation of the pixel noise, grey levels
JPEG_QUALITY = 92
GROUND_GRID_RAD = 0.005  # the terrain is solved exactly on a grid of rays this far apart and interpolated

PIXEL_PITCH_MM = 0.004  # the sensor's pixel size, for the EXIF focal length in millimetres
SCENE_VERSION = 1  # raise it with any change to the photos: a resumed run then refuses the old ones
CAMERA_MAKE, CAMERA_MODEL = "graphsfm", "survey camera"

_TAG_POSE, _TAG_GPS, _TAG_NOISE, _TAG_CELL, _TAG_TWIN, _TAG_TERRAIN, _TAG_TILE, _TAG_GROUND = range(101, 109)


# ------------------------------------------------------------------------------- the flight plan
@dataclass(frozen=True)
class SurveyPlan:
    """The options that define a survey, resolved (image size and focal length in pixels), and
    the flight plan they give.  Small and hashable: a worker renders any photo from it."""

    num_images: int
    width: int
    height: int
    focal: float
    seed: int
    twins: int
    gps_noise_m: float

    @property
    def stations(self) -> int:
        """Stations of the rig: two photos each (the last one may have only its nadir photo)."""
        return (self.num_images + 1) // 2

    @property
    def base_m(self) -> float:
        """Distance between stations along a strip (the nadir image's height is along it)."""
        return (1 - FORWARD_OVERLAP) * ALTITUDE_M * self.height / self.focal

    @property
    def strip_spacing_m(self) -> float:
        return (1 - SIDE_OVERLAP) * ALTITUDE_M * self.width / self.focal

    @property
    def strips(self) -> int:
        """Strips of the boustrophedon: about as wide as long in total."""
        return max(1, round(math.sqrt(self.stations * self.base_m / self.strip_spacing_m)))

    @property
    def stations_per_strip(self) -> int:
        return -(-self.stations // self.strips)

    @property
    def area_m(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the stations' rectangle, centred on the origin."""
        length = (self.stations_per_strip - 1) * self.base_m
        width = (self.strips - 1) * self.strip_spacing_m
        return -length / 2, length / 2, -width / 2, width / 2

    @property
    def gsd_m(self) -> float:
        """Ground sample distance of a nadir photo on level ground at z = 0."""
        return ALTITUDE_M / self.focal

    @property
    def K(self) -> np.ndarray:
        return np.array(
            [[self.focal, 0, (self.width - 1) / 2], [0, self.focal, (self.height - 1) / 2], [0, 0, 1]]
        )


def survey_plan(opts: SynthOptions) -> SurveyPlan:
    """The survey of ``opts``: its own image size when width and height are left at their
    defaults (:data:`SURVEY_SIZE`), focal length the width when not given."""
    defaults = {f.name: f.default for f in fields(SynthOptions)}
    width, height = opts.width, opts.height
    if (width, height) == (defaults["width"], defaults["height"]):
        width, height = SURVEY_SIZE
    return SurveyPlan(
        opts.num_images, width, height, float(opts.focal or width), opts.seed, opts.twins, opts.gps_noise_m
    )


def image_name(index: int) -> str:
    return f"survey_{index:05d}.jpg"


def _rng(*key: int) -> np.random.Generator:
    """A generator seeded by integers of any sign (cells have negative indices)."""
    return np.random.default_rng([2 * k if k >= 0 else -2 * k - 1 for k in key])


def station_of(plan: SurveyPlan, index: int) -> tuple[int, bool, np.ndarray, np.ndarray]:
    """``(station, oblique, centre, heading)`` of photo ``index`` before its perturbation."""
    station, oblique = divmod(index, 2)
    strip, along = divmod(station, plan.stations_per_strip)
    if strip % 2:
        along = plan.stations_per_strip - 1 - along
    x_min, _, y_min, _ = plan.area_m
    center = np.array([x_min + along * plan.base_m, y_min + strip * plan.strip_spacing_m, ALTITUDE_M])
    heading = np.array([1.0, 0.0, 0.0]) if strip % 2 == 0 else np.array([-1.0, 0.0, 0.0])
    return station, bool(oblique), center, heading


def camera_kind(plan: SurveyPlan, index: int) -> str:
    """``"nadir"`` or ``"oblique-north"`` (east, south, west)."""
    station, oblique, _, _ = station_of(plan, index)
    return f"oblique-{OBLIQUE_DIRECTIONS[station % 4][2]}" if oblique else "nadir"


def camera_pose(plan: SurveyPlan, index: int) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` ``(R, t)`` of photo ``index`` (module docstring, flight plan)."""
    station, oblique, center, heading = station_of(plan, index)
    up = np.array([0.0, 0.0, 1.0])
    if oblique:
        east, north, _ = OBLIQUE_DIRECTIONS[station % 4]
        tilt = math.radians(OBLIQUE_TILT_DEG)
        forward = -math.cos(tilt) * up + math.sin(tilt) * np.array([east, north, 0.0])
        rotation, _ = look_at(center, center + forward, up=up)
    else:
        rotation, _ = look_at(center, center - up, up=heading)
    rng = _rng(plan.seed, _TAG_POSE, index)
    center = center + rng.normal(0.0, POSITION_JITTER_M, 3)
    rotation = rotation_from_rotvec(rng.normal(0.0, math.radians(ATTITUDE_JITTER_DEG), 3)) @ rotation
    return rotation, -rotation @ center


# ------------------------------------------------------------------------------- the terrain
@dataclass(frozen=True, eq=False)
class Terrain:
    """``h(x, y) = sum_j amplitude_j sin(wave_j . (x, y) + phase_j)`` (:data:`TERRAIN_WAVES`,
    directions and phases drawn from the seed)."""

    wave: np.ndarray  # (J, 2) wave vectors, radians per metre
    phase: np.ndarray  # (J,)
    amplitude: np.ndarray  # (J,)

    def height(self, x, y):
        z = np.zeros(np.broadcast(x, y).shape)
        for (kx, ky), phase, amp in zip(self.wave, self.phase, self.amplitude):
            z = z + amp * np.sin(kx * x + ky * y + phase)
        return z

    def height_and_gradient(self, x, y):
        z = gx = gy = 0.0
        for (kx, ky), phase, amp in zip(self.wave, self.phase, self.amplitude):
            arg = kx * x + ky * y + phase
            z = z + amp * np.sin(arg)
            c = amp * np.cos(arg)
            gx, gy = gx + kx * c, gy + ky * c
        return z, gx, gy


@lru_cache(maxsize=4)
def terrain(seed: int) -> Terrain:
    rng = _rng(seed, _TAG_TERRAIN)
    lengths, amplitudes = np.array(TERRAIN_WAVES).T
    angles = rng.uniform(0, 2 * np.pi, len(lengths))
    wave = (2 * np.pi / lengths)[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    return Terrain(wave, rng.uniform(0, 2 * np.pi, len(lengths)), amplitudes)


def terrain_depth(
    ground: Terrain, center: np.ndarray, ray: np.ndarray, depth: np.ndarray, iterations: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Newton's method for the depth ``d`` at which ``center + d * ray`` meets the terrain, from
    ``depth``; ``ray`` (3, ...) are world directions of camera-depth 1, at least
    :data:`MIN_DEPRESSION_DEG` below the horizon, so ``f(d) = z - h(x, y)`` falls monotonically
    (slope below :data:`SLOPE_BOUND`) and has one root.  Returns the depth and the terrain
    gradient at the last iterate."""
    for _ in range(iterations):
        x, y = center[0] + depth * ray[0], center[1] + depth * ray[1]
        z, gx, gy = ground.height_and_gradient(x, y)
        f = center[2] + depth * ray[2] - z
        depth = depth - f / (ray[2] - gx * ray[0] - gy * ray[1])
    return depth, gx, gy


# ------------------------------------------------------------------------------- the buildings
@dataclass(frozen=True)
class Design:
    """A building in its own frame (x, y from the centre of its footprint, z up from the
    terrain at that centre): everything but its place."""

    key: tuple[int, ...]  # (0, i, j): cell (i, j)'s own design; (1, k): twin design k
    width: float  # along its x
    depth: float  # along its y
    height: float  # of the walls
    ridge: float  # of a gabled roof above the walls (0: flat)
    yaw: float  # radians, its x axis from east
    wall_rgb: tuple[float, float, float]
    roof_rgb: tuple[float, float, float]
    offsets: tuple[tuple[tuple[float, float], ...], ...]  # walls, roof: per octave, texels


@dataclass(frozen=True)
class Building:
    design: Design
    center: tuple[float, float, float]  # world point of its frame's origin


@dataclass(frozen=True, eq=False)
class Face:
    """A planar convex polygon of a building in the building's frame, with its outward normal,
    its texture coordinates ``(a, b) = tex_matrix @ X + tex_offset`` and its part (0: walls,
    1: roof)."""

    vertices: np.ndarray  # (n, 3)
    normal: np.ndarray
    tex_matrix: np.ndarray  # (2, 3)
    tex_offset: np.ndarray  # (2,)
    part: int


def _draw_design(rng: np.random.Generator, key: tuple[int, ...]) -> Design:
    width, depth = rng.uniform(*FOOTPRINT_M, 2)
    height = HEIGHT_M[0] + (HEIGHT_M[1] - HEIGHT_M[0]) * rng.random() ** 1.7
    ridge = rng.uniform(*RIDGE_M) if height < 14 and rng.random() < 0.5 else 0.0
    wall = rng.uniform(150, 215) * np.array([1.0, 0.96, 0.88]) + rng.uniform(-10, 10, 3)
    roof = rng.choice([[148.0, 70, 55], [110, 108, 112], [72, 74, 80], [165, 120, 90]])
    roof = roof + rng.uniform(-12, 12, 3)
    offsets = rng.uniform(0, TILE, (2, len(OCTAVE_TEXEL_M), 2))
    return Design(
        key,
        float(width),
        float(depth),
        float(height),
        float(ridge),
        float(rng.uniform(0, np.pi / 2)),
        tuple(wall.tolist()),
        tuple(roof.tolist()),
        tuple(tuple(map(tuple, part)) for part in offsets.tolist()),
    )


@lru_cache(maxsize=256)
def design_faces(design: Design) -> tuple[Face, ...]:
    """The faces of ``design`` in its frame: four walls (pentagons at the gable ends) and a
    flat roof or two roof planes, no floor.  Walls are textured by (distance around the
    building from its south-west corner, height), the roof by the building's (x, y)."""
    hw, hd, h, r = design.width / 2, design.depth / 2, design.height, design.ridge
    corners = np.array([[-hw, -hd], [hw, -hd], [hw, hd], [-hw, hd]])
    faces, around = [], 0.0
    for k in range(4):
        p, q = corners[k], corners[(k + 1) % 4]
        along = (q - p) / np.linalg.norm(q - p)
        verts = [[*p, -BURY_M], [*q, -BURY_M], [*q, h]]
        if r > 0 and k in (1, 3):  # the gable ends: walls across the ridge
            verts.append([*(p + q) / 2, h + r])
        verts.append([*p, h])
        tex = np.array([[along[0], along[1], 0.0], [0.0, 0.0, 1.0]])
        faces.append(
            Face(
                np.array(verts),
                np.array([along[1], -along[0], 0.0]),
                tex,
                np.array([around - along @ p, 0.0]),
                0,
            )
        )
        around += float(np.linalg.norm(q - p))
    roof_tex, roof_offset = np.array([[1.0, 0, 0], [0, 1.0, 0]]), np.zeros(2)
    if r > 0:
        for side in (-1.0, 1.0):
            verts = np.array([[-hw, side * hd, h], [hw, side * hd, h], [hw, 0, h + r], [-hw, 0, h + r]])
            normal = np.array([0.0, side * r, hd]) / math.hypot(r, hd)
            faces.append(Face(verts, normal, roof_tex, roof_offset, 1))
    else:
        verts = np.array([[-hw, -hd, h], [hw, -hd, h], [hw, hd, h], [-hw, hd, h]])
        faces.append(Face(verts, np.array([0.0, 0.0, 1.0]), roof_tex, roof_offset, 1))
    return tuple(faces)


def _survey_cells(plan: SurveyPlan) -> tuple[range, range]:
    """The cells ``i_range`` x ``j_range`` whose centre lies in the nadir photos' coverage (the
    stations' rectangle grown by half a footprint)."""
    x_min, x_max, y_min, y_max = plan.area_m
    half_along, half_across = (
        ALTITUDE_M * plan.height / plan.focal / 2,
        ALTITUDE_M * plan.width / plan.focal / 2,
    )
    i_range = range(
        math.ceil((x_min - half_along) / CELL_M - 0.5), math.floor((x_max + half_along) / CELL_M - 0.5) + 1
    )
    j_range = range(
        math.ceil((y_min - half_across) / CELL_M - 0.5), math.floor((y_max + half_across) / CELL_M - 0.5) + 1
    )
    return i_range, j_range


@lru_cache(maxsize=4)
def twin_cells(plan: SurveyPlan) -> dict[tuple[int, int], int]:
    """Cell -> twin design: each of ``plan.twins`` designs in two or three distinct cells of the
    survey area, drawn from the seed.  Raises ValueError when the area has too few cells."""
    if plan.twins == 0:
        return {}
    i_range, j_range = _survey_cells(plan)
    rng = _rng(plan.seed, _TAG_TWIN)
    counts = rng.integers(2, 4, plan.twins)
    if counts.sum() > len(i_range) * len(j_range):
        raise ValueError(
            f"twins {plan.twins}: the survey area has only {len(i_range) * len(j_range)} building cells "
            f"for {counts.sum()} twin places; fewer twins or more images"
        )
    chosen = rng.choice(len(i_range) * len(j_range), int(counts.sum()), replace=False)
    designs = np.repeat(np.arange(plan.twins), counts)
    return {(i_range[c % len(i_range)], j_range[c // len(i_range)]): int(k) for c, k in zip(chosen, designs)}


@lru_cache(maxsize=64)
def _twin_design(seed: int, k: int) -> Design:
    return _draw_design(_rng(seed, _TAG_TWIN, k), (1, k))


def building_in_cell(plan: SurveyPlan, i: int, j: int) -> Building | None:
    """The building of cell ``(i, j)`` (``[i, i + 1) x [j, j + 1)`` times :data:`CELL_M`), or None;
    its place in the cell is the cell's, its design the cell's own or a twin's."""
    rng = _rng(plan.seed, _TAG_CELL, i, j)
    twin = twin_cells(plan).get((i, j))
    exists = rng.random() < BUILDING_PROBABILITY
    free = CELL_M / 2 - MAX_HALF_DIAGONAL_M - 1.0  # the building stays 1 m inside its cell
    x, y = (np.array([i, j]) + 0.5) * CELL_M + rng.uniform(-free, free, 2)
    if twin is not None:
        design = _twin_design(plan.seed, twin)
    elif exists:
        design = _draw_design(rng, (0, i, j))
    else:
        return None
    return Building(design, (float(x), float(y), float(terrain(plan.seed).height(x, y))))


def buildings_near(
    plan: SurveyPlan, x_range: tuple[float, float], y_range: tuple[float, float]
) -> list[Building]:
    """The buildings of the cells that meet the rectangle ``x_range`` x ``y_range``."""
    found = []
    for j in range(math.floor(y_range[0] / CELL_M), math.floor(y_range[1] / CELL_M) + 1):
        for i in range(math.floor(x_range[0] / CELL_M), math.floor(x_range[1] / CELL_M) + 1):
            building = building_in_cell(plan, i, j)
            if building is not None:
                found.append(building)
    return found


def world_from_building(building: Building) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` taking the building's frame to the world."""
    c, s = math.cos(building.design.yaw), math.sin(building.design.yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array(building.center)


# ------------------------------------------------------------------------------- ray casting
@dataclass
class Trace:
    """What the rays of a grid of pixels meet: per pixel the inverse camera depth (0: sky), the
    surface (a row of the per-surface tables: 0 ground, 1 sky, then each building's walls and
    roof), its texture coordinates ``a``, ``b``, the pixel's footprint on it (metres) and its
    shade."""

    inverse_depth: np.ndarray
    surface: np.ndarray
    a: np.ndarray
    b: np.ndarray
    footprint: np.ndarray
    shade: np.ndarray
    base_rgb: np.ndarray  # (S, 3) per surface
    gain: np.ndarray  # (S,) per surface: contrast of its texture
    offsets: np.ndarray  # (S, octaves, 2) per surface, texels


def _shade_of(normal: np.ndarray) -> float:
    return AMBIENT + (1 - AMBIENT) * max(0.0, float(normal @ SUN_DIRECTION))


def _terrain_at(plan: SurveyPlan, center: np.ndarray, ray: np.ndarray) -> tuple[np.ndarray, ...]:
    """Inverse depth, footprint and shade of the terrain where rays (3, ...) meet it, exactly."""
    depth, gx, gy = terrain_depth(terrain(plan.seed), center, ray, -center[2] / ray[2], 6)
    norm = np.sqrt(1 + gx * gx + gy * gy)
    cos_incidence = np.maximum(
        (gx * ray[0] + gy * ray[1] - ray[2]) / (norm * np.linalg.norm(ray, axis=0)), 0.05
    )
    sun_x, sun_y, sun_z = SUN_DIRECTION
    shade = AMBIENT + (1 - AMBIENT) * np.maximum(0, (sun_z - sun_x * gx - sun_y * gy) / norm)
    return 1 / depth, depth / (plan.focal * cos_incidence), shade


def _ground(
    plan: SurveyPlan,
    rotation: np.ndarray,
    center: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    sky_possible: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Inverse depth, footprint and shade of the terrain at every pixel of the grid ``xs`` x
    ``ys`` (normalised coordinates), and where the sky is (None: nowhere).

    On a whole image, the terrain is solved exactly at every ``step``-th pixel (rays
    :data:`GROUND_GRID_RAD` apart) and the three are interpolated bilinearly; inverse depth is
    an affine function of the pixel on a plane and the terrain is gentle, so the points are off
    by under a millimetre.  The samples sit at pixels ``(j - 1) * step + (step - 1) / 2``, where
    ``cv2.resize`` by ``step`` puts its input's pixel ``j`` (it maps output pixel ``i`` to input
    ``(i + 0.5) / step - 0.5``).
    """
    h, w = len(ys), len(xs)
    step = max(2, int(GROUND_GRID_RAD * plan.focal))
    if sky_possible or h * w < 64 * step * step or not (_regular(xs) and _regular(ys)):
        grid = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], 1.0))
        ray = np.einsum("ji,jrc->irc", rotation, grid)  # R^T (x, y, 1)
        sky = ray[2] > -math.sin(math.radians(MIN_DEPRESSION_DEG)) * np.linalg.norm(ray, axis=0)
        inverse, footprint, shade = _terrain_at(
            plan, center, np.where(sky, np.array([0, 0, -1.0])[:, None, None], ray)
        )
        inverse, footprint = np.where(sky, 0, inverse), np.where(sky, np.inf, footprint)
        return (
            inverse.astype(np.float32),
            footprint.astype(np.float32),
            np.where(sky, 1, shade).astype(np.float32),
            sky if sky.any() else None,
        )
    cols = (np.arange(-(-w // step) + 2) - 1) * step + (step - 1) / 2
    rows = (np.arange(-(-h // step) + 2) - 1) * step + (step - 1) / 2
    grid = np.stack(
        np.broadcast_arrays(
            xs[0] + cols[None, :] * (xs[1] - xs[0]), ys[0] + rows[:, None] * (ys[1] - ys[0]), 1.0
        )
    )
    coarse = np.dstack(_terrain_at(plan, center, np.einsum("ji,jrc->irc", rotation, grid))).astype(np.float32)
    fine = cv2.resize(coarse, (len(cols) * step, len(rows) * step), interpolation=cv2.INTER_LINEAR)
    inverse, footprint, shade = cv2.split(np.ascontiguousarray(fine[step : step + h, step : step + w]))
    return inverse, footprint, shade, None


def _regular(values: np.ndarray) -> bool:
    return len(values) >= 2 and np.allclose(np.diff(values), values[1] - values[0])


def _clip_near(points: np.ndarray) -> np.ndarray:
    """The part of a convex polygon (camera coordinates, (n, 3)) at depth >= :data:`NEAR_M`."""
    out = []
    for k in range(len(points)):
        p, q = points[k], points[(k + 1) % len(points)]
        if p[2] >= NEAR_M:
            out.append(p)
        if (p[2] >= NEAR_M) != (q[2] >= NEAR_M):
            out.append(p + (NEAR_M - p[2]) / (q[2] - p[2]) * (q - p))
    return np.array(out)


def _frustum_box(
    center: np.ndarray, corner_rays: np.ndarray
) -> tuple[tuple[float, float], tuple[float, float]]:
    """The (x, y) box of where the corner rays pass through the heights buildings occupy."""
    points = [center[:2]] if center[2] < MAX_TOP_M else []
    for ray in corner_rays:
        for z in (MAX_TOP_M, -TERRAIN_BOUND - BURY_M):
            depth = (z - center[2]) / ray[2] if ray[2] < 0 else MAX_DEPTH_M
            points.append(center[:2] + min(max(depth, 0.0), MAX_DEPTH_M) * ray[:2])
    points = np.array(points)
    return (points[:, 0].min(), points[:, 0].max()), (points[:, 1].min(), points[:, 1].max())


def trace(
    plan: SurveyPlan, rotation: np.ndarray, translation: np.ndarray, us: np.ndarray, vs: np.ndarray
) -> Trace:
    """What the rays of the pixel grid ``us`` (columns, ascending) x ``vs`` (rows) of a camera
    ``cam_from_world = (rotation, translation)`` of ``plan`` meet first (module docstring).

    The ground's texture coordinates are world (x, y) less the camera's (x, y) rounded down, and
    that shift goes into the ground's octave offsets instead: small coordinates keep float32
    precise and fit OpenCV's 16-bit texel indices."""
    us, vs = np.asarray(us, np.float64), np.asarray(vs, np.float64)
    K = plan.K
    xs, ys = (us - K[0, 2]) / plan.focal, (vs - K[1, 2]) / plan.focal
    center = -rotation.T @ translation
    corners = np.array([[x, y, 1.0] for x in (xs[0], xs[-1]) for y in (ys[0], ys[-1])]) @ rotation
    # The rays steeper than the sky's limit form a convex cone: no corner in the sky, no sky.
    sky_possible = bool(
        np.any(corners[:, 2] > -math.sin(math.radians(MIN_DEPRESSION_DEG)) * np.linalg.norm(corners, axis=1))
    )
    inverse, footprint, shade, sky = _ground(plan, rotation, center, xs, ys, sky_possible)
    xg, yg = xs.astype(np.float32)[None, :], ys.astype(np.float32)[:, None]
    shift = np.floor(center[:2])
    with np.errstate(divide="ignore", invalid="ignore"):  # the sky's inverse depth is 0
        depth = 1 / inverse
        a, b = (
            (np.float32(rotation[0, i]) * xg + np.float32(rotation[1, i]) * yg + np.float32(rotation[2, i]))
            * depth
            + np.float32(center[i] - shift[i])
            for i in range(2)
        )
    surface = np.zeros(inverse.shape, np.int32)
    if sky is not None:
        a[sky], b[sky], surface[sky] = 0, 0, 1
    ground_offsets = _rng(plan.seed, _TAG_GROUND).uniform(0, TILE, (len(OCTAVE_TEXEL_M), 2))
    for k, (texel, angle) in enumerate(zip(OCTAVE_TEXEL_M, OCTAVE_ANGLE_RAD)):
        c, s = math.cos(angle) / texel, math.sin(angle) / texel
        ground_offsets[k] = (
            ground_offsets[k] + [c * shift[0] - s * shift[1], s * shift[0] + c * shift[1]]
        ) % TILE
    base, offsets = [GROUND_RGB, SKY_RGB], [ground_offsets, np.zeros_like(ground_offsets)]
    gain = [SURFACE_GAIN["ground"], SURFACE_GAIN["sky"]]

    x_range, y_range = _frustum_box(center, corners)
    for building in buildings_near(plan, x_range, y_range):
        world_r, world_t = world_from_building(building)
        first = len(base)
        base += [building.design.wall_rgb, building.design.roof_rgb]
        gain += [SURFACE_GAIN["walls"], SURFACE_GAIN["roof"]]
        offsets += [np.array(building.design.offsets[0]), np.array(building.design.offsets[1])]
        for face in design_faces(building.design):
            normal = world_r @ face.normal
            vertices = face.vertices @ world_r.T + world_t
            if normal @ (center - vertices[0]) <= 1e-9:
                continue  # seen from behind: the building's other faces hide it
            cam = _clip_near(vertices @ rotation.T + translation)
            if len(cam) < 3:
                continue
            proj = cam[:, :2] / cam[:, 2:]
            c0, c1 = np.searchsorted(xs, proj[:, 0].min()), np.searchsorted(xs, proj[:, 0].max(), "right")
            r0, r1 = np.searchsorted(ys, proj[:, 1].min()), np.searchsorted(ys, proj[:, 1].max(), "right")
            if c0 >= c1 or r0 >= r1:
                continue
            window = (slice(r0, r1), slice(c0, c1))
            buffers = (
                inverse[window],
                surface[window],
                a[window],
                b[window],
                footprint[window],
                shade[window],
            )
            _draw_face(
                face,
                (world_r, world_t),
                first + face.part,
                proj,
                (rotation, translation, plan.focal),
                xg[:, window[1]],
                yg[window[0], :],
                buffers,
            )
    return Trace(
        inverse,
        surface,
        a,
        b,
        footprint,
        shade,
        np.array(base, np.float32),
        np.array(gain, np.float32),
        np.array(offsets, np.float32),
    )


def _draw_face(
    face: Face,
    building_pose: tuple[np.ndarray, np.ndarray],
    surface_row: int,
    proj: np.ndarray,
    camera: tuple[np.ndarray, np.ndarray, float],
    x: np.ndarray,
    y: np.ndarray,
    buffers: tuple[np.ndarray, ...],
) -> None:
    """Z-buffer one face of a building (``building_pose``: world from building) into a window of
    the grid: ``x``, ``y`` are the window's normalised coordinates and ``buffers`` the trace's
    arrays over it.  The pixels whose rays pass through the face's projected polygon ``proj``
    and meet it nearer than what is there take its depth, texture coordinates (in the building's
    frame: small, like the ground's camera-relative ones), footprint and shade.  ``camera``:
    ``cam_from_world`` rotation and translation, and the focal length in pixels."""
    world_r, world_t = building_pose
    rotation, translation, focal = camera
    normal, vertex = world_r @ face.normal, world_r @ face.vertices[0] + world_t
    inverse, surface, a, b, footprint, shade = buffers
    signed_area = np.sum(proj[:, 0] * np.roll(proj[:, 1], -1) - np.roll(proj[:, 0], -1) * proj[:, 1])
    inside = np.ones(inverse.shape, bool)
    for k in range(len(proj)):
        (x0, y0), (x1, y1) = proj[k], proj[(k + 1) % len(proj)]
        edge = np.float32(x1 - x0) * (y - np.float32(y0)) - np.float32(y1 - y0) * (x - np.float32(x0))
        inside &= edge * np.float32(signed_area) >= 0
    if not inside.any():
        return
    # The plane n_c . X_c = d_c in camera coordinates; on the pixel's ray X_c = z (x, y, 1).
    normal_cam = rotation @ normal
    plane_d = float(normal_cam @ (rotation @ vertex + translation))
    inv = (
        np.float32(normal_cam[0] / plane_d) * x
        + np.float32(normal_cam[1] / plane_d) * y
        + np.float32(normal_cam[2] / plane_d)
    )
    nearer = inside & (inv > inverse)
    if not nearer.any():
        return
    # Texture coordinates: affine in the world point C + z R^T (x, y, 1), so perspective-correct.
    tex = face.tex_matrix @ world_r.T  # world point -> (a, b), plus the offset below
    at_center = tex @ (-rotation.T @ translation) + face.tex_offset - tex @ world_t
    along = tex @ rotation.T  # (a, b) per unit of the camera-frame ray
    depth = 1 / inv
    for out, k in ((a, 0), (b, 1)):
        value = (np.float32(along[k, 0]) * x + np.float32(along[k, 1]) * y + np.float32(along[k, 2])) * depth
        np.copyto(out, value + np.float32(at_center[k]), where=nearer)
    np.copyto(inverse, inv, where=nearer)
    surface[nearer] = surface_row
    shade[nearer] = _shade_of(normal)
    cos_incidence = np.maximum(np.abs(inv * np.float32(plane_d)) / np.sqrt(x * x + y * y + 1), 0.05)
    np.copyto(footprint, depth / (np.float32(focal) * cos_incidence), where=nearer)


def hit_points(
    plan: SurveyPlan, rotation: np.ndarray, translation: np.ndarray, pixels: np.ndarray
) -> np.ndarray:
    """World points (n, 3) the rays of ``pixels`` (n, 2; NaN for the sky) meet first, cast one
    by one (the renderer's own ray casting, for tests of the ground truth)."""
    center = -rotation.T @ translation
    out = np.full((len(pixels), 3), np.nan)
    for n, (u, v) in enumerate(np.asarray(pixels, np.float64)):
        hit = trace(plan, rotation, translation, np.array([u]), np.array([v]))
        if hit.surface[0, 0] != 1:
            ray = rotation.T @ np.array(
                [(u - plan.K[0, 2]) / plan.focal, (v - plan.K[1, 2]) / plan.focal, 1.0]
            )
            out[n] = center + ray / float(hit.inverse_depth[0, 0])
    return out


# ------------------------------------------------------------------------------- texture and shading
def _periodic_noise(rng: np.random.Generator, cell: int, channels: int) -> np.ndarray:
    """Smooth noise of blob size ``cell`` texels on a seamless TILE x TILE tile (white noise on a
    coarse torus, wrap-padded, upsampled by cubic interpolation and cropped)."""
    assert TILE % cell == 0, "the tile must hold a whole number of cells"
    m, pad = TILE // cell, 3
    coarse = np.pad(
        rng.standard_normal((m, m, channels)).astype(np.float32),
        ((pad, pad), (pad, pad), (0, 0)),
        mode="wrap",
    )
    size = (m + 2 * pad) * cell
    fine = cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC).reshape(size, size, channels)
    return fine[pad * cell : pad * cell + TILE, pad * cell : pad * cell + TILE]


@lru_cache(maxsize=12)
def octave_tile(seed: int, octave: int) -> np.ndarray:
    """One octave's seamless RGB tile (uint8, mean 128): colour noise of two blob sizes, then
    discs, rotated rectangles, triangles and strokes of 2-10 texels in light and dark colours
    (blobs and corners for SIFT at every scale), blurred (sigma 0.8 texel) so that it holds no
    detail finer than about two texels.  Shapes are drawn on the tile grown by a wrapped border,
    a shape near an edge once more across it, and never clipped (OpenCV's anti-aliasing differs
    at a clipped edge, which would leave a seam)."""
    rng = _rng(seed, _TAG_TILE, octave)
    lum = _periodic_noise(rng, 32, 1) * 30 + _periodic_noise(rng, 8, 1) * 26
    chroma_scale = 4.0 + 3.0 * octave  # hue varies more over large areas than in fine detail
    chroma = (_periodic_noise(rng, 64, 2) * chroma_scale + _periodic_noise(rng, 16, 2) * 3) @ CHROMA_AXES
    reach = 12.0  # no shape reaches farther from its centre
    pad = 2 * int(reach)
    canvas = np.pad(
        np.clip(128 + lum + chroma, 0, 255).astype(np.uint8), ((pad, pad), (pad, pad), (0, 0)), mode="wrap"
    )
    n = TILE * TILE // 160
    kinds = rng.integers(0, 4, n)  # disc, rectangle, triangle, stroke
    centers = rng.uniform(0, TILE, (n, 2))
    radii = rng.uniform(1.5, 5.0, n)
    angle = rng.uniform(0, 2 * np.pi, (n, 1))
    half = rng.uniform(1.0, 4.5, (n, 2))
    thickness = rng.integers(1, 3, n)
    colors = np.clip(
        128
        + rng.choice([-1.0, 1.0], (n, 1)) * rng.uniform(35, 95, (n, 1))
        + rng.normal(0, 12, (n, 2)) @ CHROMA_AXES,
        0,
        255,
    )
    corners = np.sort(rng.uniform(0, 2 * np.pi, (n, 3)), axis=1)
    u = np.stack([np.cos(angle), np.sin(angle)], -1)  # (n, 1, 2)
    v = np.stack([-np.sin(angle), np.cos(angle)], -1)
    hx, hy = half[:, :1, None], half[:, 1:, None]
    rectangles = np.concatenate([hx * u + hy * v, hx * u - hy * v, -hx * u - hy * v, -hx * u + hy * v], 1)
    triangles = radii[:, None, None] * np.stack([np.cos(corners), np.sin(corners)], -1)
    strokes = (2 * half[:, :1, None] + 1) * np.concatenate([u, -u], 1)  # 3-10 texels from the centre
    shift = 4  # sub-texel positions, in 1/16 texel
    one = 1 << shift
    at = centers + pad
    fixed = [
        np.round((shape + at[:, None, :]) * one).astype(np.int32)
        for shape in (rectangles, triangles, strokes)
    ]
    disc_centers = np.round(at * one).astype(np.int32).tolist()
    disc_radii = np.round(radii * one).astype(np.int32).tolist()
    near_edge = ((centers < reach) | (centers > TILE - reach)).any(axis=1).tolist()
    for k, kind in enumerate(kinds.tolist()):
        color = colors[k].tolist()
        copies = [(0, 0)]
        if near_edge[k]:
            cx, cy = centers[k]
            copies = [
                (dx, dy)
                for dx in [0] + ([TILE] if cx < reach else []) + ([-TILE] if cx > TILE - reach else [])
                for dy in [0] + ([TILE] if cy < reach else []) + ([-TILE] if cy > TILE - reach else [])
            ]
        for dx, dy in copies:
            if kind == 0:
                x, y = disc_centers[k]
                cv2.circle(canvas, (x + dx * one, y + dy * one), disc_radii[k], color, -1, cv2.LINE_AA, shift)
                continue
            points = fixed[kind - 1][k]
            if dx or dy:
                points = points + np.array([dx * one, dy * one], np.int32)
            if kind == 3:
                cv2.line(
                    canvas,
                    points[0].tolist(),
                    points[1].tolist(),
                    color,
                    int(thickness[k]),
                    cv2.LINE_AA,
                    shift,
                )
            else:
                cv2.fillConvexPoly(canvas, points, color, cv2.LINE_AA, shift)
    blurred = np.ascontiguousarray(
        cv2.GaussianBlur(canvas.astype(np.float32), (0, 0), 0.8)[pad:-pad, pad:-pad]
    )
    return cv2.add(
        blurred, tuple(128.0 - m for m in cv2.mean(blurred)), dtype=cv2.CV_8U
    )  # rounded, saturated


def _per_pixel(surface: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A function from a per-surface table ((S,) or (S, 3)) to its float32 values at every pixel
    of ``surface``: ``cv2.LUT`` on 8-bit indices when there are at most 256 surfaces (several
    times faster than numpy's gather), else ``np.take``."""
    if surface.max() >= 256:
        return lambda table: np.take(table, surface, axis=0).astype(np.float32)
    index = surface.astype(np.uint8)
    indices: dict[int, np.ndarray] = {}

    def lookup(table: np.ndarray) -> np.ndarray:
        lut = np.zeros((1, 256, *table.shape[1:]), np.float32)
        lut[0, : len(table)] = table
        channels = table.shape[1] if table.ndim == 2 else 1
        if channels not in indices:
            indices[channels] = index if channels == 1 else cv2.merge([index] * channels)
        return cv2.LUT(indices[channels], lut)

    return lookup


def shade(plan: SurveyPlan, traced: Trace) -> np.ndarray:
    """Linear RGB (float32, h x w x 3) of a trace: each surface's base colour plus the octaves
    that its footprint resolves, times its shade (module docstring, texture).  Texel indices are
    OpenCV's fixed-point maps (``cv2.convertMaps``), wrapped into the tile by a bitwise and."""
    h, w = traced.surface.shape
    detail = np.zeros((h, w, 3), np.float32)
    weight_sum = np.zeros((h, w), np.float32)
    fp_min, fp_max = float(traced.footprint.min()), float(traced.footprint.max())  # the sky's is inf
    per_pixel = _per_pixel(traced.surface)
    for k, (texel, angle) in enumerate(zip(OCTAVE_TEXEL_M, OCTAVE_ANGLE_RAD)):
        if fp_min >= 2 * texel:
            continue  # finer than every pixel's footprint
        c, s = math.cos(angle) / texel, math.sin(angle) / texel
        u = cv2.addWeighted(traced.a, c, traced.b, -s, 0.0)
        v = cv2.addWeighted(traced.a, s, traced.b, c, 0.0)
        u += per_pixel(traced.offsets[:, k, 0])
        v += per_pixel(traced.offsets[:, k, 1])
        texel_index, fraction = cv2.convertMaps(u, v, cv2.CV_16SC2)
        np.bitwise_and(texel_index, TILE - 1, out=texel_index)
        tex = cv2.remap(
            octave_tile(plan.seed, k), texel_index, fraction, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
        )
        if fp_max <= texel:
            cv2.accumulate(tex, detail)
            weight_sum += 1
        else:
            weight = np.clip(2 - traced.footprint * np.float32(1 / texel), 0, 1)
            cv2.accumulateProduct(tex.astype(np.float32), cv2.merge([weight] * 3), detail)
            weight_sum += weight
    detail -= 128 * weight_sum[..., None]
    detail *= per_pixel(DETAIL_GAIN * traced.gain)[..., None]
    detail += per_pixel(traced.base_rgb)
    detail *= traced.shade[..., None]
    return detail


# ------------------------------------------------------------------------------- photos
def render(plan: SurveyPlan, index: int) -> np.ndarray:
    """Photo ``index`` as RGB uint8 (h x w x 3), with its pixel noise."""
    rotation, translation = camera_pose(plan, index)
    rgb = shade(plan, trace(plan, rotation, translation, np.arange(plan.width), np.arange(plan.height)))
    noise = np.empty_like(rgb)
    cv2.setRNGSeed(int(_rng(plan.seed, _TAG_NOISE, index).integers(1, 2**31 - 1)))
    cv2.randn(noise, 0.0, PIXEL_NOISE)
    rgb += noise
    return np.clip(rgb + 0.5, 0, 255).astype(np.uint8)


def _dms(degrees: float) -> tuple[float, float, float]:
    whole = math.floor(degrees)
    minutes = math.floor((degrees - whole) * 60)
    return float(whole), float(minutes), (degrees - whole - minutes / 60) * 3600


def gps_position(plan: SurveyPlan, index: int) -> np.ndarray:
    """``(latitude, longitude, altitude)`` the photo's EXIF gives: its centre plus GPS noise."""
    rotation, translation = camera_pose(plan, index)
    noisy = -rotation.T @ translation + _rng(plan.seed, _TAG_GPS, index).normal(0.0, plan.gps_noise_m, 3)
    return wgs84_from_enu(noisy, np.array(ORIGIN_WGS84))[0]


def exif_bytes(plan: SurveyPlan, index: int) -> bytes:
    """The photo's EXIF (module docstring): the focal length in pixels is ``FocalLength`` (mm)
    times ``FocalPlaneXResolution`` (pixels per cm) / 10, what ``sfm.io.exif`` reads."""
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = CAMERA_MAKE, CAMERA_MODEL  # Make, Model
    sub = exif.get_ifd(0x8769)
    sub[0x920A] = plan.focal * PIXEL_PITCH_MM  # FocalLength, mm
    sub[0xA20E] = sub[0xA20F] = 10.0 / PIXEL_PITCH_MM  # FocalPlaneX/YResolution, pixels per unit
    sub[0xA210] = 3  # FocalPlaneResolutionUnit: cm
    sub[0xA002], sub[0xA003] = plan.width, plan.height  # PixelX/YDimension (ExifImageWidth/Height)
    lat, lon, alt = gps_position(plan, index)
    gps = exif.get_ifd(0x8825)
    gps[0] = b"\x02\x03\x00\x00"  # GPSVersionID
    gps[1], gps[2] = ("N" if lat >= 0 else "S"), _dms(abs(lat))
    gps[3], gps[4] = ("E" if lon >= 0 else "W"), _dms(abs(lon))
    gps[5], gps[6] = (b"\x00" if alt >= 0 else b"\x01"), abs(float(alt))
    gps[18] = "WGS-84"  # GPSMapDatum
    return exif.tobytes()


def photo(plan: SurveyPlan, index: int) -> bytes:
    """Photo ``index`` as the bytes of its JPEG file, with its EXIF."""
    out = io.BytesIO()
    Image.fromarray(render(plan, index)).save(out, "JPEG", quality=JPEG_QUALITY, exif=exif_bytes(plan, index))
    return out.getvalue()


def gt_table(plan: SurveyPlan) -> str:
    """The GT table of every photo (``sfm.evaluation.ground_truth.read_gt_table``'s format)."""
    K = plan.K
    lines = ["# IMAGE_NAME WIDTH HEIGHT FX FY CX CY QW QX QY QZ TX TY TZ (cam_from_world, OpenCV pixels)"]
    for index in range(plan.num_images):
        rotation, translation = camera_pose(plan, index)
        values = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *rotation_to_quaternion(rotation), *translation]
        lines.append(
            f"{image_name(index)} {plan.width} {plan.height} " + " ".join(f"{v:.17g}" for v in values)
        )
    return "\n".join(lines) + "\n"


def description(plan: SurveyPlan) -> dict:
    """The survey's parameters for ``gt/survey.json``: the options that made it (a resumed run
    must match them), the origin, the flight plan and where the twins stand."""
    x_min, x_max, y_min, y_max = plan.area_m
    places: dict[int, list] = {}
    for (i, j), k in sorted(twin_cells(plan).items()):
        building = building_in_cell(plan, i, j)
        places.setdefault(k, []).append({"cell": [i, j], "center": [round(c, 3) for c in building.center]})
    nadir = plan.stations
    return {
        "scene": "survey",
        "version": SCENE_VERSION,
        "options": {
            "num_images": plan.num_images,
            "width": plan.width,
            "height": plan.height,
            "focal": plan.focal,
            "seed": plan.seed,
            "twins": plan.twins,
            "gps_noise_m": plan.gps_noise_m,
        },
        "origin_wgs84": {
            "latitude": ORIGIN_WGS84[0],
            "longitude": ORIGIN_WGS84[1],
            "altitude_m": ORIGIN_WGS84[2],
        },
        "frame": "x east, y north, z up (metres, ENU at the origin)",
        "altitude_m": ALTITUDE_M,
        "gsd_m": plan.gsd_m,
        "area_m": {"x_min": x_min, "x_max": x_max, "y_min": y_min, "y_max": y_max},
        "strips": plan.strips,
        "stations_per_strip": plan.stations_per_strip,
        "forward_base_m": plan.base_m,
        "strip_spacing_m": plan.strip_spacing_m,
        "nadir_images": nadir,
        "oblique_images": plan.num_images - nadir,
        "oblique_tilt_deg": OBLIQUE_TILT_DEG,
        "building_cell_m": CELL_M,
        "twins": [{"design": k, "places": places[k]} for k in sorted(places)],
    }
