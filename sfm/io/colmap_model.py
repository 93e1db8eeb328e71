"""Read and write COLMAP sparse models (``.bin`` or ``.txt``) and export the points as PLY.

Conventions at this boundary, and nowhere else:

* Pixels: graphsfm keypoints and principal points use OpenCV's convention (pixel centres at
  integers); COLMAP files put the image corner at (0, 0).  Writing adds 0.5 to keypoint x, y and
  to cx, cy (:func:`sfm.io.pixel_convention.params_to_colmap`); reading subtracts 0.5
  (:func:`~sfm.io.pixel_convention.params_from_colmap`).
* Poses: an image's qvec (w, x, y, z) + tvec is ``cam_from_world`` (``x_cam = R X + t``), i.e.
  ``Image.cam_from_world_rotation`` / ``cam_from_world_translation``.
* Only registered images are written; observations in other images are left out of the tracks
  (points left with none are skipped, with a warning).  Every image read is registered.  Camera,
  image and point ids are preserved.  Tracks are written in (image_id, point2D_idx) order; the
  images' point3D ids are the source of the observations.  ERROR is ``Point3D.error`` as held
  (the point's mean reprojection error in px); colours are RGB uint8.
* COLMAP 4 (checked with pycolmap 4.2.1) writes ``rigs`` and ``frames`` files beside the classic
  three and still reads models without them, deriving one trivial rig per camera
  (rig_id = camera_id) and one frame per image (frame_id = image_id, rig_from_world =
  cam_from_world).  We write exactly those files too, so a directory that held a COLMAP 4 model
  never keeps stale rigs/frames.  Reading ignores them: the images file holds every pose.
* Text numbers are written with ``repr`` (shortest exact round trip): txt round trips are exact.
* Each file goes to a temporary file in the target directory; all are moved into place with
  ``os.replace`` once every one is complete, so an interrupted write leaves no partial file.

PLY (:func:`write_ply`): binary little-endian, one ``vertex`` element with ``double x, y, z``,
``float nx, ny, nz`` and ``uchar red, green, blue``, points in ascending id order.  A sparse
point has no surface normal; its normal is the side it was seen from, the mean of the unit
directions from the point to the cameras that observe it (zero for a point no registered image
sees), which is what the Gaussian-splatting reference code and OpenMVS read as ``nx, ny, nz``.
"""

from __future__ import annotations

import gc
import logging
import os
import uuid
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import IO

import numpy as np

from sfm.errors import DamagedFileError
from sfm.io.pixel_convention import params_from_colmap, params_to_colmap
from sfm.io.colmap_files import WRITERS, ModelTables, corrupt_file, read_bin, read_txt
from backend.geometry import quaternion_to_rotation, rotation_to_quaternion
from sfm.core.model import INVALID_POINT3D, Camera, Image, Point3D, Reconstruction

logger = logging.getLogger(__name__)

FILES = ("cameras", "images", "points3D")
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}  # fmt: skip


# ---------------------------------------------------------------------------------- public API
def write_model(recon: Reconstruction, path: str | os.PathLike, fmt: str = "bin") -> None:
    """Write ``recon`` as a COLMAP model (``fmt`` "bin" or "txt") into directory ``path``."""
    if fmt not in ("bin", "txt"):
        raise ValueError(f"unknown COLMAP model format {fmt!r}; use 'bin' or 'txt'")
    with _no_gc(), _atomic_dir(Path(path)) as open_:
        t = _to_tables(recon)
        for name, writer in WRITERS[fmt].items():  # cameras, images, points3D, rigs, frames
            with open_(f"{name}.{fmt}") as f:
                writer(f, t)
    logger.debug("wrote %s model %s: %d cameras, %d images, %d points, %d observations", fmt,
                path, len(t.cameras), len(t.image_ids), len(t.point_ids), len(t.track))


def detect_format(path: str | os.PathLike) -> str:
    """``"bin"`` or ``"txt"``: which complete COLMAP model directory ``path`` holds (bin first)."""
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"COLMAP model directory {path} does not exist (or is a file)")
    for fmt in ("bin", "txt"):
        if all((path / f"{n}.{fmt}").is_file() for n in FILES):
            return fmt
    found = sorted(p.name for p in path.iterdir() if p.stem in FILES)
    raise FileNotFoundError(f"{path} holds no complete COLMAP model (cameras, images, points3D "
                            f"as .bin or .txt); found: {', '.join(found) or 'none of them'}")


