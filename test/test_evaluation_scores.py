from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.evaluation.scores import (ObjectCounts, PixelCounts, discover,
                                                disparity_errors, road_region)
from conftest import shared_data


def test_pixel_counts_known_answer():
    truth = np.array([[1, 1, 0, 0]], bool)
    predicted = np.array([[1, 0, 1, 0]], bool)
    counts = PixelCounts()
    counts.add(predicted, truth, np.ones_like(truth))
    assert (counts.tp, counts.fp, counts.fn, counts.tn) == (1, 1, 1, 1)
    assert counts.precision == counts.recall == counts.f_score == counts.accuracy == 0.5


def test_object_counts_correct_incorrect_missed():
    truth = np.zeros((20, 40), bool)
    truth[2:8, 2:8] = True
    truth[12:18, 30:36] = True
    labels = np.zeros((20, 40), np.int32)
    labels[3:8, 3:8] = 1
    labels[12:16, 10:14] = 2
    counts = ObjectCounts()
    counts.add(labels, truth, np.ones_like(truth))
    assert (counts.correct, counts.incorrect, counts.missed) == (1, 1, 1)


def test_disparity_errors_known_answer():
    truth = np.array([[10.0, 10.0, 10.0, np.nan]], np.float32)
    estimate = np.array([[10.5, 12.5, np.nan, 3.0]], np.float32)
    errors = disparity_errors(estimate, truth)
    assert errors["pixels"] == 3
    assert errors["pep1"] == pytest.approx(200 / 3) and errors["pep3"] == pytest.approx(100 / 3)
    assert errors["rmse"] == pytest.approx(np.sqrt((0.25 + 6.25) / 2))


def test_road_region_is_the_road_plane(flat_sample):
    truth = flat_sample.disparity.copy()
    truth[250:300, 100:200] += 20
    region = road_region(truth)
    assert not region[250:300, 100:200].any()
    assert region[200:].mean() > 0.8


def test_discover_finds_the_shared_sets():
    root = shared_data()
    names = [s.name for s in discover(root)]
    assert sum(n.startswith("model1_") for n in names) == 8
    assert any(n.startswith("kitti2012_training/") for n in names)
    assert {"cones", "teddy"} <= set(names)


def test_match_potholes_pairs_by_iou_one_to_one():
    from pothole_detector.evaluation.scores import match_potholes
    truth = np.zeros((10, 20), np.int64)
    truth[1:5, 1:5], truth[1:5, 10:14] = 1, 2
    labels = np.zeros_like(truth)
    labels[1:5, 2:6] = 1   # IoU 12 / 20 with truth 1
    labels[1:2, 10:11] = 2  # IoU 1 / 16 with truth 2: too little
    labels[7:9, 7:9] = 3   # nothing there
    assert match_potholes(labels, truth) == [(1, 1)]
    assert match_potholes(labels, truth, min_iou=0.05) == [(1, 1), (2, 2)]


def test_truth_roll_is_the_fitted_roll_of_the_rendered_road():
    from dataclasses import replace

    from pothole_detector.evaluation.scores import truth_roll_deg
    from pothole_detector.stages.road_model import fit_road
    from pothole_detector.evaluation.synthetic import demo_scene, render
    sample = render(replace(demo_scene(320, 180, roll_deg=3.0), potholes=(), supersample=1))
    assert truth_roll_deg(sample) == pytest.approx(
        fit_road(np, sample.disparity).roll_deg, abs=0.02)


def test_synthetic_evaluation_scores_a_rendered_scene(tmp_path):
    from pothole_detector.backend import CPU
    from pothole_detector.evaluation.scores import evaluate_synthetic, synthetic_markdown
    from pothole_detector.params import Config
    tallies = evaluate_synthetic(Config(), CPU, ["robot"], scenes=1, clean_scenes=1,
                                 cache=tmp_path)
    tally = tallies["robot"]
    assert (tally.scenes, tally.clean_scenes, tally.failed, tally.bad_reports) == (1, 1, 0, 0)
    assert tally.pixels_observed.f_score > 0.7 and tally.false_on_clean == 0
    assert tally.matched >= 2 and max(tally.roll_errors_deg) < 0.5
    assert len(list(tmp_path.glob("*.pkl"))) == 2
    assert "| robot | 1 + 1 clean |" in synthetic_markdown(tallies)


def test_synthetic_evaluation_renders_in_worker_processes_with_the_same_result():
    from pothole_detector.backend import CPU
    from pothole_detector.evaluation.scores import evaluate_synthetic, synthetic_markdown
    from pothole_detector.params import Config
    alone = evaluate_synthetic(Config(), CPU, ["robot"], scenes=1, clean_scenes=1)
    pooled = evaluate_synthetic(Config(), CPU, ["robot"], scenes=1, clean_scenes=1, jobs=2)
    assert synthetic_markdown(pooled) == synthetic_markdown(alone)
    assert pooled["robot"].volume_errors == alone["robot"].volume_errors


