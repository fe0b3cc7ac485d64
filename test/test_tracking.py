"""Pothole tracking on the road plane (tracking.py), shared by the survey and the node."""

from __future__ import annotations

import numpy as np

from pothole_detector.motion import Pose2, RoadFrame
from pothole_detector.stages.measure import Pothole
from pothole_detector.tracking import MAX_ID, PotholeTracker, Sighting, relabel, sightings_of


def _sighting(forward: float, left: float, area: float = 0.03) -> Sighting:
    return Sighting(0, (0.0, 0.0, 1.0), (forward, left), True, 0.05, 0.03, area, area * 0.03,
                    (10, 10, 20, 20))


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

    # camera 1 m above a level road, looking ahead: forward = z, left = -x, up = -y
    plane = RoadFrame(np.array([0.0, 1.0, 0.0]),
                      np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]))
    seen = sightings_of(7, Result(), plane, 40, 30)
    assert seen[0].road_xy == (2.0, -0.2) and seen[0].observed and not seen[0].whole
    tracker = PotholeTracker(0.25, 30)
    assert tracker.update(seen, Pose2()) == [1, 2]
    assert tracker.update(seen, Pose2()) == [1, 3]


def test_relabel_renames_labels():
    labels = np.array([[0, 1, 1], [2, 2, 0]], np.int32)
    renamed = relabel(labels, [type("P", (), {"label": 1}), type("P", (), {"label": 2})], [7, 3])
    np.testing.assert_array_equal(renamed, [[0, 7, 7], [3, 3, 0]])
    assert renamed.dtype == labels.dtype
