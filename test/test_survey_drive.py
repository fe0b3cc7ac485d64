"""The survey: severity, tracking, merging chunks, the outputs, and whole drives of our generator
with known poses (visual odometry, odometry topic, GNSS)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from conftest import SURVEY_ORIGIN_LATLON

from pothole_detector.geodesy import enu_of, latlon_of
from pothole_detector.recordings import bags as recorded
from pothole_detector.survey import drive as drive_module
from pothole_detector.survey.motion import Pose2
from pothole_detector.params import Config
from pothole_detector.survey.drive import (CSV_COLUMNS, FrameCamera, FrameObservation,
                                           MapFrame, MotionSeries, Sighting, assemble,
                                           chunk_spans, drive_topics, map_only_entries,
                                           in_plan_order, observe, observe_here, severity,
                                           survey, survey_pothole, track, utc_time, write_csv,
                                           write_geojson)
from pothole_detector.survey.roadmap import MapPothole, RoadMap, RoadPatch, merged
from pothole_detector.survey.tracking import Track


def _sighting(stamp, forward, left, depth=0.03, area=0.02, observed=True):
    return Sighting(stamp, (0.0, 0.0, 1.0), (forward, left), observed, depth, depth / 2, area,
                    area * depth / 2, (0, 0, 10, 10))


def test_severity_follows_the_fhwa_bounds_and_the_parameters():
    config = Config()
    assert [severity(d, config) for d in (0.01, 0.025, 0.026, 0.05, 0.051)] == \
        ["low", "low", "moderate", "moderate", "high"]
    strict = Config({"severity_moderate_depth_m": 0.01, "severity_high_depth_m": 0.02})
    assert severity(0.015, strict) == "moderate"
    with pytest.raises(Exception, match="severity_high_depth_m must be larger"):
        Config({"severity_moderate_depth_m": 0.06})


def test_severity_by_astm_d6433_takes_depth_and_diameter():
    astm = Config({"severity_standard": "astm_d6433"})
    cases = [(0.02, 0.15, "low"), (0.02, 0.30, "low"), (0.02, 0.60, "moderate"),
             (0.04, 0.15, "low"), (0.04, 0.30, "moderate"), (0.04, 0.60, "high"),
             (0.06, 0.15, "moderate"), (0.06, 0.30, "moderate"), (0.06, 0.60, "high"),
             (0.02, 0.90, "moderate"), (0.03, 0.90, "high"), (0.06, float("nan"), "moderate")]
    assert [severity(depth, astm, diameter) for depth, diameter, _ in cases] == \
        [expected for _, _, expected in cases]


def test_times_are_iso_8601_utc():
    assert utc_time(1_700_000_000_123_456_789) == "2023-11-14T22:13:20.123Z"
    assert utc_time(0) == "1970-01-01T00:00:00.000Z"


def test_tracking_keeps_one_id_per_pothole_as_the_vehicle_moves():
    """Two potholes 1 m and 1.5 m ahead, the vehicle moving 0.1 m a frame: each is seen
    closer every frame; a one-frame mismatch is not reported."""
    observations, poses = [], []
    for index in range(6):
        travelled = 0.1 * index
        sightings = [_sighting(index, 1.0 - travelled, 0.2), _sighting(index, 1.5 - travelled,
                                                                       -0.3)]
        if index == 3:
            sightings.append(_sighting(index, 0.7, 0.9))
        observations.append(FrameObservation(index, tuple(sightings), (0.2, 2.0), None))
        poses.append(Pose2(travelled, 0.0, 0.0))
    tracks = [t for t in track(observations, poses, Config()) if len(t.sightings) > 1]
    assert len(tracks) == 2 and len(track(observations, poses, Config())) == 3
    for tracked, expected in zip(tracks, ([1.0, 0.2], [1.5, -0.3])):
        assert len(tracked.sightings) == 6
        np.testing.assert_allclose(tracked.position, expected, atol=1e-9)
        assert tracked.best().road_xy[0] == pytest.approx(expected[0] - 0.5)


def test_the_best_view_is_the_nearest_inside_the_observed_range():
    observations = [FrameObservation(i, (_sighting(i, f, 0.0, observed=o),), (0.5, 2.0), None)
                    for i, (f, o) in enumerate([(1.5, True), (0.9, True), (0.3, False)])]
    poses = [Pose2(1.5 - f, 0.0, 0.0) for f in (1.5, 0.9, 0.3)]
    (tracked,) = track(observations, poses, Config())
    assert tracked.best().stamp_ns == 1


def test_chunk_spans_split_the_bag_by_time_and_merged_chunks_keep_each_frame_once():
    from conftest import REPO
    bag = REPO / "bags" / "sample_drive"
    count, spans = chunk_spans(bag, drive_topics(bag), Config({"chunk_frames": 5}))
    period = 100_000_000  # the sample drive's frames are 0.1 s apart
    assert count == 16 and len(spans) == 4
    assert all(a.stop_ns == b.start_ns for a, b in zip(spans, spans[1:]))
    assert all(abs(span.lead_ns - 4 * period) < period for span in spans)
    assert spans[0].start_ns == 1_700_000_000_000_000_000
    assert spans[-1].stop_ns > 1_700_000_000_000_000_000 + 15 * period
    first = FrameObservation(40, (), (0.5, 1.0), None)
    again = FrameObservation(40, (), (0.5, 1.0), Pose2(0.1, 0.0, 0.0))
    other = FrameObservation(30, (), (0.5, 1.0), Pose2(0.1, 0.0, 0.0))
    drive = assemble("bag", [other, first, again], MotionSeries(), Config())
    assert drive.frames == 2
    assert drive.route_xy[-1] == pytest.approx([0.1, 0.0])
    assert drive.observed_length_m == pytest.approx(0.6)


def test_csv_has_exactly_the_columns_and_geojson_needs_gnss(tmp_path):
    observations = [FrameObservation(i, (_sighting(i, 1.0 - 0.1 * i, 0.0),), (0.2, 2.0),
                                     Pose2(0.1, 0.0, 0.0) if i else None) for i in range(3)]
    drive = assemble(tmp_path / "drive", observations, MotionSeries(), Config())
    write_csv([drive], tmp_path / "survey.csv")
    with open(tmp_path / "survey.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == 1
    assert rows[0]["lat"] == "" and rows[0]["severity"] == "moderate"
    assert not write_geojson([drive], tmp_path / "survey.geojson")
    assert not (tmp_path / "survey.geojson").exists()


def _truth(scenes, samples, kind):
    """(position in the survey's motion frame, depth, frames seen) of each generated pothole."""
    start = scenes[0].camera_y_m
    truths = []
    for index, shape in enumerate(scenes[0].potholes, start=1):
        seen = sum(int((sample.labels == index).any()) for sample in samples)
        forward, left = shape.y_m - start, -shape.x_m
        position = (-left, forward) if kind == "gnss" else (forward, left)
        truths.append((np.array(position), shape.depth_m, seen))
    return truths


def _extents(shape):
    """(length along the drive, width across it) m of a generated pothole's ellipse."""
    angle = np.deg2rad(shape.angle_deg)
    along = np.hypot(shape.a_m * np.sin(angle), shape.b_m * np.cos(angle))
    across = np.hypot(shape.a_m * np.cos(angle), shape.b_m * np.sin(angle))
    return 2 * along, 2 * across


@pytest.mark.parametrize("kind", ["none", "odom", "gnss"])
def test_a_drive_reports_each_pothole_once_where_it_is(survey_drive_bags, kind, tmp_path):
    bags, scenes, samples = survey_drive_bags
    (drive,) = survey([bags[kind]], Config({"backend": "cpu"}))
    source = {"none": "visual odometry", "odom": "odometry (/odom)",
              "gnss": "GNSS (/gnss/fix)"}[kind]
    assert drive.motion_source == source and drive.failed == 0 and drive.frames == 48
    truths = _truth(scenes, samples, kind)
    assert all(seen >= 3 for _, _, seen in truths)
    found = [np.array([p.row["odom_x_m"], p.row["odom_y_m"]]) for p in drive.potholes]
    assert len(found) == len(truths), [f.round(2) for f in found]
    for pothole, position in zip(drive.potholes, found):
        gaps = [np.linalg.norm(position - truth) for truth, _, _ in truths]
        nearest = int(np.argmin(gaps))
        assert gaps[nearest] < 0.2, (pothole.row, truths[nearest])
        assert pothole.row["severity"] == severity(truths[nearest][1], Config())
        assert pothole.row["sightings"] >= 3
        length, width = _extents(scenes[0].potholes[nearest])
        assert abs(pothole.row["length_m"] / length - 1) < 0.2, (pothole.row, length)
        assert abs(pothole.row["width_m"] / width - 1) < 0.2, (pothole.row, width)
        assert pothole.row["best_time_utc"] == utc_time(pothole.row["best_stamp_ns"])
    matched = {int(np.argmin([np.linalg.norm(f - t) for t, _, _ in truths])) for f in found}
    assert matched == set(range(len(truths)))  # no duplicate, none missed
    if kind == "gnss":
        assert write_geojson([drive], tmp_path / "survey.geojson")
        features = json.loads((tmp_path / "survey.geojson").read_text())["features"]
        points = [f for f in features if f["geometry"]["type"] == "Point"]
        outlines = [f for f in features if f["geometry"]["type"] == "Polygon"]
        assert len(points) == len(outlines) == len(truths)
        for feature in points:
            lon, lat = feature["geometry"]["coordinates"]
            east_north = enu_of(np.array([lat]), np.array([lon]), *SURVEY_ORIGIN_LATLON)[0]
            assert min(np.linalg.norm(east_north - t) for t, _, _ in truths) < 0.2
        for feature, shape_truth in zip(outlines, drive.potholes):
            ring = np.array(feature["geometry"]["coordinates"][0])
            corners = enu_of(ring[:, 1], ring[:, 0], *SURVEY_ORIGIN_LATLON)
            x, y = corners[:, 0], corners[:, 1]
            area = abs(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1])) / 2
            assert abs(area / shape_truth.row["area_m2"] - 1) < 0.3, (area, shape_truth.row)
    else:
        assert drive.route_latlon is None


