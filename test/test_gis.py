"""The survey's GeoPackage and KML (gis.py), read back with the libraries that wrote them."""

from __future__ import annotations

import numpy as np
import pytest

pyogrio = pytest.importorskip("pyogrio")
shapely = pytest.importorskip("shapely")

from pothole_detector.gis import write_gis  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.survey import CSV_COLUMNS, survey  # noqa: E402


def test_a_gnss_drive_gives_points_and_outlines_in_wgs84(survey_drive_bags, tmp_path):
    bags, scenes, _ = survey_drive_bags
    (drive,) = survey([bags["gnss"]], Config({"backend": "cpu"}))
    assert len(drive.potholes) == len(scenes[0].potholes)
    written = write_gis([drive], tmp_path)
    assert [p.name for p in written] == ["survey.gpkg", "survey.kml"]
    layers = {name: kind for name, kind in pyogrio.list_layers(tmp_path / "survey.gpkg")}
    assert layers == {"potholes": "Point", "outlines": "Polygon"}
    meta, _, points, fields = pyogrio.raw.read(tmp_path / "survey.gpkg", layer="potholes")
    assert meta["crs"] == "EPSG:4326" and list(meta["fields"]) == list(CSV_COLUMNS)
    assert len(points) == len(drive.potholes)
    depth = fields[list(CSV_COLUMNS).index("max_depth_m")]
    np.testing.assert_allclose(depth, [p.row["max_depth_m"] for p in drive.potholes])
    _, _, outlines, _ = pyogrio.raw.read(tmp_path / "survey.gpkg", layer="outlines")
    assert len(outlines) == len(drive.potholes)
    for point, outline in zip(shapely.from_wkb(points), shapely.from_wkb(outlines)):
        assert outline.is_valid and outline.contains(point)
    kml_layers = [name for name, _ in pyogrio.list_layers(tmp_path / "survey.kml")]
    assert kml_layers == ["potholes", "outlines"]
    meta, _, kml_points, _ = pyogrio.raw.read(tmp_path / "survey.kml", layer="potholes")
    assert len(kml_points) == len(drive.potholes) and meta["crs"] == "EPSG:4326"


def test_without_gnss_nothing_is_written(survey_drive_bags, tmp_path):
    bags, _, _ = survey_drive_bags
    (drive,) = survey([bags["odom"]], Config({"backend": "cpu"}))
    assert write_gis([drive], tmp_path) == []
    assert not list(tmp_path.iterdir())
