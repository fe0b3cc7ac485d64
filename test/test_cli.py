from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from conftest import REPO
from pothole_detector.calibration import camera_info_yaml
from pothole_detector.cli import main


@pytest.fixture(scope="module")
def pair_dir(tmp_path_factory, demo_sample):
    folder = tmp_path_factory.mktemp("pair")
    cv2.imwrite(str(folder / "left.png"), demo_sample.left)
    cv2.imwrite(str(folder / "right.png"), demo_sample.right)
    height, width = demo_sample.left.shape
    for side in ("left", "right"):
        (folder / f"{side}.yaml").write_text(
            camera_info_yaml(demo_sample.calibration, width, height, side))
    return folder


def test_detect_writes_the_contract(pair_dir, tmp_path, demo_sample):
    out = tmp_path / "out"
    code = main(["detect", "--left", str(pair_dir / "left.png"), "--right",
                 str(pair_dir / "right.png"), "--camera-info-left", str(pair_dir / "left.yaml"),
                 "--camera-info-right", str(pair_dir / "right.yaml"), "--out", str(out),
                 "--backend", "cpu"])
    assert code == 0
    disparity = np.load(out / "disparity.npy")
    transformed = np.load(out / "disparity_transformed.npy")
    assert disparity.dtype == np.float32 and disparity.shape == demo_sample.left.shape
    assert transformed.dtype == np.float32 and np.isnan(disparity).any()
    labels = cv2.imread(str(out / "labels.png"), cv2.IMREAD_UNCHANGED)
    assert labels.dtype == np.uint16 and labels.shape == demo_sample.left.shape
    report = json.loads((out / "potholes.json").read_text())
    assert set(report) >= {"road", "backend", "timings_ms", "potholes", "observed_range_m"}
    near, far = report["observed_range_m"]["near"], report["observed_range_m"]["far"]
    assert 0 <= near < far < 3  # the demo rig sees about 0.1 to 1.2 m of road
    assert set(report["road"]) >= {"a0", "a1", "roll_deg", "inlier_fraction"}
    assert report["backend"] == "cpu" and len(report["potholes"]) == 3
    for pothole in report["potholes"]:
        assert set(pothole) == {"label", "pixels", "area_m2", "max_depth_m", "mean_depth_m",
                                "volume_m3", "centroid_cam_m", "bbox_px"}
        assert (labels == pothole["label"]).sum() == pothole["pixels"]
        assert 0.02 < pothole["max_depth_m"] < 0.09 and pothole["centroid_cam_m"][2] > 0
    overlay = cv2.imread(str(out / "overlay.png"))
    assert overlay.shape[:2] == demo_sample.left.shape


def test_focal_baseline_equals_camera_info(pair_dir, tmp_path, demo_sample):
    out = tmp_path / "fb"
    calibration = demo_sample.calibration
    assert main(["detect", "--left", str(pair_dir / "left.png"), "--right",
                 str(pair_dir / "right.png"), "--focal", str(calibration.f), "--baseline",
                 str(calibration.baseline), "--out", str(out), "--backend", "cpu"]) == 0
    assert len(json.loads((out / "potholes.json").read_text())["potholes"]) == 3


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "pothole_detector.cli", *args],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("case,says", [
    ("missing", "does not exist"), ("size", "equal sizes"), ("texture", "texture"),
    ("calibration", "--focal and --baseline"), ("config", "delta_pd_px"),
    ("same", "not a stereo pair"), ("empty_info", "is empty"), ("conflict", "conflicts"),
    ("auto_backend", "not a stereo pair"), ("not_a_bag", "is not a bag"),
    ("jobs_and_ray", "give one of them")])