def read_model(path: str | os.PathLike, fmt: str | None = None) -> Reconstruction:
    """Read the COLMAP model in directory ``path`` (format detected unless ``fmt`` is given)."""
    path = Path(path)
    fmt = fmt or detect_format(path)
    if fmt not in ("bin", "txt"):
        raise ValueError(f"unknown COLMAP model format {fmt!r}; use 'bin' or 'txt'")
    for name in FILES:
        if not (path / f"{name}.{fmt}").is_file():
            raise FileNotFoundError(f"COLMAP model file {path / f'{name}.{fmt}'} is missing")
    try:
        with _no_gc():
            recon = _from_tables(read_bin(path) if fmt == "bin" else read_txt(path), path)
    except ValueError as exc:  # colmap_files.corrupt_file: any parse failure, naming the file
        raise DamagedFileError(path, str(exc),
                               "give a complete model, or delete it and rerun the stage that wrote it") from exc
    logger.debug("read %s model %s: %d cameras, %d images, %d points", fmt, path,
                len(recon.cameras), len(recon.images), len(recon.points3D))
    return recon


def ply_arrays(recon: Reconstruction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(xyz (N, 3), rgb (N, 3) uint8, normals (N, 3))`` of the points in ascending id order
    (normals: the module docstring's viewing side)."""
    ids = sorted(recon.points3D)
    xyz = np.array([recon.points3D[i].xyz for i in ids], np.float64).reshape(-1, 3)
    rgb = np.array([recon.points3D[i].color for i in ids], np.uint8).reshape(-1, 3)
    centers = {i: im.center for i, im in recon.images.items() if im.registered}
    normals = np.zeros_like(xyz)
    for row, i in enumerate(ids):
        rays = np.array([centers[img] for img, _ in recon.points3D[i].track if img in centers]).reshape(-1, 3) - xyz[row]
        if len(rays):
            mean = (rays / np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-300)).mean(axis=0)
            normals[row] = mean / max(float(np.linalg.norm(mean)), 1e-300)
    return xyz, rgb, normals


def write_ply(recon: Reconstruction, path: str | os.PathLike) -> None:
    """Write the points (ascending id) as binary little-endian PLY: double x,y,z, float
    nx,ny,nz, uchar rgb (module docstring)."""
    write_ply_arrays(path, *ply_arrays(recon))


def write_ply_arrays(path: str | os.PathLike, xyz: np.ndarray, rgb: np.ndarray, normals: np.ndarray | None = None) -> None:
    """Binary little-endian PLY of points ``xyz`` (N, 3) with colours ``rgb`` and, if given,
    ``normals`` (N, 3)."""
    path = Path(path)
    fields = [("xyz", "<f8", (3,))] + ([("n", "<f4", (3,))] if normals is not None else []) + [("rgb", "u1", (3,))]
    data = np.empty(len(xyz), np.dtype(fields))
    data["xyz"] = np.asarray(xyz).reshape(-1, 3)
    if normals is not None:
        data["n"] = np.asarray(normals).reshape(-1, 3)
    data["rgb"] = np.asarray(rgb).reshape(-1, 3)
    names = [("double", "x"), ("double", "y"), ("double", "z")]
    names += [("float", "nx"), ("float", "ny"), ("float", "nz")] if normals is not None else []
    names += [("uchar", "red"), ("uchar", "green"), ("uchar", "blue")]
    props = "".join(f"property {t} {n}\n" for t, n in names)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(data)}\n{props}end_header\n"
    with _atomic_dir(path.parent) as open_, open_(path.name) as f:
        f.write(header.encode("ascii"))
        f.write(data.tobytes())


