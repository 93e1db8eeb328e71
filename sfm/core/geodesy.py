"""WGS84 geodetic coordinates to a local east-north-up (ENU) frame in metres.

GPS gives latitude and longitude in degrees and altitude in metres on the WGS84 ellipsoid
(semi-major axis 6,378,137 m, flattening 1 / 298.257223563).  A point goes to Earth-centred
Earth-fixed (ECEF) coordinates, then into the ENU frame of an origin: x east, y north, z up,
metres, tangent to the ellipsoid at the origin.  Near the origin (a few km) ENU is a metric
frame in which a reconstruction can be expressed with small coordinates; the origin is kept
beside it so the exact geodetic position can be recovered.
"""

from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0  # semi-major axis, metres
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared


def ecef_from_wgs84(lat_lon_alt: np.ndarray) -> np.ndarray:
    """ECEF (N, 3) metres of (N, 3) rows ``(latitude deg, longitude deg, altitude m)``."""
    lla = np.asarray(lat_lon_alt, np.float64).reshape(-1, 3)
    lat, lon, alt = np.deg2rad(lla[:, 0]), np.deg2rad(lla[:, 1]), lla[:, 2]
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)  # prime vertical radius of curvature
    return np.stack([(n + alt) * np.cos(lat) * np.cos(lon), (n + alt) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - WGS84_E2) + alt) * np.sin(lat)], axis=1)


def enu_from_ecef_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """The rotation (3, 3) taking ECEF directions to east, north, up at a latitude and longitude."""
    lat, lon = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    return np.array([
        [-np.sin(lon), np.cos(lon), 0.0],
        [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
        [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)],
    ])  # fmt: skip


def enu_from_wgs84(lat_lon_alt: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """ENU (N, 3) metres of WGS84 rows ``(lat, lon, alt)`` in the frame of ``origin`` (lat, lon, alt)."""
    origin = np.asarray(origin, np.float64).reshape(3)
    rotation = enu_from_ecef_rotation(origin[0], origin[1])
    return (ecef_from_wgs84(lat_lon_alt) - ecef_from_wgs84(origin)) @ rotation.T


def wgs84_from_enu(enu: np.ndarray, origin: np.ndarray, iterations: int = 10) -> np.ndarray:
    """Inverse of :func:`enu_from_wgs84`: (lat, lon, alt) rows of ENU points (Bowring's
    fixed-point iteration for the latitude; converges to well below a millimetre)."""
    origin = np.asarray(origin, np.float64).reshape(3)
    rotation = enu_from_ecef_rotation(origin[0], origin[1])
    ecef = np.asarray(enu, np.float64).reshape(-1, 3) @ rotation + ecef_from_wgs84(origin)
    x, y, z = ecef.T
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(iterations):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        alt = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + alt)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    alt = p / np.cos(lat) - n
    return np.stack([np.rad2deg(lat), np.rad2deg(lon), alt], axis=1)
