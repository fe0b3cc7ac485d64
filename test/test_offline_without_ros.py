"""process, survey, detect and evaluate in an install without ROS: a fresh virtual environment
with the base install only (pip install pothole_detector, no extras)."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest
from conftest import REPO

from pothole_detector.recordings.bags import open_bag

PAIR = REPO / "bags" / "sample_pair"


@pytest.fixture(scope="module")
def base_install(tmp_path_factory):
    venv = tmp_path_factory.mktemp("base_install") / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    done = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet",
                           str(REPO)], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    return venv / "bin"


def run(bin_dir, *args, cwd):
    return subprocess.run([str(bin_dir / "pothole-detector"), *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=600)


def test_the_base_install_has_no_ros(base_install):
    for module in ("rclpy", "sensor_msgs", "pothole_detector_msgs"):
        done = subprocess.run([str(base_install / "python"), "-c", f"import {module}"],
                              capture_output=True, text=True)
        assert done.returncode != 0, module


def test_offline_commands_run_without_ros(base_install, tmp_path):
    drive = REPO / "bags" / "sample_drive"
    done = run(base_install, "survey", drive, "--out", tmp_path / "survey", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    with open(tmp_path / "survey" / "survey.csv") as handle:
        assert len(list(csv.DictReader(handle))) == 5
    done = run(base_install, "process", drive, "--out", tmp_path / "processed", cwd=tmp_path)
    assert done.returncode == 0 and "16 frames" in done.stdout, done.stderr
    reader = open_bag(tmp_path / "processed")  # our rclpy-free bag reads back here
    try:
        topics = {c.topic: c.msgcount for c in reader.connections}
    finally:
        reader.close()
    assert topics["/stereo/potholes"] == 16 and topics["/stereo/pothole_markers"] == 16
    done = run(base_install, "detect", "--left", PAIR / "left.png", "--right",
               PAIR / "right.png", "--camera-info-left", PAIR / "left_camera_info.yaml",
               "--camera-info-right", PAIR / "right_camera_info.yaml", "--out",
               tmp_path / "detect", cwd=tmp_path)
    assert done.returncode == 0 and "1 pothole(s)" in done.stdout, done.stderr
    done = run(base_install, "evaluate", "--synthetic", "--rig-class", "robot", "--scenes", "1",
               "--clean-scenes", "0", cwd=tmp_path)
    assert done.returncode == 0 and "| robot |" in done.stdout, done.stderr


def test_process_without_ros_writes_what_rclpy_writes(base_install, tmp_path):
    """The same bag from both installs: every message decodes to the same values (the CDR
    padding bytes may differ)."""
    pytest.importorskip("rclpy")
    from pothole_detector.ros.bagtools import process
    from pothole_detector.recordings.messages import typestore
    from pothole_detector.params import Config

    drive = REPO / "bags" / "sample_drive"
    assert run(base_install, "process", drive, "--out", tmp_path / "plain", "--backend", "cpu",
               cwd=tmp_path).returncode == 0
    process(drive, tmp_path / "ros", Config({"backend": "cpu"}))
    store = typestore()

    def messages(path):
        reader = open_bag(path)
        try:
            return [(c.topic, bytes(store.serialize_cdr(store.deserialize_cdr(raw, c.msgtype),
                                                        c.msgtype)))
                    for c, _, raw in reader.messages()]
        finally:
            reader.close()

    assert messages(tmp_path / "plain") == messages(tmp_path / "ros")