def test_the_map_measures_depth_better_than_the_best_single_view(survey_drive_bags, tmp_path):
    """Twelve potholes on two drives of our generator (the survey drive, and its mirror with
    other depths and another texture): each is one entry measured in the fused road map, and
    the map's depth errs less than the best single view's (median over the twelve)."""
    from dataclasses import replace

    from pothole_detector.recordings.writing import write_drive_bag
    from pothole_detector.evaluation.synthetic import render

    bags, scenes, _ = survey_drive_bags
    mirrored = [replace(s, texture_seed=21, potholes=tuple(
        replace(p, x_m=-p.x_m, depth_m=0.8 * p.depth_m + 0.01) for p in s.potholes))
        for s in scenes]
    forward = [s.camera_y_m - scenes[0].camera_y_m for s in scenes]
    write_drive_bag(tmp_path / "mirrored", forward, [render(s) for s in mirrored],
                             "odom")
    map_errors, view_errors = [], []
    for bag, drive_scenes in ((bags["odom"], scenes), (tmp_path / "mirrored", mirrored)):
        (drive,) = survey([bag], Config({"backend": "cpu"}))
        start = drive_scenes[0].camera_y_m
        truths = [(np.array([p.y_m - start, -p.x_m]), p.depth_m)
                  for p in drive_scenes[0].potholes]
        assert len(drive.potholes) == len(truths) and drive.left_out == 0
        matched = set()
        for pothole in drive.potholes:
            position = np.array([pothole.row["odom_x_m"], pothole.row["odom_y_m"]])
            gaps = [np.linalg.norm(position - truth) for truth, _ in truths]
            nearest = int(np.argmin(gaps))
            assert gaps[nearest] < 0.05 and pothole.row["map_views"] >= 5, pothole.row
            matched.add(nearest)
            depth = truths[nearest][1]
            map_errors.append(abs(pothole.row["max_depth_m"] - depth))
            view_errors.append(abs(pothole.best_view_depth_m - depth))
        assert matched == set(range(len(truths)))
    assert len(map_errors) == 12
    assert np.median(map_errors) < np.median(view_errors), (map_errors, view_errors)


