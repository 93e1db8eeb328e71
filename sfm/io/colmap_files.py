"""Byte level of COLMAP sparse models: ``.bin`` and ``.txt`` readers and writers.

Used by :mod:`sfm.io.colmap_model`, which documents the conventions and converts to and from
:class:`sfm.core.model.Reconstruction`.  Here a model is a :class:`ModelTables`: flat arrays already in
COLMAP's conventions (pixel corner at 0,0; qvec w, x, y, z + tvec = cam_from_world).  Binary
blocks are read and written whole with numpy structured dtypes (``np.frombuffer`` / ``tobytes``
per image and per group of points with equal track length), never per observation.  Text
numbers are written with ``repr`` (exact round trip) and parsed in bulk by ``np.fromstring``.
Layouts (little-endian) as pycolmap 4.2.1 writes them:

* cameras.bin: u64 n; n x (u32 camera_id, i32 model_id, u64 width, u64 height, f64 params[]).
* images.bin: u64 n; n x (u32 image_id, f64 qvec[4], f64 tvec[3], u32 camera_id, name + NUL,
  u64 k, k x (f64 x, f64 y, i64 point3D_id)).
* points3D.bin: u64 n; n x (u64 point3D_id, f64 xyz[3], u8 rgb[3], f64 error, u64 l,
  l x (u32 image_id, u32 point2D_idx)).
* rigs.bin (trivial rigs only): u64 n; n x (u32 rig_id, u32 num_sensors = 1, i32 ref sensor
  type = 0 (CAMERA), u32 ref sensor id).
* frames.bin: u64 n; n x (u32 frame_id, u32 rig_id, f64 rig_from_world (qvec, tvec), u32 num
  data ids, per data id (i32 sensor type, u32 sensor id, u64 data id = image_id)).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from backend.camera_models import model_spec

logger = logging.getLogger(__name__)

_U64 = struct.Struct("<Q")
_CAMERA = struct.Struct("<IiQQ")
_IMAGE = struct.Struct("<I4d3dI")
_FRAME = struct.Struct("<II7dIiIQ")  # one data id: (CAMERA = 0, camera_id, image_id)
_RIG = struct.Struct("<IIiI")  # rig_id, 1 sensor, ref sensor (CAMERA = 0, camera_id)
_POINT2D = np.dtype([("xy", "<f8", (2,)), ("pid", "<i8")])
_POINT_HEAD = np.dtype(
    [("pid", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"), ("n", "<u8")]
)
_TRACK = np.dtype([("image_id", "<u4"), ("idx", "<u4")])


@dataclass
class ModelTables:
    """A model as flat arrays, in COLMAP's pixel convention (the common form of both formats)."""

    cameras: list[tuple[int, str, int, int, np.ndarray]]  # id, model, width, height, params
    image_ids: list[int]
    qvecs: np.ndarray  # (n, 4) w, x, y, z
    tvecs: np.ndarray  # (n, 3)
    camera_ids: list[int]
    names: list[str]
    xys: list[np.ndarray]  # per image (k, 2), corner at (0, 0)
    pids2d: list[np.ndarray]  # per image (k,), -1 for none
    point_ids: np.ndarray  # (p,)
    xyz: np.ndarray  # (p, 3)
    rgb: np.ndarray  # (p, 3) uint8
    error: np.ndarray  # (p,)
    track_len: np.ndarray  # (p,)
    track: np.ndarray  # (m, 2) image_id, point2D_idx, point after point


@contextmanager
def corrupt_file(file: Path) -> Iterator[None]:
    """Turn any parse failure into a ValueError that names the file."""
    try:
        yield
    except (ValueError, IndexError, KeyError, struct.error, UnicodeDecodeError) as exc:
        raise ValueError(f"{file}: corrupt or truncated COLMAP/PLY file ({exc})") from exc


# ---------------------------------------------------------------------------------- binary
def _write_cameras_bin(f: IO[bytes], t: ModelTables) -> None:
    f.write(_U64.pack(len(t.cameras)))
    for cid, model, width, height, params in t.cameras:
        f.write(_CAMERA.pack(cid, model_spec(model).model_id, width, height))
        f.write(params.astype("<f8").tobytes())