def read_ply(path: str | os.PathLike, normals: bool = False) -> tuple[np.ndarray, ...]:
    """``(xyz (N, 3) float64, rgb (N, 3) uint8)`` of a binary little-endian PLY's vertices,
    and with ``normals`` their ``nx, ny, nz`` (N, 3) float64 (NaN when the file has none)."""
    path = Path(path)
    buf = path.read_bytes()
    with corrupt_file(path):
        end = buf.index(b"end_header\n") + len(b"end_header\n")
        lines = buf[:end].decode("ascii").splitlines()
        if lines[0] != "ply" or lines[1].split()[:2] != ["format", "binary_little_endian"]:
            raise ValueError("not a binary little-endian PLY")
        elem = [ln.split() for ln in lines if ln.startswith("element")]
        if not elem or elem[0][1] != "vertex":
            raise ValueError("the first element is not 'vertex'")
        fields, count = [], 0
        for ln in lines:
            words = ln.split()
            count += words[0] == "element"
            if count == 1 and words[0] == "property":
                fields.append((words[2], "<" + _PLY_TYPES[words[1]]))
        data = np.frombuffer(buf, np.dtype(fields), int(elem[0][2]), end)
        xyz = np.stack([data[c].astype(np.float64) for c in "xyz"], axis=1)
        has_rgb = all(c in data.dtype.names for c in ("red", "green", "blue"))
        rgb = (np.stack([data[c] for c in ("red", "green", "blue")], axis=1).astype(np.uint8)
               if has_rgb else np.full((len(data), 3), 128, np.uint8))
        if not normals:
            return xyz, rgb
        has_normals = all(c in data.dtype.names for c in ("nx", "ny", "nz"))
        nxyz = (np.stack([data[c].astype(np.float64) for c in ("nx", "ny", "nz")], axis=1)
                if has_normals else np.full((len(data), 3), np.nan))
    return xyz, rgb, nxyz


# ---------------------------------------------------------------------------------- conversion
def _to_tables(recon: Reconstruction) -> ModelTables:
    images = [recon.images[i] for i in recon.registered_image_ids]
    for im in images:
        if im.camera_id not in recon.cameras:
            raise ValueError(f"image {im.name}: camera {im.camera_id} is not in the model")
    point_ids = np.array(sorted(recon.points3D), dtype=np.int64)
    pts = [recon.points3D[i] for i in point_ids.tolist()]
    pids2d = [im.point3D_ids for im in images]
    obs_kp = [np.flatnonzero(p != INVALID_POINT3D) for p in pids2d]
    obs_pid = np.concatenate([p[k] for p, k in zip(pids2d, obs_kp)] + [np.zeros(0, np.int64)])
    obs_img = np.repeat([im.image_id for im in images], [len(k) for k in obs_kp])
    obs_kp_all = np.concatenate(obs_kp + [np.zeros(0, np.int64)])
    order = np.lexsort((obs_kp_all, obs_img, obs_pid))
    pos = np.searchsorted(point_ids, obs_pid[order])  # sorted queries: fast
    if np.any(pos >= len(point_ids)) or np.any(point_ids[np.minimum(pos, len(point_ids) - 1)]
                                                 != obs_pid[order]):
        raise ValueError("an image observes a 3D point that is not in the model")
    counts = np.bincount(pos, minlength=len(point_ids))
    keep = counts > 0
    if not keep.all():
        logger.warning("%d points seen by no registered image are not written", (~keep).sum())
    return ModelTables(
        cameras=[(c.camera_id, c.model, c.width, c.height, params_to_colmap(c.model, c.params))
                 for c in sorted(recon.cameras.values(), key=lambda c: c.camera_id)],
        image_ids=[im.image_id for im in images],
        qvecs=np.array([rotation_to_quaternion(im.cam_from_world_rotation) for im in images]),
        tvecs=np.array([im.cam_from_world_translation for im in images]),
        camera_ids=[im.camera_id for im in images],
        names=[im.name for im in images],
        xys=[im.keypoints + 0.5 for im in images],
        pids2d=pids2d,
        point_ids=point_ids[keep],
        xyz=np.array([p.xyz for p in pts]).reshape(-1, 3)[keep],
        rgb=np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)[keep],
        error=np.array([p.error for p in pts], dtype=np.float64)[keep],
        track_len=counts[keep],
        track=np.stack([obs_img[order], obs_kp_all[order]], axis=1).astype(np.int64),
    )