def test_visual_odometry_drift_on_the_drive(survey_drive_bags):
    """The generator's drive moves 2.35 m straight ahead: visual odometry ends within 1 % of
    the distance along the road and 1.5 % across it (docs/accuracy.md has the measured
    drift)."""
    bags, scenes, _ = survey_drive_bags
    (drive,) = survey([bags["none"]], Config({"backend": "cpu"}))
    travelled = scenes[-1].camera_y_m - scenes[0].camera_y_m
    along, across = drive.route_xy[-1] - [travelled, 0.0]
    assert abs(along) < 0.01 * travelled and abs(across) < 0.015 * travelled, drive.route_xy[-1]


@pytest.mark.parametrize("motion", ["none", "odom"])
def test_chunked_survey_gives_the_unchunked_one(survey_drive_bags, motion, monkeypatch):
    """Chunks read their own part of the bag, odometry included, with the readers of the
    reads before them: the chunked survey after the whole one opens the bag no more."""
    bags, _, _ = survey_drive_bags
    whole = survey([bags[motion]], Config({"backend": "cpu"}))[0]
    opened = []
    monkeypatch.setattr(recorded, "open_bag", lambda path: opened.append(path))
    split = survey([bags[motion]], Config({"backend": "cpu", "chunk_frames": 17}))[0]
    assert opened == []
    assert split.motion_source == whole.motion_source
    np.testing.assert_allclose(split.route_xy, whole.route_xy, atol=0.02)
    assert_same_potholes(split, whole)