def _write_images_bin(f: IO[bytes], t: ModelTables) -> None:
    f.write(_U64.pack(len(t.image_ids)))
    for i, image_id in enumerate(t.image_ids):
        f.write(_IMAGE.pack(image_id, *t.qvecs[i], *t.tvecs[i], t.camera_ids[i]))
        f.write(t.names[i].encode("utf-8") + b"\0" + _U64.pack(len(t.xys[i])))
        block = np.empty(len(t.xys[i]), _POINT2D)
        block["xy"], block["pid"] = t.xys[i], t.pids2d[i]
        f.write(block.tobytes())


def _write_points_bin(f: IO[bytes], t: ModelTables) -> None:
    """Points grouped by track length, so that each group is one fixed-size record array."""
    f.write(_U64.pack(len(t.point_ids)))
    starts = np.concatenate([[0], np.cumsum(t.track_len)[:-1]]).astype(np.int64)
    for length in np.unique(t.track_len).tolist():
        sel = np.flatnonzero(t.track_len == length)
        rec = np.empty(len(sel), np.dtype([("head", _POINT_HEAD), ("track", _TRACK, (length,))]))
        head = rec["head"]
        head["pid"], head["xyz"], head["rgb"] = t.point_ids[sel], t.xyz[sel], t.rgb[sel]
        head["error"], head["n"] = t.error[sel], length
        obs = t.track[starts[sel][:, None] + np.arange(length)]
        rec["track"]["image_id"], rec["track"]["idx"] = obs[..., 0], obs[..., 1]
        f.write(rec.tobytes())


def _write_rigs_bin(f: IO[bytes], t: ModelTables) -> None:
    f.write(_U64.pack(len(t.cameras)) + b"".join(_RIG.pack(c[0], 1, 0, c[0]) for c in t.cameras))


def _write_frames_bin(f: IO[bytes], t: ModelTables) -> None:
    f.write(_U64.pack(len(t.image_ids)))
    for i, (image_id, cid) in enumerate(zip(t.image_ids, t.camera_ids)):
        f.write(_FRAME.pack(image_id, cid, *t.qvecs[i], *t.tvecs[i], 1, 0, cid, image_id))


def read_bin(path: Path) -> ModelTables:
    """The model in ``path``/{cameras,images,points3D}.bin (rigs and frames are not needed)."""
    with corrupt_file(path / "cameras.bin"):
        buf, off, cameras = (path / "cameras.bin").read_bytes(), 8, []
        for _ in range(_U64.unpack_from(buf)[0]):
            cid, model_id, width, height = _CAMERA.unpack_from(buf, off)
            spec = model_spec(model_id)
            params = np.frombuffer(buf, "<f8", spec.num_params, off + _CAMERA.size)
            cameras.append((cid, spec.name, width, height, params.astype(np.float64)))
            off += _CAMERA.size + 8 * spec.num_params
        _check_end(buf, off)
    with corrupt_file(path / "images.bin"):
        buf, off, heads, names, xys, pids2d = (path / "images.bin").read_bytes(), 8, [], [], [], []
        for _ in range(_U64.unpack_from(buf)[0]):
            heads.append(_IMAGE.unpack_from(buf, off))
            end = buf.index(b"\0", off + _IMAGE.size)
            names.append(buf[off + _IMAGE.size:end].decode("utf-8"))
            count = _U64.unpack_from(buf, end + 1)[0]
            block = np.frombuffer(buf, _POINT2D, count, end + 9)
            xys.append(block["xy"].astype(np.float64))
            pids2d.append(block["pid"].astype(np.int64))
            off = end + 9 + _POINT2D.itemsize * count
        _check_end(buf, off)
    with corrupt_file(path / "points3D.bin"):
        buf = (path / "points3D.bin").read_bytes()
        num, off, lens, size = _U64.unpack_from(buf)[0], 8, [], _POINT_HEAD.itemsize
        unpack, len_at = _U64.unpack_from, _POINT_HEAD.fields["n"][1]
        for _ in range(num):  # records have variable length: find them, then slice in bulk
            n = unpack(buf, off + len_at)[0]
            lens.append(n)
            off += size + _TRACK.itemsize * n
        _check_end(buf, off)
        track_len = np.array(lens, dtype=np.int64)
        body = np.frombuffer(buf, np.uint8, offset=8)
        parts = np.stack([np.full(num, size), _TRACK.itemsize * track_len], axis=1).ravel()
        is_track = np.repeat(np.tile([False, True], num), parts)
        head, track = body[~is_track].view(_POINT_HEAD), body[is_track].view(_TRACK)
    h = np.array(heads, dtype=np.float64).reshape(-1, 9)
    return ModelTables(
        cameras, [int(x[0]) for x in heads], h[:, 1:5], h[:, 5:8], [int(x[8]) for x in heads],
        names, xys, pids2d, head["pid"].astype(np.int64), head["xyz"].astype(np.float64),
        head["rgb"].copy(), head["error"].astype(np.float64), track_len,
        np.stack([track["image_id"], track["idx"]], axis=1).astype(np.int64))


