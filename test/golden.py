"""Digests of the pipeline's CPU outputs on the bundled data, to prove that a change keeps them
bit for bit: ``python test/golden.py`` rewrites test/golden_outputs.json from the current code
(do that only for a change that is meant to alter results, and say so in its commit)."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
from pathlib import Path
from typing import Any, Iterator

# as in conftest.py: OpenBLAS's AVX2 kernels on every x86 processor, so that the digests do not
# depend on whether it has AVX-512
if platform.machine().lower() in ("x86_64", "amd64"):
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
GOLDEN = Path(__file__).resolve().parent / "golden_outputs.json"
sys.path.insert(0, str(REPO))

from pothole_detector.backend import to_host  # noqa: E402
from pothole_detector.calibration import load_stereo_camera_info  # noqa: E402
from pothole_detector.imageio import read_image  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.method import PipelineResult  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402
from pothole_detector.evaluation.synthetic import demo_scene, drive_scenes, render  # noqa: E402


def _digest(array: Any) -> str:
    array = np.ascontiguousarray(array)
    return hashlib.sha256(str(array.dtype).encode() + str(array.shape).encode()
                          + array.tobytes()).hexdigest()[:24]


def result_digest(result: PipelineResult) -> dict:
    """What a frame's outputs are, as digests of the arrays and the report's exact numbers."""
    return {
        "disparity": _digest(to_host(result.disparity)),
        "transformed": _digest(to_host(result.transformed)),
        "labels": _digest(to_host(result.labels).astype(np.int32)),
        "road": repr(sorted(result.road.as_dict().items())),
        "threshold_px": repr(result.threshold_px),
        "band": repr(tuple(result.band)),
        "disparity_range": repr(tuple(result.disparity_range)),
        "potholes": repr([sorted(p.as_dict().items()) for p in result.potholes]),
    }


def _bag_pairs(bag: Path) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Left and right mono8 images of a stereo bag in stamp order (rosbags only)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([bag], default_typestore=store) as reader:
        images: dict[int, dict[str, np.ndarray]] = {}
        wanted = [c for c in reader.connections if c.topic.endswith("image_rect")]
        for connection, stamp, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, connection.msgtype)
            pixels = np.asarray(msg.data, np.uint8).reshape(msg.height, msg.step)[:, :msg.width]
            side = "left" if "/left/" in connection.topic else "right"
            images.setdefault(stamp, {})[side] = pixels
    for stamp in sorted(images):
        yield images[stamp]["left"], images[stamp]["right"]


def cases() -> dict[str, list[dict]]:
    """Every case's per-frame digests from the code as it is."""
    out: dict[str, list[dict]] = {}
    pair = REPO / "bags" / "sample_pair"
    camera, _ = load_stereo_camera_info(pair / "left_camera_info.yaml",
                                        pair / "right_camera_info.yaml")
    calibration = camera.calibration()
    left, right = read_image(pair / "left.png"), read_image(pair / "right.png")
    for name, config in (("pair", Config()),
                         ("pair_metric", Config({"threshold_mode": "metres"}))):
        pipeline = Pipeline(config, calibration)
        out[name] = [result_digest(pipeline.run(left, right)) for _ in range(2)]
    demo = render(demo_scene(480, 270))
    opencv = Pipeline(Config({"matcher": "opencv"}), demo.calibration)
    out["demo_opencv"] = [result_digest(opencv.run(demo.left, demo.right)) for _ in range(2)]
    drive_calibration = render(drive_scenes(frames=1)[0]).calibration
    stream = Pipeline(Config(), drive_calibration).run_stream(
        _bag_pairs(REPO / "bags" / "sample_drive"))
    out["sample_drive"] = [result_digest(r) if isinstance(r, PipelineResult) else repr(r)
                           for r in stream]
    return out


if __name__ == "__main__":
    GOLDEN.write_text(json.dumps(cases(), indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}")