def test_chunk_runners_give_each_plan_once_its_chunks_are_done():
    """Plans of 2, 0, 1 and 2 chunks (numbered plan after plan) whose chunks finish in the
    order 0, 3, 1, 2, 4: plan 0 comes (with the empty plan 1 after it) as soon as chunk 1 is
    done, before chunk 2 is; plan 2 then, plan 3 last."""
    pulled, given = [], []

    def finished():
        for chunk in (0, 3, 1, 2, 4):
            pulled.append(chunk)
            yield chunk

    for plan in in_plan_order([2, 0, 1, 2], finished()):
        given.append((plan, tuple(pulled)))
    assert given == [(0, (0, 3, 1)), (1, (0, 3, 1)), (2, (0, 3, 1, 2)), (3, (0, 3, 1, 2, 4))]
    assert list(in_plan_order([0, 0], iter(()))) == [0, 1]


def test_a_bag_is_assembled_while_the_bags_after_it_are_observed(survey_drive_bags,
                                                                  monkeypatch):
    """survey takes each bag's results from its chunk runner as they come: the first bag is
    assembled before the runner observes the second; the runner is run to its end."""
    bags, _, _ = survey_drive_bags
    events = []
    assembling = drive_module.assemble
    monkeypatch.setattr(drive_module, "assemble", lambda bag, *rest, **named: (
        events.append(("assembled", bag)), assembling(bag, *rest, **named))[1])

    def runner(plans, config, progress):
        for plan in plans:
            events.append(("observed", plan.bag))
            yield next(observe_here([plan], config, progress))
        events.append(("ended", None))

    drives = [bags["odom"], bags["none"]]
    surveyed = survey(drives, Config({"backend": "cpu"}), chunks=runner)
    assert [event for event, _ in events] == ["observed", "assembled", "observed",
                                              "assembled", "ended"]
    assert [bag for _, bag in events[:4]] == [drives[0]] * 2 + [drives[1]] * 2
    assert [len(d.potholes) for d in surveyed] == [6, 6]