def test_the_classes_pooled_sum_their_counts_and_keep_every_error():
    from pothole_detector.evaluation.scores import (PixelCounts, RigTally, pooled,
                                                    synthetic_markdown)
    small = RigTally(scenes=2, pixels_observed=PixelCounts(tp=10, fp=0, fn=10, tn=80),
                     detections=2, matched=2, truths_observed=2, matched_observed=2,
                     depth_errors=[0.1])
    large = RigTally(scenes=3, pixels_observed=PixelCounts(tp=90, fp=10, fn=0, tn=900),
                     detections=4, matched=3, truths_observed=5, matched_observed=3,
                     depth_errors=[0.3, 0.2], false_on_clean=1)
    total = pooled([small, large])
    assert (total.scenes, total.detections, total.matched, total.false_on_clean) == (5, 6, 5, 1)
    assert total.pixels_observed.f_score == pytest.approx(2 * 100 / (200 + 10 + 10))
    assert total.pothole_scores(True) == pytest.approx((5 / 6, 5 / 7, 10 / 13))
    assert sorted(total.depth_errors) == [0.1, 0.2, 0.3] and small.depth_errors == [0.1]
    table = synthetic_markdown({"robot": small, "survey": large})
    assert table.splitlines()[-1].startswith("| **all** | 5 + 0 clean | 0.91 / 0.91 / 0.91 |")
    assert "**all**" not in synthetic_markdown({"robot": small})


def _box(shape, top, left, height, width, value=1):
    out = np.zeros(shape, dtype=np.int64)
    out[top:top + height, left:left + width] = value
    return out


def test_a_validation_scene_is_scored_as_we_are_judged():
    """Four truths (one too small to count) and four detections: one matches a scored
    pothole, one matches the small one (counted neither way), one is false; a scored pothole
    outside the observed range is missed; errors of the matched one, its area's also among
    those of potholes in full view until the frame's edge cuts it."""
    from types import SimpleNamespace

    from pothole_detector.evaluation.scores import RigTally, score_scene, validation_markdown
    from pothole_detector.stages.measure import Pothole

    shape = (60, 80)
    truth = _box(shape, 5, 5, 10, 10, 1) + _box(shape, 30, 5, 5, 5, 2) \
        + _box(shape, 40, 40, 12, 12, 3) + _box(shape, 5, 50, 10, 12, 4)
    labels = _box(shape, 6, 5, 10, 10, 1) + _box(shape, 30, 5, 5, 5, 2) \
        + _box(shape, 30, 60, 8, 8, 3)
    potholes = [Pothole(label, 100, 0.12, 0.05, 0.03, 0.002, np.array([0.0, 0.0, 3.0]),
                        (0, 0, 1, 1)) for label in (1, 2, 3)]
    meta = {"C_left_world": [0.0, 0.0, 1.0], "potholes": [
        {"id": 1, "max_depth_m": 0.04, "area_m2": 0.1, "volume_m3": 0.002,
         "centroid_world_m": [0.0, 3.0, 0.0]},
        {"id": 2, "max_depth_m": 0.02, "area_m2": 0.01, "volume_m3": 0.0001,
         "centroid_world_m": [0.0, 3.0, 0.0]},
        {"id": 3, "max_depth_m": 0.05, "area_m2": 0.2, "volume_m3": 0.004,
         "centroid_world_m": [0.0, 3.5, 0.0]},
        {"id": 4, "max_depth_m": 0.05, "area_m2": 0.2, "volume_m3": 0.004,
         "centroid_world_m": [0.0, 9.0, 0.0]}]}
    observed = np.ones(shape, dtype=bool)
    arrays = {"labels": labels, "observed": observed}
    result = SimpleNamespace(host=arrays.__getitem__, potholes=potholes,
                             observed_range_m=(1.0, 5.0))
    tally = RigTally()
    score_scene(tally, result, truth, meta)
    assert (tally.truths_all, tally.truths_observed, tally.matched_observed) == (3, 2, 1)
    assert (tally.detections, tally.matched, tally.false_on_clean) == (2, 1, 1)
    precision, recall, f = tally.pothole_scores(False)
    assert (precision, recall) == (0.5, 1 / 3) and f == pytest.approx(0.4)
    assert tally.depth_errors == [pytest.approx(0.25)] and tally.area_errors == \
        tally.whole_area_errors == [pytest.approx(0.2)]
    assert tally.pixels_all.tp == 9 * 10 + 25
    cut_off = RigTally()
    rolled = {"labels": np.roll(labels, -6, axis=0), "observed": observed}
    score_scene(cut_off, SimpleNamespace(host=rolled.__getitem__, potholes=potholes,
                                         observed_range_m=(1.0, 5.0)),
                np.roll(truth, -6, axis=0), meta)
    assert cut_off.area_errors == [pytest.approx(0.2)] and cut_off.whole_area_errors == []
    table = validation_markdown({"vehicle": tally})
    assert "| vehicle | 1 | " in table and "| 0.50 / 0.33 / 0.40 |" in table
    assert "| 1.00 |" in table  # one false pothole in one frame


def test_evaluate_reads_the_validation_scenes():
    from pothole_detector.backend import CPU
    from pothole_detector.evaluation.scores import evaluate
    from pothole_detector.params import Config

    root = shared_data("validation", "robot_640x480")
    found = [s for s in discover(root) if s.scene is not None]
    assert len(found) == 8 and {s.group for s in found} == {"robot_640x480"}
    report = evaluate(found[0].scene, Config({"backend": "cpu"}), CPU)
    text = report.markdown()
    assert "## Validation scenes" in text and "| robot_640x480 | 1 |" in text


def test_the_validation_drive_is_surveyed_and_scored():
    from pothole_detector.evaluation.scores import score_drive
    from pothole_detector.params import Config

    folder = shared_data("validation", "drive_640x480")
    row = score_drive(folder, Config({"backend": "cpu"}))
    assert row["frames"] == 40 and row["seen"] == 2
    assert row["found"] + row["duplicates"] + row["false"] <= row["entries"]
    # the 2.8 cm pothole no frame shows alone is found by the views together (the map)
    assert row["found"] == 2 and row["duplicates"] == 0 and row["false"] == 0
    assert 0 <= row["error_median_m"] <= row["error_max_m"] <= 0.2