def _from_tables(t: ModelTables, path: Path) -> Reconstruction:
    point_ids = t.point_ids.astype(np.int64)
    if len(np.unique(point_ids)) != len(point_ids) or len(set(t.image_ids)) != len(t.image_ids):
        raise ValueError(f"{path}: duplicate image or point ids")
    recon = Reconstruction(_next_point_id=int(point_ids.max()) + 1 if len(point_ids) else 1)
    for cid, model, width, height, params in sorted(t.cameras, key=lambda c: c[0]):
        recon.cameras[cid] = Camera(cid, model, width, height, params_from_colmap(model, params))
    for i in np.argsort(t.image_ids, kind="stable").tolist():
        if t.camera_ids[i] not in recon.cameras:
            raise ValueError(f"{path}: image {t.names[i]} uses unknown camera {t.camera_ids[i]}")
        recon.images[t.image_ids[i]] = Image(
            t.image_ids[i], t.names[i], t.camera_ids[i], quaternion_to_rotation(t.qvecs[i]),
            t.tvecs[i].copy(), t.xys[i] - 0.5, t.pids2d[i].astype(np.int64), registered=True)
    # Every track element must hit a keypoint holding that point id, and no other keypoint may.
    img_ids = np.array(sorted(recon.images), dtype=np.int64)
    sizes = np.array([len(recon.images[i].point3D_ids) for i in img_ids.tolist()], np.int64)
    flat_pids = np.concatenate([recon.images[i].point3D_ids for i in img_ids.tolist()]
                               + [np.zeros(0, np.int64)])
    base = np.concatenate([[0], np.cumsum(sizes)])
    ok = int(np.count_nonzero(flat_pids != INVALID_POINT3D)) == len(t.track)
    if ok and len(t.track):
        pos = np.minimum(np.searchsorted(img_ids, t.track[:, 0]), max(len(img_ids) - 1, 0))
        ok = len(img_ids) > 0 and bool(np.all(img_ids[pos] == t.track[:, 0]))
        ok = ok and bool(np.all((t.track[:, 1] >= 0) & (t.track[:, 1] < sizes[pos])))
    if ok and len(t.track):
        flat = base[pos] + t.track[:, 1]
        hit = np.zeros(len(flat_pids), bool)
        hit[flat] = True
        ok = int(hit.sum()) == len(flat)
        ok = ok and bool(np.all(flat_pids[flat] == np.repeat(point_ids, t.track_len)))
    if not ok:
        raise ValueError(f"{path}: points3D tracks and the images' point3D ids disagree")
    starts = np.concatenate([[0], np.cumsum(t.track_len)]).tolist()
    obs = list(zip(t.track[:, 0].tolist(), t.track[:, 1].tolist()))
    ids, xyz, rgb, err = point_ids.tolist(), t.xyz.astype(np.float64), t.rgb, t.error.tolist()
    for i in np.argsort(point_ids, kind="stable").tolist():
        recon.points3D[ids[i]] = Point3D(xyz[i], obs[starts[i]:starts[i + 1]], rgb[i], err[i])
    return recon


# ---------------------------------------------------------------------------------- files
@contextmanager
def _no_gc() -> Iterator[None]:
    """Pause the cyclic garbage collector while millions of acyclic objects are made."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


@contextmanager
def _atomic_dir(directory: Path) -> Iterator[Callable[[str], AbstractContextManager[IO[bytes]]]]:
    """Yield ``open_(name)``: files written to temporaries, all moved into place at the end."""
    directory.mkdir(parents=True, exist_ok=True)
    pending: list[tuple[Path, Path]] = []

    @contextmanager
    def open_(name: str) -> Iterator[IO[bytes]]:
        tmp = directory / f".{name}.{uuid.uuid4().hex}.tmp"  # open() gives the umask's mode
        pending.append((tmp, directory / name))
        with open(tmp, "xb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())

    try:
        yield open_
    except BaseException:
        for tmp, _ in pending:
            tmp.unlink(missing_ok=True)
        raise
    for tmp, final in pending:
        os.replace(tmp, final)
