"""Which camera each image gets: the ``--intrinsics`` file, EXIF priors and camera grouping.

The intrinsics file (``--intrinsics``) has lines ``IMAGE_NAME WIDTH HEIGHT FX FY CX CY [more columns
ignored]``; ``#`` lines and blank lines are skipped; the name ``*`` applies a line to every image
no other line names; the principal point uses OpenCV's pixel convention (pixel centres at
integers), like every pixel in graphsfm. The ground-truth tables ``gt/cameras_gt_opencv.txt``
are such files. Names must equal the image names (paths relative to the image folder).

Cameras (:func:`assign_cameras`):

- An image named by the file gets a ``PINHOLE (fx, fy, cx, cy)`` camera with
  ``prior_focal_length`` True; images whose lines hold the same values share one camera.
- Any other image gets a camera of ``camera_model`` (``--camera-model``, COLMAP's names:
  ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL`` (the default), ``RADIAL``, ``OPENCV``) with
  ``cx, cy = ((W-1)/2, (H-1)/2)``, no distortion, and every focal length the EXIF prior
  (``prior_focal_length`` True) or ``1.2 * max(W, H)`` (False); bundle adjustment refines what
  ``MapperOptions.intrinsics_refinement`` says. ``camera_mode`` groups these images: ``auto`` one camera per (size, EXIF make and
  model, focal prior); ``single`` one camera for all (all must have the same upright size);
  ``per-folder`` one per sub-folder (same-size rule); ``per-image`` one per image. A shared
  camera takes the focal prior of its first image (by name) that has an EXIF prior.
- With ``per-folder`` and ``per-image`` the PINHOLE cameras are split the same way, so each
  folder or image can be refined on its own.

Each camera has a group key (a JSON string) so a resumed run finds the camera it made before;
``CameraSpec.given`` marks the cameras of the intrinsics file, which the mapper holds fixed.
"""

from __future__ import annotations

import json
import logging
import math
import posixpath
from dataclasses import dataclass, field
from pathlib import Path

from backend.camera_models import CAMERA_MODELS, default_params
from sfm.errors import InputError
from sfm.io.image_files import ImageInfo

logger = logging.getLogger(__name__)

CAMERA_MODES = ("auto", "single", "per-folder", "per-image")
CAMERA_MODEL_NAMES = tuple(CAMERA_MODELS)  # SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV
DEFAULT_CAMERA_MODEL = "SIMPLE_RADIAL"
DEFAULT_FOCAL_FACTOR = 1.2  # focal = 1.2 * max(W, H) without an EXIF prior (COLMAP's default)


@dataclass(frozen=True)
class KnownIntrinsics:
    """One line of an intrinsics file (``line`` is its 1-based line number)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    line: int = field(default=0, compare=False)

    @property
    def values(self) -> tuple[int, int, float, float, float, float]:
        return (self.width, self.height, self.fx, self.fy, self.cx, self.cy)


@dataclass(frozen=True)
class IntrinsicsTable:
    """An intrinsics file: per-image lines and the optional ``*`` line."""

    path: Path
    by_name: dict[str, KnownIntrinsics]
    default: KnownIntrinsics | None = None

    def lookup(self, name: str) -> KnownIntrinsics | None:
        return self.by_name.get(name, self.default)


def _parse_line(path: Path, lineno: int, tokens: list[str]) -> KnownIntrinsics:
    where = f"{path}:{lineno}"
    if len(tokens) < 7:
        raise InputError(
            f"{where}: expected 'IMAGE_NAME WIDTH HEIGHT FX FY CX CY', got {len(tokens)} columns"
        )
    try:
        values = [float(t) for t in tokens[1:7]]
    except ValueError:
        raise InputError(
            f"{where}: WIDTH HEIGHT FX FY CX CY must be numbers: {' '.join(tokens[1:7])}"
        ) from None
    w, h, fx, fy, cx, cy = values
    if not all(math.isfinite(v) for v in values):
        raise InputError(f"{where}: intrinsics must be finite numbers")
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise InputError(
            f"{where}: WIDTH and HEIGHT must be positive integers, got {tokens[1]} {tokens[2]}"
        )
    if fx <= 0 or fy <= 0:
        raise InputError(f"{where}: FX and FY must be positive, got {tokens[3]} {tokens[4]}")
    return KnownIntrinsics(int(w), int(h), fx, fy, cx, cy, lineno)


def read_intrinsics(path: Path) -> IntrinsicsTable:
    """Parse an intrinsics file; :class:`InputError` names the file and line of any bad line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"intrinsics file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read intrinsics file {path}: {exc}") from None
    by_name: dict[str, KnownIntrinsics] = {}
    default = None
    for lineno, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        k = _parse_line(path, lineno, tokens)
        previous = default if tokens[0] == "*" else by_name.get(tokens[0])
        if previous is not None and previous != k:
            raise InputError(
                f"{path}:{lineno}: {tokens[0]} has other intrinsics on line {previous.line}"
            )
        if tokens[0] == "*":
            default = previous or k
        else:
            by_name[tokens[0]] = previous or k
    if not by_name and default is None:
        raise InputError(f"intrinsics file {path} has no intrinsics lines")
    return IntrinsicsTable(path, by_name, default)