@pytest.mark.parametrize("motion", ["odom", "gnss"])
def test_reading_ahead_observes_what_one_reader_does(survey_drive_bags, motion, monkeypatch):
    """A chunk (24 frames) read in blocks of five frames by three threads, and by two worker
    processes: the same frames, sightings and motion messages as read in the pipeline's
    thread."""
    monkeypatch.setattr(recorded, "READ_BLOCK_FRAMES", 5)
    bags, _, _ = survey_drive_bags
    topics = drive_topics(bags[motion])
    config = Config({"backend": "cpu", "chunk_frames": 30})
    _, spans = chunk_spans(bags[motion], topics, config)
    alone = observe(bags[motion], topics, config.replace(read_threads=1), spans[1])
    ahead = observe(bags[motion], topics, config.replace(read_threads=3), spans[1])
    assert ahead == alone
    assert observe(bags[motion], topics, config.replace(read_processes=2), spans[1]) == alone
    assert len(alone[0]) == 24 and len(alone[1].odometry) + len(alone[1].gnss) >= 24


def test_chunks_in_worker_processes_give_the_sequential_survey(survey_drive_bags):
    """survey --jobs: chunks of two drives in two worker processes, merged per drive."""
    from conftest import REPO
    bags, _, _ = survey_drive_bags
    drives = [bags["none"], REPO / "bags" / "sample_drive"]
    seen = []
    in_workers = survey(drives, Config({"backend": "cpu", "chunk_frames": 12,
                                             "read_processes": 2}), jobs=2,
                        progress=lambda done, total: seen.append((done, total)))
    here = survey(drives, Config({"backend": "cpu"}))
    assert [len(d.potholes) for d in in_workers] == [6, 5]
    assert seen[-1] == (6, 6)  # 48 frames in 4 chunks, 16 in 2
    for split, whole in zip(in_workers, here):
        assert (split.frames, split.failed) == (whole.frames, whole.failed)
        assert_same_potholes(split, whole)


def assert_same_potholes(split, whole):
    """A chunk starts with a fresh road fit (and the backends' matchers differ in a few
    pixels), so frames may differ a little: the same potholes and severities, first seen
    within two frames, sightings within two, positions within 2 cm and measurements within
    10 % (so the severity where the depth is more than 1 mm from a class bound)."""
    bounds = np.array([Config().severity_moderate_depth_m, Config().severity_high_depth_m])
    assert len(split.potholes) == len(whole.potholes)
    for a, b in zip(split.potholes, whole.potholes):
        a, b = a.row, b.row
        assert a["pothole_id"] == b["pothole_id"]
        if np.abs(bounds - b["max_depth_m"]).min() > 0.001:
            assert a["severity"] == b["severity"]
        assert abs(a["first_stamp_ns"] - b["first_stamp_ns"]) <= 200_000_000
        assert abs(a["sightings"] - b["sightings"]) <= 2
        assert math.hypot(a["odom_x_m"] - b["odom_x_m"], a["odom_y_m"] - b["odom_y_m"]) < 0.02
        for key in ("max_depth_m", "area_m2"):
            assert a[key] == pytest.approx(b[key], rel=0.1), key


def test_latlon_of_gnss_drive_truth_round_trips():
    east_north = np.array([[1.0, 2.0], [-3.0, 0.5]])
    back = latlon_of(east_north, *SURVEY_ORIGIN_LATLON)
    np.testing.assert_allclose(enu_of(back[:, 0], back[:, 1], *SURVEY_ORIGIN_LATLON),
                               east_north, atol=1e-6)


