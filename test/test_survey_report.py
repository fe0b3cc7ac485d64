"""report.html: self-contained, the route, the sortable table and the pictures; looked at in
headless Chromium (the screenshot is kept in out/test-artifacts/)."""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from conftest import REPO, rewrite_bag

from pothole_detector.params import Config
from pothole_detector.survey.report import LEAFLET_URL, write_report
from pothole_detector.survey.drive import best_view_picture, survey

CHROMIUM = next((shutil.which(name) for name in ("chromium", "chromium-browser",
                                                "google-chrome") if shutil.which(name)), None)


@pytest.fixture(scope="module")
def report(survey_drive_bags, tmp_path_factory):
    bags, _, _ = survey_drive_bags
    surveys = survey([bags["gnss"], REPO / "bags" / "sample_drive"], Config({"backend": "cpu"}))
    path = tmp_path_factory.mktemp("report") / "report.html"
    write_report(surveys, path, lambda d, p: best_view_picture(
        d.bag, d.topics, p.row["best_stamp_ns"], p.bbox_px, Config()))
    return path, surveys


def test_the_report_holds_route_table_pictures_and_distributions(report):
    path, surveys = report
    text = path.read_text()
    count = sum(len(d.potholes) for d in surveys)
    assert count == 11
    assert text.count('<img src="data:image/png;base64,') == count
    assert len(re.findall(r"<tr><td", text)) == count
    assert text.count('aria-label="route"') == 2 and "east / north (m, from GNSS)" in text
    assert 'aria-label="largest depth"' in text and 'aria-label="area"' in text
    assert "road observed" in text
    # offline, nothing is fetched: the only addresses are the base map's, loaded by script
    addresses = set(re.findall(r"https?://[^\s\"'&]+", text))
    assert addresses <= {"http://www.w3.org/2000/svg", LEAFLET_URL,
                         "https://tile.openstreetmap.org/{z}/{x}/{y}.png"}, addresses


def test_a_gnss_drive_has_a_base_map_with_its_outlines(report):
    """The GNSS drive's map (shown where Leaflet loads) holds the route and each pothole
    with its outline around it; the drive without GNSS has none."""
    path, surveys = report
    maps = re.findall(r'<div class=map [^>]*data-map="([^"]*)"', path.read_text())
    assert len(maps) == 1
    data = json.loads(html.unescape(maps[0]))
    gnss = surveys[0]
    assert len(data["route"]) >= 2 and len(data["potholes"]) == len(gnss.potholes)
    for pothole in data["potholes"]:
        outline = np.array(pothole["outline"])
        assert len(outline) >= 3
        assert outline[:, 0].min() < pothole["lat"] < outline[:, 0].max()
        assert outline[:, 1].min() < pothole["lon"] < outline[:, 1].max()
    # the page's own rules for its drawings and pictures leave Leaflet's panes alone (an
    # opaque background on every svg hid the tiles under the route's overlay)
    style = re.search(r"<style>(.*?)</style>", path.read_text(), re.S).group(1)
    rules = re.findall(r"(?:^|})\s*([^{}]+)\{", style)
    assert not {r.strip() for r in rules} & {"svg", "img", "div", "path"}, rules


def test_a_best_view_picture_is_the_pothole_with_its_box(survey_drive_bags):
    bags, _, _ = survey_drive_bags
    (drive,) = survey([bags["odom"]], Config({"backend": "cpu"}))
    pothole = drive.potholes[0]
    crop = best_view_picture(drive.bag, drive.topics, pothole.row["best_stamp_ns"],
                             pothole.bbox_px, Config())
    assert crop.ndim == 3 and crop.dtype == np.uint8 and max(crop.shape[:2]) <= 240
    red = (crop[..., 0] > 200) & (crop[..., 1] < 100)
    assert red.sum() > 20  # the drawn box


def test_a_best_view_picture_is_found_however_early_its_image_was_logged(tmp_path):
    """The sample drive with every message logged 0.5 s before its stamp: the picture at a
    stamp is still that frame's left image."""
    from pothole_detector.recordings import bags
    from pothole_detector.survey.drive import drive_topics

    source, early = REPO / "bags" / "sample_drive", tmp_path / "early"
    rewrite_bag(source, early, lambda topic, timestamp: timestamp - 500_000_000)
    stamps = [stamp for _, stamp, _ in bags.read_messages(source)]
    topics = drive_topics(early)
    box = (10, 10, 40, 40)
    stamp = sorted(set(stamps))[8]
    np.testing.assert_array_equal(best_view_picture(early, topics, stamp, box, Config()),
                                  best_view_picture(source, topics, stamp, box, Config()))
    with pytest.raises(Exception, match="has no left image"):
        best_view_picture(early, topics, stamp + 1, box, Config())


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (apt install chromium)")
def test_the_report_renders_in_headless_chromium(report):
    path, _ = report
    artifacts = REPO / "out" / "test-artifacts"
    artifacts.mkdir(parents=True, exist_ok=True)
    screenshot = artifacts / "report.png"
    screenshot.unlink(missing_ok=True)
    subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                    "--hide-scrollbars", "--window-size=1280,2400",
                    f"--screenshot={screenshot}", path.as_uri()],
                   capture_output=True, timeout=120, check=True)
    import cv2
    image = cv2.imread(str(screenshot))
    assert image is not None and image.shape[:2] == (2400, 1280)
    blue = (image[..., 0] > 150) & (image[..., 1] < 140) & (image[..., 2] < 100)
    red = (image[..., 2] > 180) & (image[..., 1] < 80) & (image[..., 0] < 80)
    assert blue.sum() > 500, "no route or histogram drawn"
    assert red.sum() > 200, "no high-severity pothole or picture box drawn"
    assert (image.std(axis=2) < 3).mean() < 0.99  # more than a blank page