@dataclass(frozen=True)
class CameraSpec:
    """A camera to create: model, upright size, params (OpenCV pixel convention), prior flag.

    ``key`` identifies its group; ``shared`` is False for per-image cameras (found again
    through the image's row, so a resumed run needs no record of them); ``given``: the values
    come from the intrinsics file.
    """

    key: str
    model: str
    width: int
    height: int
    params: tuple[float, ...]
    prior_focal_length: bool
    shared: bool = True
    given: bool = False


def default_camera_params(info: ImageInfo, camera_model: str = DEFAULT_CAMERA_MODEL) -> tuple[tuple[float, ...], bool]:
    """Params of ``camera_model`` for an image (focal lengths the EXIF prior or 1.2 x the
    longer side, principal point at the centre, no distortion) and ``prior_focal_length``."""
    w, h = info.width, info.height
    prior = info.focal_px is not None
    f = float(info.focal_px) if prior else DEFAULT_FOCAL_FACTOR * max(w, h)
    return tuple(float(v) for v in default_params(camera_model, w, h, f)), prior


def _scope(camera_mode: str, name: str) -> list[str]:
    if camera_mode == "per-folder":
        return ["folder", posixpath.dirname(name)]
    if camera_mode == "per-image":
        return ["image", name]
    return []


def _check_same_size(camera_mode: str, names: list[str], infos: dict[str, ImageInfo]) -> None:
    sizes = {(infos[n].width, infos[n].height): n for n in reversed(names)}
    if len(sizes) > 1:
        examples = ", ".join(
            f"{n} is {w}x{h}" for (w, h), n in sorted(sizes.items(), key=lambda s: s[1])
        )
        raise InputError(
            f"camera_mode {camera_mode} needs images of one size per camera, but {examples}; "
            "use camera_mode auto"
        )


def assign_cameras(
    infos: dict[str, ImageInfo], camera_mode: str, table: IntrinsicsTable | None,
    camera_model: str = DEFAULT_CAMERA_MODEL,
) -> dict[str, CameraSpec]:
    """The camera of every image (module docstring for the rules); :class:`InputError` when an
    intrinsics line's size differs from its image or a shared camera would span two sizes."""
    if camera_mode not in CAMERA_MODES:
        raise InputError(
            f"camera_mode must be one of {'|'.join(CAMERA_MODES)}, got {camera_mode!r}"
        )
    if camera_model not in CAMERA_MODEL_NAMES:
        raise InputError(
            f"camera_model must be one of {'|'.join(CAMERA_MODEL_NAMES)}, got {camera_model!r}"
        )
    groups: dict[str, list[str]] = {}
    known: dict[str, KnownIntrinsics] = {}
    uncovered = []
    source = table.path if table is not None else None
    for name in sorted(infos):
        info = infos[name]
        k = table.lookup(name) if table is not None else None
        if k is not None:
            if (k.width, k.height) != (info.width, info.height):
                raise InputError(
                    f"{source}:{k.line}: intrinsics for a {k.width}x{k.height} image, but "
                    f"{name} is {info.width}x{info.height} (after EXIF orientation)"
                )
            key = json.dumps(["pinhole", *_scope(camera_mode, name), *k.values])
            known[key] = k
        else:
            uncovered.append(name)
            if camera_mode == "auto":
                focal = None if info.focal_px is None else round(info.focal_px, 3)
                key = json.dumps(["auto", info.width, info.height, info.make, info.model, focal])
            else:
                key = json.dumps(["exif", *(_scope(camera_mode, name) or ["single"])])
        groups.setdefault(key, []).append(name)
    if table is not None and uncovered:
        logger.warning(
            "%d image(s) not in intrinsics file %s (e.g. %s): they get %s cameras with EXIF or "
            "default focal priors", len(uncovered), table.path, ", ".join(uncovered[:3]), camera_model,
        )  # fmt: skip
    specs: dict[str, CameraSpec] = {}
    for key, names in groups.items():
        shared = camera_mode != "per-image"
        if key in known:
            k = known[key]
            spec = CameraSpec(key, "PINHOLE", k.width, k.height, k.values[2:], True, shared, given=True)
        else:
            _check_same_size(camera_mode, names, infos)
            with_prior = [n for n in names if infos[n].focal_px is not None]
            info = infos[(with_prior or names)[0]]
            params, prior = default_camera_params(info, camera_model)
            spec = CameraSpec(key, camera_model, info.width, info.height, params, prior, shared)
        for name in names:
            specs[name] = spec
    return specs


def warn_unused_lines(table: IntrinsicsTable, names: list[str]) -> None:
    """Warn once when lines of the intrinsics file name no image of the folder."""
    unused = sorted(set(table.by_name) - set(names))
    if unused:
        logger.warning(
            "%d line(s) of intrinsics file %s name no image in the folder (e.g. %s); names must "
            "be paths relative to the image folder", len(unused), table.path, ", ".join(unused[:3]),
        )  # fmt: skip
