"""Survey results as GIS files: a GeoPackage and a KML of the potholes (points) and their
outlines on the road (polygons), in WGS 84, every column of the survey's rows on each feature;
and each drive's road map as a GeoTIFF of the depth below the road.

Written with pyogrio (GDAL), shapely and rasterio, the optional ``gis`` extra
(``pip install pothole_detector[gis]``); a drive needs GNSS to be placed on the earth (a map
without it is written as NumPy tiles and a picture).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from ..errors import ConfigError
from ..geodesy import local_crs
from .drive import CSV_COLUMNS, DriveSurvey, SurveyPothole
from .roadmap import TILE_CELLS, RoadMap

WGS84 = "EPSG:4326"
# the layers of both files: (name, geometry type)
POINT_LAYER = ("potholes", "Point")
OUTLINE_LAYER = ("outlines", "Polygon")
# the depth (m) drawn black in a road map's picture; the road level is white
PICTURE_DEPTH_M = 0.10


def _libraries() -> tuple[Any, Any]:
    """pyogrio and shapely, or ConfigError saying how to install them."""
    try:
        import pyogrio
        import shapely
    except ImportError:
        raise ConfigError("GIS files need the gis extra: pip install 'pothole_detector[gis]' "
                          "(pyogrio and shapely)") from None
    return pyogrio, shapely


def placed(surveys: Sequence[DriveSurvey]) -> list[SurveyPothole]:
    """The potholes of ``surveys`` that have a position on the earth (GNSS)."""
    return [p for drive in surveys for p in drive.potholes if p.row["lat"] is not None]


def _fields(potholes: Sequence[SurveyPothole]) -> list[np.ndarray]:
    """One array per CSV column over ``potholes``: int64, float64 (None as NaN) or str."""
    arrays = []
    for column in CSV_COLUMNS:
        values = [p.row[column] for p in potholes]
        if all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in values):
            arrays.append(np.array(values, dtype=np.int64))
        elif all(v is None or isinstance(v, (float, int, np.floating)) for v in values):
            arrays.append(np.array([np.nan if v is None else float(v) for v in values]))
        else:
            arrays.append(np.array([str(v) for v in values], dtype=object))
    return arrays


def write_gis(surveys: Sequence[DriveSurvey], folder: str | Path) -> list[Path]:
    """survey.gpkg and survey.kml in ``folder``: layer ``potholes`` (a point per pothole at its
    position) and layer ``outlines`` (its outline on the road at its best view, where
    measured), each feature with every column of the survey's rows, in WGS 84. Returns the
    files written; none when no drive has GNSS. Raises ConfigError without the gis extra."""
    potholes = placed(surveys)
    if not potholes:
        return []
    pyogrio, shapely = _libraries()
    folder = Path(folder)
    points = shapely.points([p.row["lon"] for p in potholes], [p.row["lat"] for p in potholes])
    outlined = [p for p in potholes if len(p.outline_latlon) >= 3]
    polygons = [shapely.polygons(np.asarray(p.outline_latlon)[:, ::-1]) for p in outlined]
    written = []
    for name, driver in (("survey.gpkg", "GPKG"), ("survey.kml", "KML")):
        path = folder / name
        path.unlink(missing_ok=True)
        for (layer, geometry_type), rows, shapes in ((POINT_LAYER, potholes, points),
                                                     (OUTLINE_LAYER, outlined, polygons)):
            if not rows:
                continue
            pyogrio.raw.write(path, shapely.to_wkb(np.asarray(shapes, dtype=object)),
                              _fields(rows), list(CSV_COLUMNS), layer=layer, driver=driver,
                              geometry_type=geometry_type, crs=WGS84,
                              append=path.exists())
        written.append(path)
    return written


# the bands of the road map rasters: name, what it holds
MAP_BANDS = (("depth_below_road_m", "depth below the local road level (m, + into the ground)"),
             ("sigma_m", "standard deviation of the fused height (m)"),
             ("views", "frames that saw the cell"))


def write_maps(surveys: Sequence[DriveSurvey], folder: str | Path) -> list[Path]:
    """Each drive's map of the whole road (DriveSurvey.roadmap) beside the survey: where GNSS
    placed it, ``<bag>_map.tif``, a GeoTIFF (float32, tiled, deflate, NaN where unseen) in
    the drive's local east-north plane (geodesy.local_crs) with the bands of MAP_BANDS, north
    up; else ``<bag>_map.npz`` (the tiles in the motion frame: ``tiles`` (N, 2) tile indices,
    ``depth``, ``sigma``, ``views`` (N, T, T), rows along y, ``cell_m``) and ``<bag>_map.png``,
    a picture of the depth (deeper is darker; grey where unseen, at most 4096 px a side).
    Returns the files written. Raises ConfigError for a GeoTIFF without the gis extra."""
    written: list[Path] = []
    for drive in surveys:
        if drive.roadmap is None:
            continue
        stem = Path(folder) / f"{drive.bag.stem or drive.bag.name}_map"
        if drive.map_origin_latlon is not None:
            written.append(_write_geotiff(drive.roadmap, drive.map_origin_latlon,
                                          stem.with_suffix(".tif")))
        else:
            written += _write_tiles(drive.roadmap, stem)
    return written


def _write_geotiff(roadmap: RoadMap, origin: tuple[float, float], path: Path) -> Path:
    try:
        import rasterio
        from rasterio.transform import from_origin
        from rasterio.windows import Window
    except ImportError:
        raise ConfigError("the road map's GeoTIFF needs the gis extra: pip install "
                          "'pothole_detector[gis]' (rasterio)") from None
    keys = np.array(list(roadmap.tiles))
    low, high = keys.min(axis=0), keys.max(axis=0)
    size = TILE_CELLS
    width, height = (high - low + 1) * size
    transform = from_origin(low[0] * roadmap.tile_m, (high[1] + 1) * roadmap.tile_m,
                            roadmap.cell_m, roadmap.cell_m)
    profile = dict(driver="GTiff", width=int(width), height=int(height), count=len(MAP_BANDS),
                   dtype="float32", crs=rasterio.crs.CRS.from_proj4(local_crs(*origin)),
                   transform=transform, nodata=float("nan"), tiled=True, blockxsize=size,
                   blockysize=size, compress="deflate", predictor=3, BIGTIFF="IF_SAFER",
                   sparse_ok=True)
    with rasterio.open(path, "w", **profile) as raster:
        for band, (name, description) in enumerate(MAP_BANDS, 1):
            raster.set_band_description(band, f"{name}: {description}")
        for (tx, ty), view in roadmap.tile_views():
            window = Window((tx - low[0]) * size, (high[1] - ty) * size, size, size)
            views = np.where(view.views > 0, view.views, np.nan).astype(np.float32)
            for band, values in enumerate((view.depth, view.sigma, views), 1):
                raster.write(values[::-1], band, window=window)
    return path


def _write_tiles(roadmap: RoadMap, stem: Path) -> list[Path]:
    keys, views = zip(*roadmap.tile_views())
    npz = stem.with_suffix(".npz")
    np.savez_compressed(npz, tiles=np.array(keys, dtype=np.int64).reshape(-1, 2),
                        depth=np.array([v.depth for v in views], np.float32),
                        sigma=np.array([v.sigma for v in views], np.float32),
                        views=np.array([v.views for v in views], np.uint16),
                        cell_m=np.float64(roadmap.cell_m))
    index = np.array(keys).reshape(-1, 2)
    low, high = index.min(axis=0), index.max(axis=0)
    step = max(1, math.ceil(max(high - low + 1) * TILE_CELLS / 4096))
    shape = ((high[1] - low[1] + 1) * TILE_CELLS, (high[0] - low[0] + 1) * TILE_CELLS)
    picture = np.full((shape[0] // step + 1, shape[1] // step + 1), 160, np.uint8)
    for (tx, ty), view in zip(keys, views):
        rows = (ty - low[1]) * TILE_CELLS + np.arange(TILE_CELLS)
        cols = (tx - low[0]) * TILE_CELLS + np.arange(TILE_CELLS)
        seen = np.isfinite(view.depth)
        shade = np.clip(255 - np.nan_to_num(view.depth) / PICTURE_DEPTH_M * 255, 0, 255)
        grid_rows, grid_cols = np.meshgrid(rows // step, cols // step, indexing="ij")
        picture[grid_rows[seen], grid_cols[seen]] = shade[seen].astype(np.uint8)
    png = stem.with_suffix(".png")
    cv2.imwrite(str(png), picture[::-1])
    return [npz, png]