def _check_end(buf: bytes, off: int) -> None:
    if off != len(buf):
        raise ValueError(f"{len(buf) - off} unexpected trailing bytes")


# ---------------------------------------------------------------------------------- text
def _r(values: np.ndarray | list) -> str:
    return " ".join(map(repr, np.asarray(values).tolist()))


def _write_cameras_txt(f: IO[bytes], t: ModelTables) -> None:
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(t.cameras)}"]
    lines += [f"{c} {m} {w} {h} {_r(p)}" for c, m, w, h, p in t.cameras]
    f.write(("\n".join(lines) + "\n").encode())


def _write_images_txt(f: IO[bytes], t: ModelTables) -> None:
    f.write(("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY,"
             " TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
             f"# Number of images: {len(t.image_ids)}\n").encode())
    spaced = [n for n in t.names if len(n.split()) != 1 or n != n.strip()]
    if spaced:
        logger.warning("%d image names hold whitespace (e.g. %r): COLMAP's text reader cuts them "
                       "at the first space; the binary format keeps them", len(spaced), spaced[0])
    for i, image_id in enumerate(t.image_ids):
        flat: list = [None] * (3 * len(t.xys[i]))
        flat[0::3], flat[1::3] = t.xys[i][:, 0].tolist(), t.xys[i][:, 1].tolist()
        flat[2::3] = t.pids2d[i].tolist()
        head = f"{image_id} {_r(t.qvecs[i])} {_r(t.tvecs[i])} {t.camera_ids[i]} {t.names[i]}\n"
        f.write((head + " ".join(map(repr, flat)) + "\n").encode("utf-8"))


def _write_points_txt(f: IO[bytes], t: ModelTables) -> None:
    f.write(("# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, "
             "ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
             f"# Number of points: {len(t.point_ids)}\n").encode())
    ends = (2 * np.cumsum(t.track_len)).tolist()
    track, xyz, rgb = t.track.ravel().tolist(), t.xyz.tolist(), t.rgb.tolist()
    err = t.error.tolist()
    start, lines = 0, []
    for i, pid in enumerate(t.point_ids.tolist()):
        (x, y, z), (r, g, b) = xyz[i], rgb[i]
        obs = " ".join(map(str, track[start:ends[i]]))
        lines.append(f"{pid} {x!r} {y!r} {z!r} {r} {g} {b} {err[i]!r} {obs}")
        start = ends[i]
        if len(lines) >= 65536 or i == len(ends) - 1:
            f.write(("\n".join(lines) + "\n").encode())
            lines = []


def _write_rigs_txt(f: IO[bytes], t: ModelTables) -> None:
    lines = ["# Rig calib list with one line of data per calib:", "#   RIG_ID, NUM_SENSORS, "
             "REF_SENSOR_TYPE, REF_SENSOR_ID, SENSORS[] as (SENSOR_TYPE, SENSOR_ID, HAS_POSE, "
             "[QW, QX, QY, QZ, TX, TY, TZ])", f"# Number of rigs: {len(t.cameras)}"]
    f.write(("\n".join(lines + [f"{c[0]} 1 CAMERA {c[0]}" for c in t.cameras]) + "\n").encode())