def test_survey_command_writes_the_table_and_the_report(tmp_path):
    from conftest import REPO

    out = tmp_path / "survey"
    done = subprocess.run(
        [sys.executable, "-m", "pothole_detector.cli", "survey",
         str(REPO / "bags" / "sample_drive"), "--out", str(out), "--backend", "cpu",
         "--read-processes", "2"],
        capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "sample_drive: 16 frames (0 failed), 5 potholes" in done.stdout
    with open(out / "survey.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 5 and {r["bag"] for r in rows} == {"sample_drive"}
    assert (out / "report.html").stat().st_size > 10_000
    assert not (out / "survey.geojson").exists()
    missing = subprocess.run(
        [sys.executable, "-m", "pothole_detector.cli", "survey", str(tmp_path / "nope"),
         "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1


def test_the_best_view_shows_the_pothole_whole():
    """The nearest sighting is cut by the image border: the nearest whole one is the best."""
    cut = Sighting(2, (0.0, 0.0, 1.0), (0.3, 0.0), True, 0.01, 0.005, 0.004, 1e-5,
                   (10, 300, 60, 359), whole=False)
    observations = [FrameObservation(i, (_sighting(i, f, 0.0),), (0.2, 2.0), None)
                    for i, f in enumerate([1.2, 0.8])]
    observations.append(FrameObservation(2, (cut,), (0.2, 2.0), None))
    poses = [Pose2(1.2 - f, 0.0, 0.0) for f in (1.2, 0.8, 0.3)]
    (tracked,) = track(observations, poses, Config())
    assert tracked.best().stamp_ns == 1


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("pothole_detector.backend").backend.gpu_available(),
                    reason="needs CuPy and a CUDA device")
def test_the_survey_on_the_gpu_gives_the_cpu_survey():
    from conftest import REPO

    drive = REPO / "bags" / "sample_drive"
    on_gpu = survey([drive], Config({"backend": "gpu", "matcher": "census"}))[0]
    on_cpu = survey([drive], Config({"backend": "cpu", "matcher": "census"}))[0]
    assert len(on_gpu.potholes) == 5
    assert_same_potholes(on_gpu, on_cpu)


def _level_camera() -> FrameCamera:
    """A level camera 1 m above the road looking along it (f 500 px, 640x480)."""
    return FrameCamera((0.0, 1.0, 0.0), ((0.0, 0.0, 1.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0)),
                       500.0, 319.5, 239.5, 640, 480)


def test_a_frame_camera_projects_road_points_to_their_pixels():
    points, pixels = _level_camera().project(np.array([[2.0, 0.0], [4.0, 1.0]]))
    np.testing.assert_allclose(points, [[0.0, 1.0, 2.0], [-1.0, 1.0, 4.0]])
    np.testing.assert_allclose(pixels, [[319.5, 489.5], [194.5, 364.5]])


def test_pieces_of_a_map_depression_merge_into_one():
    square = np.array([[0.0, 0.0], [0.1, 0.0], [0.1, 0.1], [0.0, 0.1]])
    a = MapPothole((0.05, 0.05), square, 0.02, 0.01, 0.001, 0.03, 0.0003, 3, 5, 0.1)
    b = MapPothole((0.35, 0.05), square + [0.3, 0.0], 0.03, 0.02, 0.002, 0.01, 0.0002, 1, 7, 0.1)
    both = merged([a, b])
    assert both.area_m2 == pytest.approx(0.04) and both.volume_m3 == pytest.approx(0.0005)
    assert both.mean_depth_m == pytest.approx(0.0125) and both.max_depth_m == 0.03
    assert both.max_depth_sigma_m == 0.002 and both.cells == 4 and both.views == 7
    np.testing.assert_allclose(both.xy, (0.125, 0.05))
    assert len(both.outline) == 4 and both.outline[:, 0].max() == pytest.approx(0.4)


def test_a_pothole_only_the_views_together_show_gets_one_entry():
    """A 1.5 cm dip that the detector reported in one frame only becomes one entry, seen by
    every frame whose road samples reach it (that frame's sighting with its own measures: 11
    of the 13 frames, the first two searched to 4.6 m ahead only), its best view
    the nearest that shows it whole; a dip under an entry's pothole adds none, nor does one at
    the edge of the seen road (it may be the road falling away), and none is made from fewer
    views than min_sightings."""
    overview = RoadMap(0.1, 0.5, 3.0, 0.004, 0.0005, 0.008)
    xs, ys = np.meshgrid(np.arange(0.0, 8.0, 0.04), np.arange(-1.5, 1.5, 0.04))
    xy = np.stack([xs.ravel(), ys.ravel()], axis=1)
    depth = np.where(np.hypot(xy[:, 0] - 5.0, xy[:, 1] - 0.3) < 0.2, 0.015, 0.0)
    depth[np.hypot(xy[:, 0] - 2.0, xy[:, 1] + 0.5) < 0.2] = 0.02
    depth[np.hypot(xy[:, 0] - 5.0, xy[:, 1] + 1.5) < 0.2] = 0.02  # at the seen road's edge
    for _ in range(6):
        overview.add(xy, depth, np.full(len(xy), 0.002))
    assert sorted((p.xy[1] > -1, p.enclosed) for p in overview.potholes()) == [
        (False, False), (True, True), (True, True)]
    poses = [Pose2(x, 0.0, 0.0) for x in [0.25 * i for i in range(12)] + [2.9]]
    forward, left = np.meshgrid(np.arange(10, 46), np.arange(-15, 15), indexing="ij")
    searched = np.stack([forward.ravel(), left.ravel()], axis=1).astype(np.int16)
    patch = RoadPatch(searched, 0.1, np.zeros(len(searched), np.float16),
                      np.full(len(searched), 0.002, np.float16))  # 1.0-4.6 m ahead
    frames = [FrameObservation(i, (), (1.0, 3.0), None, camera=_level_camera(),
                               overview=patch) for i in range(13)]
    entered = Track(1, [_sighting(0, 2.0, -0.5)], [np.array([2.0, -0.5])])
    # entries far from the dip on either side of it: positions, not an outline around it
    others = [Track(3 + k, [_sighting(0, x, y)], [np.array([x, y])])
              for k, (x, y) in enumerate([(7.5, -1.2), (7.5, 1.4)])]
    spare = Track(2, [_sighting(5, 3.77, 0.31, depth=0.014, observed=False)],
                  [np.array([5.02, 0.31])])
    place = MapFrame(None, np.array([[p.x, p.y] for p in poses]))
    config = Config()
    (made,) = map_only_entries(overview, [entered, spare, *others],
                               [([t], t, None) for t in [entered, *others]], frames, poses,
                               place, config)
    own, together, depression = made
    assert own == [spare]
    np.testing.assert_allclose(depression.xy, (5.0, 0.3), atol=0.05)
    assert [s.stamp_ns for s in together.sightings] == list(range(2, 13))
    assert together.sightings[3] is spare.sightings[0]
    assert [s.observed for s in together.sightings] == [i >= 8 for i in range(2, 13)]
    assert [s.whole for s in together.sightings] == [i < 12 for i in range(2, 13)]
    best = together.best()
    assert best.stamp_ns == 11 and best.road_xy == pytest.approx((2.25, 0.3), abs=0.05)
    x0, y0, x1, y1 = best.bbox_px
    assert 0 < x0 < 319.5 - 500 * 0.3 / 2.25 < x1 < 319.5 and 239.5 + 500 / 2.25 < y1 <= 479
    row = survey_pothole(1, "drive", together, depression, place, config).row
    assert row["sightings"] == 11 and row["best_stamp_ns"] == 11
    assert row["max_depth_m"] == pytest.approx(0.015, abs=0.002)
    assert row["odom_x_m"] == pytest.approx(5.0, abs=0.05)
    assert map_only_entries(overview, [entered], [], frames, poses, place,
                            config.replace(min_sightings=12)) == []