def test_bad_input_exits_with_one_line(case, says, pair_dir, tmp_path):
    """Each refusal: exit status 2 and one line on stderr that says why (under the auto
    backend too, whose notice goes to stdout)."""
    left, right = pair_dir / "left.png", pair_dir / "right.png"
    extra = ["--focal", "430", "--baseline", "0.12"]
    backend = ["--backend", "cpu"]
    if case == "missing":
        left = tmp_path / "nope.png"
    elif case == "size":
        right = tmp_path / "small.png"
        cv2.imwrite(str(right), cv2.imread(str(pair_dir / "right.png"))[:, :-8])
    elif case == "texture":
        left = right = tmp_path / "flat.png"
        cv2.imwrite(str(left), np.full((120, 160), 90, np.uint8))
    elif case in ("same", "auto_backend"):
        right = left
        backend = [] if case == "auto_backend" else backend
    elif case == "calibration":
        extra = ["--focal", "430"]
    elif case == "config":
        config = tmp_path / "bad.yaml"
        config.write_text("pothole_detector:\n  ros__parameters:\n    delta_pd_px: -1\n")
        extra += ["--config", str(config)]
    elif case == "empty_info":
        (tmp_path / "empty.yaml").write_text("")
        extra = ["--camera-info-left", str(tmp_path / "empty.yaml"),
                 "--camera-info-right", str(pair_dir / "right.yaml")]
    elif case == "conflict":
        extra = ["--camera-info-left", str(pair_dir / "left.yaml"),
                 "--camera-info-right", str(pair_dir / "right.yaml"), "--cx", "300"]
    if case == "not_a_bag":
        (tmp_path / "notes.txt").write_text("not a bag\n")
        result = run_cli("process", str(tmp_path / "notes.txt"), "--out", str(tmp_path / "o"))
    elif case == "jobs_and_ray":
        result = run_cli("survey", str(REPO / "bags" / "sample_drive"), "--out",
                         str(tmp_path / "o"), "--jobs", "2", "--ray")
    else:
        result = run_cli("detect", "--left", str(left), "--right", str(right), *extra, "--out",
                         str(tmp_path / "o"), *backend)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pothole-detector: error:"), result.stderr
    assert says in lines[0] and "Traceback" not in result.stderr


