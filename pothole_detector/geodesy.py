"""Latitude and longitude to a local east-north plane about a reference point and back: the
plane of our surveys' positions and of their map rasters (:func:`local_crs` names it for GIS
files)."""

from __future__ import annotations

import math

import numpy as np

# the sphere of the local plane (m): WGS 84's semi-major axis
EARTH_RADIUS_M = 6_378_137.0


def enu_of(lat_deg: np.ndarray, lon_deg: np.ndarray, lat0_deg: float,
           lon0_deg: float) -> np.ndarray:
    """(N, 2) east, north (m) of latitudes/longitudes about a reference (local tangent
    plane; metres-accurate over a few kilometres)."""
    lat0 = math.radians(lat0_deg)
    east = np.radians(np.asarray(lon_deg) - lon0_deg) * EARTH_RADIUS_M * math.cos(lat0)
    north = np.radians(np.asarray(lat_deg) - lat0_deg) * EARTH_RADIUS_M
    return np.stack([east, north], axis=-1)


def latlon_of(enu: np.ndarray, lat0_deg: float, lon0_deg: float) -> np.ndarray:
    """(N, 2) latitude, longitude (deg) of east, north offsets (m): inverse of :func:`enu_of`."""
    enu = np.asarray(enu, dtype=np.float64).reshape(-1, 2)
    lat = lat0_deg + np.degrees(enu[:, 1] / EARTH_RADIUS_M)
    lon = lon0_deg + np.degrees(enu[:, 0] / (EARTH_RADIUS_M * math.cos(math.radians(lat0_deg))))
    return np.stack([lat, lon], axis=-1)


def local_crs(lat0_deg: float, lon0_deg: float) -> str:
    """The PROJ definition of the plane of :func:`enu_of` about (``lat0_deg``, ``lon0_deg``):
    an equirectangular projection true at the reference's latitude, east and north in metres,
    for GIS files whose coordinates are our east, north."""
    return (f"+proj=eqc +lat_ts={lat0_deg:.9f} +lat_0={lat0_deg:.9f} +lon_0={lon0_deg:.9f} "
            f"+x_0=0 +y_0=0 +R={EARTH_RADIUS_M:.1f} +units=m +no_defs")
