"""EXIF metadata of an image file, read with Pillow without decoding pixels: the focal-length
prior, GPS position, orientation, make and model.

Focal prior (:func:`focal_prior_from_exif`), in pixels of the upright image:
``FocalLengthIn35mmFilm / 36 * max(W, H)`` (36 mm is the long side of a 35 mm frame; COLMAP
divides by 35), else ``FocalLength`` (mm) times the sensor's pixels per mm from
``FocalPlaneXResolution`` / ``FocalPlaneResolutionUnit``, rescaled by
``max(W, H) / max(PixelXDimension, PixelYDimension)`` when the file was resized after the
camera wrote those tags; else no prior. Priors outside ``[0.1, 50] * max(W, H)`` are treated
as bogus EXIF and ignored.

GPS (:func:`gps_from_exif`): the GPS IFD's latitude, longitude (degrees, minutes, seconds with
their N/S and E/W references) and altitude (metres, below sea level when GPSAltitudeRef is 1)
on WGS84; like COLMAP, all three must be there, else the image has no GPS.
"""

from __future__ import annotations

import math

from PIL import Image

# EXIF tags (IFD0 and the Exif sub-IFD)
_EXIF_IFD = 0x8769
_GPS_IFD = 0x8825
_GPS_LAT_REF, _GPS_LAT, _GPS_LON_REF, _GPS_LON, _GPS_ALT_REF, _GPS_ALT = 1, 2, 3, 4, 5, 6
ORIENTATION = 0x0112
MAKE, MODEL = 0x010F, 0x0110
_FOCAL_LENGTH = 0x920A
_FOCAL_35MM = 0xA405
_FOCAL_PLANE_X_RES, _FOCAL_PLANE_UNIT = 0xA20E, 0xA210
_PIXEL_X_DIM, _PIXEL_Y_DIM = 0xA002, 0xA003
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # inch, cm, mm, micrometre
_PLAUSIBLE_FOCAL = (0.1, 50.0)  # times max(W, H)


def exif_number(value: object) -> float | None:
    """A finite float from an EXIF value (rational, int, tuple of one), or None."""
    if isinstance(value, (tuple, list)):
        value = value[0] if len(value) == 1 else None
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) else None


def exif_text(value: object) -> str:
    if isinstance(value, bytes):
        value = value.decode("latin-1", errors="replace")
    return str(value).strip().strip("\x00").strip() if value is not None else ""


def focal_prior_from_exif(tags: dict, width: int, height: int) -> tuple[float | None, str]:
    """EXIF focal prior in pixels and its source (module docstring).

    ``tags`` maps EXIF tag ids to values (IFD0 and the Exif sub-IFD merged); ``width`` and
    ``height`` are the image's (either orientation: only ``max(W, H)`` matters).
    """
    max_size = max(width, height)
    lo, hi = _PLAUSIBLE_FOCAL[0] * max_size, _PLAUSIBLE_FOCAL[1] * max_size
    f35 = exif_number(tags.get(_FOCAL_35MM))
    if f35 is not None and f35 > 0 and lo <= f35 / 36.0 * max_size <= hi:
        return f35 / 36.0 * max_size, "exif-35mm"
    f_mm = exif_number(tags.get(_FOCAL_LENGTH))
    x_res = exif_number(tags.get(_FOCAL_PLANE_X_RES))
    unit = exif_number(tags.get(_FOCAL_PLANE_UNIT))
    unit_mm = _MM_PER_UNIT.get(int(unit) if unit is not None else 2)  # EXIF default: inches
    if f_mm and f_mm > 0 and x_res and x_res > 0 and unit_mm is not None:
        f_px = f_mm * x_res / unit_mm
        exif_w, exif_h = exif_number(tags.get(_PIXEL_X_DIM)), exif_number(tags.get(_PIXEL_Y_DIM))
        if exif_w and exif_h and exif_w > 0 and exif_h > 0:
            f_px *= max_size / max(exif_w, exif_h)  # the file was resized after capture
        if lo <= f_px <= hi:
            return f_px, "exif-focal-plane"
    return None, "none"


def _degrees(value: object) -> float | None:
    """Degrees from an EXIF (degrees, minutes, seconds) triple of rationals, or None."""
    if not isinstance(value, (tuple, list)) or not 1 <= len(value) <= 3:
        return None
    parts = [exif_number(v) for v in value]
    if any(p is None for p in parts):
        return None
    return sum(p / 60.0**k for k, p in enumerate(parts))  # type: ignore[operator]


def gps_from_exif(gps: dict) -> tuple[float, float, float] | None:
    """``(latitude, longitude, altitude)`` from a GPS IFD (tag ids to values), or None when
    one of them is missing or out of range (module docstring)."""
    lat, lon, alt = _degrees(gps.get(_GPS_LAT)), _degrees(gps.get(_GPS_LON)), exif_number(gps.get(_GPS_ALT))
    if lat is None or lon is None or alt is None or not (0 <= lat <= 90 and 0 <= lon <= 180):
        return None
    if exif_text(gps.get(_GPS_LAT_REF)).upper().startswith("S"):
        lat = -lat
    if exif_text(gps.get(_GPS_LON_REF)).upper().startswith("W"):
        lon = -lon
    ref = gps.get(_GPS_ALT_REF)
    if (ref[0] if isinstance(ref, (bytes, tuple, list)) and len(ref) else exif_number(ref)) == 1:
        alt = -alt
    return float(lat), float(lon), float(alt)


def gps_tags(im: Image.Image) -> dict:
    if im.format == "PNG" and "exif" not in im.info:
        return {}
    try:
        return dict(im.getexif().get_ifd(_GPS_IFD))
    except Exception:  # noqa: BLE001 - malformed EXIF is common and never fatal
        return {}


def exif_tags(im: Image.Image) -> dict:
    """IFD0 and Exif sub-IFD tags merged (sub-IFD wins), read without decoding pixels."""
    if im.format == "PNG" and "exif" not in im.info:
        return {}  # PngImageFile.getexif() would decode the whole image to look after IDAT
    try:
        exif = im.getexif()
        tags = dict(exif)
        tags.update(exif.get_ifd(_EXIF_IFD))
    except Exception:  # noqa: BLE001 - malformed EXIF is common and never fatal
        return {}
    return tags