def test_the_node_prints_its_usage_and_exits():
    pytest.importorskip("rclpy")
    result = subprocess.run([sys.executable, "-m", "pothole_detector.ros.node", "--help"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.startswith("usage: pothole_detector_node")
    assert "left/image_rect" in result.stdout and "--params-file" in result.stdout


def test_evaluate_prints_the_papers_metrics(tmp_path, demo_sample):
    frame = tmp_path / "data" / "synthetic_01"
    frame.mkdir(parents=True)
    cv2.imwrite(str(frame / "left.png"), demo_sample.left)
    cv2.imwrite(str(frame / "right.png"), demo_sample.right)
    cv2.imwrite(str(frame / "pothole_mask.png"), ((demo_sample.labels > 0) * 255).astype(np.uint8))
    cv2.imwrite(str(frame / "label_roi.png"), np.full(demo_sample.left.shape, 255, np.uint8))
    result = run_cli("evaluate", str(tmp_path / "data"), "--out", str(tmp_path / "r.md"),
                     "--backend", "cpu")
    assert result.returncode == 0, result.stderr
    assert "F-score" in result.stdout and "synthetic_01" in result.stdout
    assert "1/1" in result.stderr
    row = [line for line in result.stdout.splitlines() if line.startswith("| **all**")][0]
    precision = float(row.split("|")[2])
    assert precision > 0.8
    assert (tmp_path / "r.md").read_text().strip() == result.stdout.strip()


@pytest.fixture(scope="module")
def drive_without_baseline(tmp_path_factory):
    """Three frames of the driving sequence whose right camera_info has Tx = 0 (some drivers
    publish it so), and the baseline they were taken with."""
    from dataclasses import replace

    from pothole_detector.recordings.writing import RecordingForm, write_stereo_bag
    from pothole_detector.evaluation.synthetic import drive_scenes, render

    samples = [render(replace(s, supersample=1)) for s in drive_scenes(frames=3)]
    bag = tmp_path_factory.mktemp("tx0") / "drive"
    write_stereo_bag(bag, [(1_700_000_000_000_000_000 + i * 100_000_000, s)
                           for i, s in enumerate(samples)],
                     form=RecordingForm(no_baseline=True))
    return bag, samples[0].calibration.baseline


def test_a_run_that_processes_nothing_exits_non_zero_and_says_why(tmp_path,
                                                                 drive_without_baseline):
    """process and survey on a bag whose every frame fails: status 1, the reason counted on
    stdout, one error line; survey's summary.json and report.html tell the failures. With
    --baseline both process every frame."""
    bag, baseline = drive_without_baseline
    done = run_cli("process", str(bag), "--out", str(tmp_path / "p"), "--backend", "cpu")
    assert done.returncode == 1, done.stderr
    assert "3 frames failed: right camera_info has Tx = P[0,3] = 0" in done.stdout
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("pothole-detector: error: no frame of") and "--baseline" in last
    survey_out = tmp_path / "s"
    broken = tmp_path / "broken_bag"
    broken.mkdir()
    (broken / "broken_bag_0.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(100))
    done = run_cli("survey", str(bag), str(broken), "--out", str(survey_out),
                   "--backend", "cpu")
    assert done.returncode == 1, done.stderr
    assert "broken_bag: not surveyed: " in done.stdout and "3 frames failed" in done.stdout
    summary = json.loads((survey_out / "summary.json").read_text())
    assert (summary["frames"], summary["processed"], summary["failed"]) == (3, 0, 3)
    assert summary["unreadable_bags"] == 1
    [kind] = summary["drives"][0]["failures_by_reason"]
    assert kind["count"] == 3 and "baseline" in kind["reason"]
    assert len(summary["drives"][0]["failed_frames"]) == 3
    page = (survey_out / "report.html").read_text()
    assert "Frames that failed" in page and "Tx = P[0,3] = 0" in page and "not read" in page
    done = run_cli("process", str(bag), "--out", str(tmp_path / "p2"), "--backend", "cpu",
                   "--baseline", str(baseline), "--compression", "lz4")
    assert done.returncode == 0, done.stderr
    assert "using baseline" in done.stdout and "3 frames" in done.stdout
    (written,) = (tmp_path / "p2").glob("*.mcap")
    with written.open("rb") as stream:
        assert {chunk.compression for chunk
                in make_reader(stream).get_summary().chunk_indexes} == {"lz4"}
    assert "stereo topics: /stereo/left/image_rect and /stereo/right/image_rect" in done.stdout
    done = run_cli("survey", str(bag), "--out", str(tmp_path / "s2"), "--backend", "cpu",
                   "--baseline", str(baseline))
    assert done.returncode == 0, done.stderr
    summary = json.loads((tmp_path / "s2" / "summary.json").read_text())
    assert (summary["processed"], summary["failed"]) == (3, 0)


def test_detect_rectifies_raw_images_and_takes_a_missing_baseline(tmp_path):
    """detect on a raw pair of a distorted, rotated camera with calibration files whose right
    P has Tx = 0: refused without --baseline (one line saying how), then the potholes of the
    rectified pair, the overlay in the rectified frame."""
    import yaml

    from pothole_detector.evaluation.synthetic import demo_scene, raw_camera, render, render_raw

    scene = demo_scene(640, 360)
    sample = render(scene)
    camera = raw_camera(sample.calibration, 640, 360, "plumb_bob", seed=1)
    left, right = render_raw(scene, camera)
    for side, image, model in (("left", left, camera.left), ("right", right, camera.right)):
        cv2.imwrite(str(tmp_path / f"{side}.png"), image)
        p = [float(v) for v in model.p]
        p[3] = 0.0
        (tmp_path / f"{side}.yaml").write_text(yaml.safe_dump({
            "image_width": 640, "image_height": 360, "distortion_model": model.distortion_model,
            "distortion_coefficients": {"rows": 1, "cols": 5,
                                        "data": [float(v) for v in model.d]},
            "camera_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in model.k]},
            "rectification_matrix": {"rows": 3, "cols": 3,
                                     "data": [float(v) for v in model.r]},
            "projection_matrix": {"rows": 3, "cols": 4, "data": p}}))
    args = ["detect", "--left", str(tmp_path / "left.png"), "--right",
            str(tmp_path / "right.png"), "--camera-info-left", str(tmp_path / "left.yaml"),
            "--camera-info-right", str(tmp_path / "right.yaml"), "--backend", "cpu"]
    refused = run_cli(*args, "--out", str(tmp_path / "refused"))
    assert refused.returncode == 2 and "--baseline" in refused.stderr
    done = run_cli(*args, "--out", str(tmp_path / "out"), "--baseline",
                   str(sample.calibration.baseline))
    assert done.returncode == 0, done.stderr
    assert "using baseline" in done.stdout
    report = json.loads((tmp_path / "out" / "potholes.json").read_text())
    assert len(report["potholes"]) == len(sample.potholes)
    labels = cv2.imread(str(tmp_path / "out" / "labels.png"), cv2.IMREAD_UNCHANGED) > 0
    truth = sample.labels > 0
    assert 2 * (labels & truth).sum() / (labels.sum() + truth.sum()) > 0.85