def _write_frames_txt(f: IO[bytes], t: ModelTables) -> None:
    lines = ["# Frame list with one line of data per frame:", "#   FRAME_ID, RIG_ID, RIG_FROM_WORLD"
             "[QW, QX, QY, QZ, TX, TY, TZ], NUM_DATA_IDS, DATA_IDS[] as (SENSOR_TYPE, SENSOR_ID, "
             "DATA_ID)", f"# Number of frames: {len(t.image_ids)}"]
    lines += [f"{iid} {cid} {_r(t.qvecs[i])} {_r(t.tvecs[i])} 1 CAMERA {cid} {iid}"
              for i, (iid, cid) in enumerate(zip(t.image_ids, t.camera_ids))]
    f.write(("\n".join(lines) + "\n").encode())


def _data_lines(file: Path) -> list[str]:
    return [ln for ln in file.read_text(encoding="utf-8").splitlines() if not ln.startswith("#")]


def _numbers(lines: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """All numbers of ``lines`` as float64 (parsed in C, exact) and how many each line holds."""
    counts = np.array([len(ln.split()) for ln in lines], dtype=np.int64)
    values = np.fromstring(" ".join(lines), sep=" ") if counts.sum() else np.zeros(0)
    if len(values) != counts.sum():
        raise ValueError("a value is not a number")
    return values, counts


def read_txt(path: Path) -> ModelTables:
    """The model in ``path``/{cameras,images,points3D}.txt (rigs and frames are not needed)."""
    with corrupt_file(path / "cameras.txt"):
        cameras = [(int(v[0]), v[1], int(v[2]), int(v[3]), np.array(v[4:], dtype=np.float64))
                   for v in map(str.split, _data_lines(path / "cameras.txt")) if v]
    with corrupt_file(path / "images.txt"):
        lines, k, heads, names, point_lines = _data_lines(path / "images.txt"), 0, [], [], []
        while k < len(lines):
            if lines[k].strip():  # header line, then the (possibly empty) points line
                v = lines[k].split(maxsplit=9)
                heads.append([float(x) for x in v[:9]])
                names.append(v[9])
                point_lines.append(lines[k + 1] if k + 1 < len(lines) else "")
                k += 1
            k += 1
        values, counts = _numbers(point_lines)
        if np.any(counts % 3):
            raise ValueError("a POINTS2D line does not hold (X, Y, POINT3D_ID) triplets")
        rows = np.split(values.reshape(-1, 3), np.cumsum(counts // 3)[:-1]) if heads else []
    with corrupt_file(path / "points3D.txt"):
        values, counts = _numbers([ln for ln in _data_lines(path / "points3D.txt") if ln.strip()])
        if np.any((counts < 8) | (counts % 2 == 1)):
            raise ValueError("a point line does not hold 8 values and (IMAGE_ID, IDX) pairs")
        is_head = np.repeat(np.tile([True, False], len(counts)),
                            np.stack([np.full(len(counts), 8), counts - 8], axis=1).ravel())
        head, track = values[is_head].reshape(-1, 8), values[~is_head].reshape(-1, 2)
        if np.any((head[:, 4:7] < 0) | (head[:, 4:7] > 255)):
            raise ValueError("a colour is outside 0..255")
    h = np.array(heads, dtype=np.float64).reshape(-1, 9)
    return ModelTables(
        cameras, h[:, 0].astype(np.int64).tolist(), h[:, 1:5], h[:, 5:8],
        h[:, 8].astype(np.int64).tolist(), names, [r[:, :2].copy() for r in rows],
        [r[:, 2].astype(np.int64) for r in rows], head[:, 0].astype(np.int64), head[:, 1:4],
        head[:, 4:7].astype(np.uint8), head[:, 7], (counts - 8) // 2, track.astype(np.int64))


WRITERS: dict[str, dict[str, Callable[[IO[bytes], ModelTables], None]]] = {
    "bin": {"cameras": _write_cameras_bin, "images": _write_images_bin,
            "points3D": _write_points_bin, "rigs": _write_rigs_bin, "frames": _write_frames_bin},
    "txt": {"cameras": _write_cameras_txt, "images": _write_images_txt,
            "points3D": _write_points_txt, "rigs": _write_rigs_txt, "frames": _write_frames_txt},
}
