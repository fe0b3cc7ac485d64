"""The survey's GeoPackage, KML and road map files (survey/gis.py), read back with the
libraries that wrote them."""

from __future__ import annotations

import numpy as np
import pytest

pyogrio = pytest.importorskip("pyogrio")
shapely = pytest.importorskip("shapely")

from pothole_detector.survey.gis import MAP_BANDS, write_gis, write_maps  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.survey.drive import CSV_COLUMNS, survey  # noqa: E402


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


def test_the_road_map_geotiff_puts_each_pothole_on_its_depression(survey_drive_bags, tmp_path):
    """GDAL's own transformation from WGS 84 into the GeoTIFF's plane finds each pothole (the
    survey's lat, lon) on cells of the map that lie well below the road (a cell of 10 cm
    averages a small pothole's floor with its rim)."""
    rasterio = pytest.importorskip("rasterio")
    from rasterio.warp import transform

    bags, _, _ = survey_drive_bags
    (drive,) = survey([bags["gnss"]], Config({"backend": "cpu"}))
    (path,) = write_maps([drive], tmp_path)
    assert path.name == "drive_gnss_map.tif"
    with rasterio.open(path) as raster:
        assert raster.count == len(MAP_BANDS) and raster.dtypes[0] == "float32"
        assert raster.descriptions[0].startswith("depth_below_road_m")
        assert raster.crs.is_projected and raster.res == (0.1, 0.1)
        depth, views = raster.read(1), raster.read(3)
        seen = np.isfinite(depth)
        assert seen.sum() * 0.01 > 3.0 and np.nanmedian(views) >= 5  # m2 of road seen
        assert abs(np.nanmedian(depth)) < 0.003
        east, north = transform("EPSG:4326", raster.crs,
                                [p.row["lon"] for p in drive.potholes],
                                [p.row["lat"] for p in drive.potholes])
        for pothole, x, y in zip(drive.potholes, east, north):
            row, col = raster.index(x, y)
            around = depth[row - 1:row + 2, col - 1:col + 2]
            assert np.nanmax(around) > max(0.2 * pothole.row["max_depth_m"],
                                           10 * abs(np.nanmedian(depth))), pothole.row


def test_a_map_without_gnss_is_written_as_tiles_and_a_picture(survey_drive_bags, tmp_path):
    cv2 = pytest.importorskip("cv2")
    bags, _, _ = survey_drive_bags
    (drive,) = survey([bags["odom"]], Config({"backend": "cpu"}))
    npz, png = write_maps([drive], tmp_path)
    tiles = np.load(npz)
    assert tiles["depth"].shape[0] == len(tiles["tiles"]) == len(drive.roadmap.tiles)
    assert float(tiles["cell_m"]) == 0.1
    picture = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    assert picture is not None and (picture < 200).any() and (picture > 240).any()
