"""The bars of the pipeline issue on the real pothole frames (skipped without ../shared/data)."""

from __future__ import annotations

import pytest

from pothole_detector.backend import CPU
from pothole_detector.evaluation import evaluate
from pothole_detector.params import Config
from conftest import shared_data

pytestmark = [pytest.mark.real_data, pytest.mark.slow]


def test_fan_potholes_pixel_f_score_accuracy_and_no_false_pothole(tmp_path):
    report = evaluate(shared_data("fan_potholes"), Config(), CPU)
    assert not report.errors
    assert len(report.pothole_rows) == 8
    assert report.pixels.f_score >= 0.85
    assert report.pixels.accuracy >= 0.995
    assert report.objects.incorrect == 0 and report.objects.missed == 0
    assert all(row["incorrect"] == 0 for row in report.pothole_rows)


def test_kitti_gpt_sgm_against_plain_sgbm():
    report = evaluate(shared_data("kitti"), Config(), CPU)
    assert not report.errors
    rows = [row for row in report.disparity_rows if row["region"] == "road"]
    ours = [row for row in rows if row["matcher"].startswith("GPT-SGM")]
    plain = [row for row in rows if row["matcher"] == "OpenCV SGBM"]
    assert len(ours) == len(plain) == 4
    mean = {name: sum(r["pep3"] for r in group) / len(group)
            for name, group in (("ours", ours), ("plain", plain))}
    assert mean["ours"] <= mean["plain"] + 1.0
    assert all(r["levels"] <= p["levels"] for r, p in zip(ours, plain))
    assert all(r["density"] > 85 for r in ours)
