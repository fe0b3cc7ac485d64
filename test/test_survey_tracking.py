"""Pothole tracking on the road plane (survey/tracking.py), shared by the survey and the node."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from pothole_detector.survey.motion import Pose2, RoadFrame
from pothole_detector.stages.measure import Pothole
from pothole_detector.calibration import StereoCalibration
from pothole_detector.survey.tracking import (MAX_ID, PotholeTracker, Sighting, Track, combined,
                                              footprints, merge_overlapping, pieces, radius_of,
                                              sightings_of)

# a camera 1 m above a level road, looking ahead (forward = z, left = -x, up = -y), f 500 px
LEVEL_ROAD = RoadFrame(np.array([0.0, 1.0, 0.0]),
                       np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]))
LEVEL_CAMERA = StereoCalibration(f=500.0, baseline=0.1, cx=320.0, cy=240.0)


def _sighting(forward: float, left: float, area: float = 0.03, depth: float = 0.05,
              stamp: int = 0, box: tuple[int, int, int, int] = (10, 10, 20, 20)) -> Sighting:
    return Sighting(stamp, (0.0, 0.0, 1.0), (forward, left), True, depth, 0.03, area,
                    area * 0.03, box)


def test_a_pothole_keeps_its_id_while_it_stays_in_view():
    tracker = PotholeTracker(0.25, forget_frames=2)
    assert tracker.update([_sighting(2.0, 0.0), _sighting(3.0, 1.0)], Pose2()) == [1, 2]
    # the vehicle moved 5 cm (no ego-motion given); another order, and a new one appears
    assert tracker.update([_sighting(2.95, 1.0), _sighting(2.0, -1.0), _sighting(1.95, 0.0)],
                          Pose2()) == [2, 3, 1]
    # with the ego-motion the road positions stay put though the vehicle moved 1 m
    moved = Pose2(1.0, 0.0, 0.0)
    assert tracker.update([_sighting(0.95, 0.0), _sighting(1.95, 1.0), _sighting(5.0, 0.0)],
                          moved) == [1, 2, 4]
    tracker.reset()
    assert tracker.update([_sighting(0.95, 0.0)], moved) == [5]
    assert [t.id for t in tracker.tracks] == [1, 2, 3, 4, 5]


def test_a_track_out_of_view_for_longer_than_forget_frames_takes_no_sighting():
    tracker = PotholeTracker(0.25, forget_frames=2)
    assert tracker.update([_sighting(1.0, 0.0)], Pose2()) == [1]
    tracker.skip()
    assert tracker.update([_sighting(1.0, 0.0)], Pose2()) == [1]
    for _ in range(3):
        tracker.update([], Pose2())
    assert tracker.update([_sighting(1.0, 0.0)], Pose2()) == [2]


def test_ids_wrap_after_the_label_images_largest_and_the_node_keeps_no_history():
    tracker = PotholeTracker(0.25, 30, max_id=MAX_ID, keep_history=False)
    tracker._next = MAX_ID
    assert tracker.update([_sighting(1.0, 0.0), _sighting(5.0, 0.0)], Pose2()) == [MAX_ID, 1]
    assert tracker.tracks == []


def test_sightings_are_on_the_road_frame_and_a_nan_centroid_matches_nothing():
    pothole = Pothole(label=1, pixels=100, area_m2=0.03, max_depth_m=0.05, mean_depth_m=0.03,
                      volume_m3=0.001, centroid_cam_m=(0.2, 0.5, 2.0), bbox_px=(0, 5, 9, 9))
    lost = Pothole(label=2, pixels=10, area_m2=0.01, max_depth_m=0.05, mean_depth_m=0.03,
                   volume_m3=0.001, centroid_cam_m=(np.nan, 0.5, 2.0), bbox_px=(5, 5, 9, 9))

    class Result:
        potholes = [pothole, lost]
        observed_range_m = (0.5, 3.0)

    plane = LEVEL_ROAD
    seen = sightings_of(7, Result(), plane, 40, 30)
    assert seen[0].road_xy == (2.0, -0.2) and seen[0].observed and not seen[0].whole
    tracker = PotholeTracker(0.25, 30)
    assert tracker.update(seen, Pose2()) == [1, 2]
    assert tracker.update(seen, Pose2()) == [1, 3]


def test_pieces_of_one_depression_whose_discs_touch_are_one_pothole():
    """Discs of 0.03 m2 have a radius of 0.098 m: centres 0.15 m apart touch, 0.25 m do not;
    touching chains."""
    found = pieces([_sighting(2.0, 0.0), _sighting(2.0, 0.15), _sighting(2.0, 0.30),
                    _sighting(2.0, 0.60)])
    assert found == [[0, 1, 2], [3]]
    one = combined([_sighting(2.0, 0.0, 0.01, 0.04, box=(5, 6, 10, 12)),
                    _sighting(2.0, 0.2, 0.03, 0.07, box=(8, 2, 30, 9))])
    assert one.area_m2 == 0.04 and one.max_depth_m == 0.07
    assert abs(one.volume_m3 - 0.04 * 0.03) < 1e-15 and one.bbox_px == (5, 2, 30, 12)
    assert abs(one.road_xy[1] - 0.15) < 1e-12


def test_pieces_in_a_frame_take_one_id_and_one_sighting():
    tracker = PotholeTracker(0.25, forget_frames=2)
    assert tracker.update([_sighting(2.0, 0.0), _sighting(2.0, 0.15), _sighting(4.0, 0.0)],
                          Pose2()) == [1, 1, 2]
    assert tracker.update([_sighting(2.0, 0.07)], Pose2()) == [1]
    first = tracker.tracks[0]
    assert len(first.sightings) == 2 and abs(first.sightings[0].area_m2 - 0.06) < 1e-12


def test_tracks_that_overlap_on_the_road_are_one_entry():
    """A pothole tracked as two (its pieces apart in some frames), and one nearby that does
    not overlap it."""
    def track(track_id, left, stamps, area=0.03):
        made = Track(track_id)
        for stamp in stamps:
            made.sightings.append(_sighting(2.0, left, area, 0.02 + 0.01 * track_id, stamp))
            made.positions.append(np.array([2.0, left]))
        return made

    merged = merge_overlapping([track(1, 0.0, [1, 2, 3]), track(2, 0.12, [2, 3, 4]),
                                track(3, 0.5, [1, 2])])
    assert [t.id for t in merged] == [1, 3]
    joined = merged[0]
    assert [s.stamp_ns for s in joined.sightings] == [1, 2, 3, 4]
    assert abs(joined.sightings[1].area_m2 - 0.06) < 1e-12
    assert joined.sightings[1].max_depth_m == 0.04
    assert abs(joined.position[1] - 0.06) < 1e-9


def test_a_track_s_radius_is_that_of_its_median_area_however_its_sightings_came():
    rng = np.random.default_rng(3)
    areas = rng.uniform(0.01, 0.5, 41)
    track = Track(1)
    for count, area in enumerate(areas, 1):
        track.sightings.append(_sighting(2.0, 0.0, float(area)))
        if count % 3 and count not in (1, 2):
            continue
        assert track.radius_m == radius_of(float(np.median(areas[:count])))
    assert track.radius_m == radius_of(float(np.median(areas)))
    track.sightings.append(_sighting(2.0, 0.0, float("nan")))
    assert np.isnan(track.radius_m) and np.isnan(Track(2).radius_m)


def test_a_footprint_reaches_where_its_pixels_rays_meet_the_road():
    """A level camera 1 m above a flat road (f 500 px): pixel (u, v) below the horizon meets the
    road f / (v - cy) m ahead and -(u - cx) / (v - cy) m to the left."""
    calibration, plane = LEVEL_CAMERA, LEVEL_ROAD
    labels = np.zeros((480, 640), np.int32)
    labels[290:340, 300:340] = 1
    labels[200:230, 10:20] = 2  # above the horizon: never meets the road
    labels[180:260, 500:520] = 4  # across the horizon: only its rows below it reach the road
    found, outlines = footprints(labels, ndimage.find_objects(labels, max_label=5), plane,
                                calibration)
    np.testing.assert_allclose(found[0], [500 / 99, 500 / 50, -19 / 50, 20 / 50])
    assert np.isnan(found[1:3]).all() and np.isnan(found[4]).all()
    np.testing.assert_allclose(found[3], [500 / 19, 500 / 1, -199 / 1, -180 / 19])
    assert len(outlines) == 5 and len(outlines[0]) == 4 and len(outlines[1]) == 0
    np.testing.assert_allclose(outlines[0].min(axis=0), found[0][[0, 2]])


def test_a_footprint_read_in_a_window_of_the_labels_is_the_whole_image_s():
    """footprints of a window of the label image, given the window's origin, are those of the
    whole image."""
    calibration, plane = LEVEL_CAMERA, LEVEL_ROAD
    labels = np.zeros((480, 640), np.int32)
    labels[290:340, 300:340] = 1
    labels[300:305, 330:420] = 1
    labels[180:260, 500:520] = 2
    whole = footprints(labels, ndimage.find_objects(labels), plane, calibration)
    window = labels[170:350, 290:530]
    part = footprints(window, ndimage.find_objects(window), plane, calibration, (170, 290))
    np.testing.assert_array_equal(part[0], whole[0])
    for got, expected in zip(part[1], whole[1]):
        np.testing.assert_array_equal(got, expected)
    assert len(whole[1][0]) >= 3


def test_footprint_extents_are_those_of_every_pixel_projected(demo_sample):
    """The convex hull's corners give the extremes every labelled pixel's ray gives."""
    from pothole_detector.survey.tracking import on_road

    calibration = demo_sample.calibration
    plane = RoadFrame(np.array([0.0, 0.6, 0.0]), np.array(
        [[0.0, -0.5, 0.866], [-1.0, 0.0, 0.0], [0.0, -0.866, -0.5]]))
    labels = demo_sample.labels.astype(np.int32)
    count = int(labels.max())
    found, _ = footprints(labels, ndimage.find_objects(labels), plane, calibration)
    for label in range(1, count + 1):
        rows, cols = np.nonzero(labels == label)
        reach, _ = on_road(cols.astype(float), rows.astype(float), plane, calibration)
        np.testing.assert_allclose(found[label - 1], [reach[:, 0].min(), reach[:, 0].max(),
                                                      reach[:, 1].min(), reach[:, 1].max()])


def test_a_sighting_s_footprint_is_read_in_its_pothole_s_box(demo_sample):
    """sightings_of reads each label within its pothole's box: the footprints of the boxes
    ndimage.find_objects finds over the whole label image."""
    from pothole_detector.params import Config
    from pothole_detector.pipeline import Pipeline
    from pothole_detector.survey.motion import road_frame

    result = Pipeline(Config(), demo_sample.calibration).run(demo_sample.left,
                                                             demo_sample.right)
    labels = result.host("labels")
    height, width = labels.shape
    plane = road_frame(result.road, demo_sample.calibration, width, height)
    seen = sightings_of(1, result, plane, width, height, demo_sample.calibration)
    extents, outlines = footprints(labels, ndimage.find_objects(labels), plane,
                                   demo_sample.calibration)
    assert len(seen) == len(result.potholes) == len(outlines) > 0
    for pothole, sighting in zip(result.potholes, seen):
        np.testing.assert_array_equal(sighting.extent_m, extents[pothole.label - 1])
        np.testing.assert_array_equal(np.reshape(sighting.outline_m, (-1, 2)),
                                      outlines[pothole.label - 1])
