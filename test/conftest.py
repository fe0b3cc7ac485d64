from __future__ import annotations

import os
import platform
from pathlib import Path

# OpenBLAS picks its kernels by the processor, and its AVX-512 ones round some sums of the road
# fit differently in the last bit: the golden outputs (test_golden.py) hold with its AVX2 ones,
# chosen here before NumPy loads it
if platform.machine().lower() in ("x86_64", "amd64"):
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from pothole_detector.evaluation.synthetic import (PotholeShape, Scene,  # noqa: E402
                                                   demo_scene, render)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def demo_sample():
    """The demo road (three potholes) at 640x360."""
    return render(demo_scene(640, 360))


@pytest.fixture(scope="session")
def flat_sample():
    """The demo rig over a road without potholes."""
    scene = demo_scene(640, 360)
    return render(Scene(**{**scene.__dict__, "potholes": ()}))


@pytest.fixture(scope="session")
def bowl_sample():
    """One large bowl in the middle of the view, rendered without supersampling."""
    scene = Scene(width=480, height=360, focal_px=0.67 * 480, camera_height_m=0.6,
                  pitch_deg=60.0, roll_deg=2.0, supersample=1,
                  potholes=(PotholeShape(0.0, 0.38, 0.12, 0.09, 0.05, 10.0),))
    return render(scene)


@pytest.fixture(scope="session")
def near_rim_sample():
    """A robot's camera 0.4 m up, pitched 30 deg, over a steep-walled pothole 1.6 m ahead whose
    near rim hides part of the floor."""
    hole = PotholeShape(0.05, 1.6, 0.15, 0.12, 0.06, 15.0, wall_power=6.0)
    return render(Scene(width=640, height=480, focal_px=500.0, baseline_m=0.08,
                        camera_height_m=0.4, pitch_deg=30.0, potholes=(hole,)))


@pytest.fixture(scope="session")
def high_survey_sample():
    """A survey rig 1.74 m up, pitched 51 deg, baseline 0.48 m, at 520x260 (focal 462 px): the
    road's disparity grows from 60 px at the top to 124 px at the bottom."""
    return render(Scene(width=520, height=260, focal_px=462.3, baseline_m=0.484,
                        camera_height_m=1.742, pitch_deg=51.2, roll_deg=-2.0, supersample=1,
                        noise_grey=1.8, right_gain=0.96))


def shared_data(*parts: str) -> Path:
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data {path} is not available")
    return path


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = (a | b).sum()
    return float((a & b).sum() / union) if union else 1.0


SURVEY_START_NS = 1_700_000_000_000_000_000
SURVEY_ORIGIN_LATLON = (48.137, 11.575)


@pytest.fixture(scope="session")
def survey_drive_bags(tmp_path_factory):
    """The survey drive (48 frames, six potholes) at 480x270 without supersampling, as three
    bags: stereo only, with /odom (nav_msgs/Odometry) and with /gnss/fix (NavSatFix, driving
    north). Returns (bags by kind, scenes)."""
    from dataclasses import replace

    from pothole_detector.recordings.writing import DRIVE_MOTIONS, write_drive_bag
    from pothole_detector.evaluation.synthetic import survey_drive

    scenes = [replace(s, supersample=1) for s in survey_drive(width=480, height=270)]
    samples = [render(s) for s in scenes]
    folder = tmp_path_factory.mktemp("survey_drives")
    forward = [s.camera_y_m - scenes[0].camera_y_m for s in scenes]
    bags = {}
    for kind in DRIVE_MOTIONS:
        bags[kind] = folder / f"drive_{kind}"
        write_drive_bag(bags[kind], forward, samples, kind, SURVEY_ORIGIN_LATLON,
                        SURVEY_START_NS)
    return bags, scenes, samples


def rewrite_bag(source, out, log_time=lambda topic, timestamp: timestamp,
                payload=lambda topic, index, data: data):
    """Copy bag ``source`` to ``out`` with each message logged at ``log_time(topic, log time
    ns)`` (None: left out) and its CDR bytes as ``payload(topic, index in the bag, bytes)``
    gives them."""
    from pothole_detector.recordings.bags import cdr_bytes, open_bag
    from pothole_detector.recordings.messages import typestore
    from pothole_detector.recordings.bagwriter import BagWriter

    reader = open_bag(source)
    writer = BagWriter(out, "mcap")
    try:
        store = typestore()
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store)
                       for c in reader.connections}
        for index, (connection, timestamp, rawdata) in enumerate(reader.messages()):
            moved = log_time(connection.topic, timestamp)
            if moved is not None:
                writer.write(connections[connection.id], moved, payload(
                    connection.topic, index, cdr_bytes(reader, connection, rawdata)))
    finally:
        writer.close()
        reader.close()
