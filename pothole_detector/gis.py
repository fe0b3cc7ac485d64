"""Survey results as GIS files: a GeoPackage and a KML of the potholes (points) and their
outlines on the road (polygons), in WGS 84, every column of the survey's rows on each feature.

Written with pyogrio (GDAL) and shapely, the optional ``gis`` extra
(``pip install pothole_detector[gis]``); a drive needs GNSS to be placed on the earth.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .errors import ConfigError
from .survey import CSV_COLUMNS, DriveSurvey, SurveyPothole

WGS84 = "EPSG:4326"
# the layers of both files: (name, geometry type)
POINT_LAYER = ("potholes", "Point")
OUTLINE_LAYER = ("outlines", "Polygon")


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
