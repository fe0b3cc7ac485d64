"""Helpers for tests that run the node as its own process and talk to it over DDS."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_msgs.msg import Header
from stereo_msgs.msg import DisparityImage
from visualization_msgs.msg import MarkerArray

from pothole_detector.recordings import bags, messages
from pothole_detector.recordings.images import decode_raw
from pothole_detector.recordings.messages import stamp_ns
from pothole_detector.ros.transport import large_image_transport
from pothole_detector_msgs.msg import PotholeArray

REPO = Path(__file__).resolve().parents[1]
SAMPLE_DRIVE = REPO / "bags" / "sample_drive"
OUTPUTS = {"disparity": DisparityImage, "disparity_transformed": Image, "pothole_labels": Image,
           "pothole_points": PointCloud2, "points2": PointCloud2, "potholes": PotholeArray,
           "pothole_markers": MarkerArray, "overlay": Image}
# the road map's outputs, published only while subscribed and at most map_publish_rate_hz
MAP_OUTPUTS = {"map_cloud": PointCloud2, "map_potholes": OccupancyGrid}


def isolate_ros_graph() -> None:
    """Give this test run a DDS domain of its own on the loopback interface, with the transport
    profile the README asks of the camera's node (a left and a right 640x480 image published
    together outgrow Fast DDS's default shared memory)."""
    os.environ["ROS_DOMAIN_ID"] = str(100 + os.getpid() % 100)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    large_image_transport()


def header_at(nanoseconds: int, frame_id: str = "stereo_left_optical_frame") -> Header:
    return messages.header_at(nanoseconds, frame_id)


def sample_frames(count: int) -> list[dict[str, Any]]:
    """The first ``count`` frames of the sample drive bag as rclpy messages by role."""
    roles = {"/stereo/left/image_rect": "left", "/stereo/right/image_rect": "right",
             "/stereo/left/camera_info": "left_info", "/stereo/right/camera_info": "right_info",
             "/stereo/ground_truth/pothole_labels": "truth"}
    frames: dict[int, dict[str, Any]] = defaultdict(dict)
    for topic, stamp, msg in bags.read_messages(SAMPLE_DRIVE, roles):
        frames[stamp][roles[topic]] = msg
        if len(frames) > count:
            break
    return [frames[s] for s in sorted(frames)[:count]]


class NodeProcess:
    """``python -m pothole_detector.ros.node`` in namespace ``namespace`` with ``params``, the
    parameter file ``params_file`` (the shipped one by default) and, where given, the node
    renamed ``node_name``."""

    def __init__(self, log: Path, namespace: str = "/stereo", params_file: Path | None = None,
                 node_name: str | None = None, **params: Any) -> None:
        args = [sys.executable, "-m", "pothole_detector.ros.node", "--ros-args",
                "-r", f"__ns:={namespace}",
                "--params-file", str(params_file or REPO / "config" / "pothole_detector.yaml")]
        if node_name:
            args += ["-r", f"__node:={node_name}"]
        for name, value in params.items():
            text = str(value).lower() if isinstance(value, bool) else str(value)
            args += ["-p", f"{name}:={text}"]
        self.log = log
        self.namespace = namespace
        self._file = open(log, "w")
        self.process = subprocess.Popen(args, stdout=self._file, stderr=subprocess.STDOUT)

    def alive(self) -> bool:
        return self.process.poll() is None

    def text(self) -> str:
        return self.log.read_text()

    def stop(self) -> int:
        if self.alive():
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._file.close()
        return self.process.returncode


class Probe:
    """A test-side node: publishes stereo input and collects every output of the node."""

    def __init__(self, namespace: str = "/stereo", reliability: str = "reliable",
                 outputs: tuple[str, ...] = tuple(OUTPUTS), input_reliability: str = "reliable",
                 durability: str = "volatile", compressed: bool = False) -> None:
        """``reliability`` and ``durability``: of the output subscriptions;
        ``input_reliability``: of the camera publishers; ``compressed``: the images go as
        CompressedImage on ``.../image_rect/compressed``."""
        self.namespace = namespace
        self.node = rclpy.create_node(f"probe_{uuid.uuid4().hex[:8]}")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

        def profile(reliability_name: str) -> QoSProfile:
            return QoSProfile(
                depth=50, reliability=ReliabilityPolicy.RELIABLE
                if reliability_name == "reliable" else ReliabilityPolicy.BEST_EFFORT,
                durability=DurabilityPolicy.TRANSIENT_LOCAL
                if durability == "transient_local" else DurabilityPolicy.VOLATILE)

        qos, camera = profile(reliability), profile(input_reliability)
        self.received: dict[str, list[Any]] = defaultdict(list)
        self._subs = [
            self.node.create_subscription({**OUTPUTS, **MAP_OUTPUTS}[name], f"{namespace}/{name}",
                                          lambda m, n=name: self.received[n].append(m), qos)
            for name in outputs
        ]
        self._subs.append(self.node.create_subscription(
            DiagnosticArray, "/diagnostics", lambda m: self.received["diagnostics"].append(m),
            10))
        kind, suffix = (CompressedImage, "/compressed") if compressed else (Image, "")
        self.inputs = {
            "left": self.node.create_publisher(kind, f"{namespace}/left/image_rect{suffix}",
                                               camera),
            "right": self.node.create_publisher(kind, f"{namespace}/right/image_rect{suffix}",
                                                camera),
            "left_info": self.node.create_publisher(CameraInfo, f"{namespace}/left/camera_info",
                                                    camera),
            "right_info": self.node.create_publisher(CameraInfo,
                                                     f"{namespace}/right/camera_info", camera),
        }

    def spin(self, seconds: float, until: Callable[[], bool] | None = None) -> bool:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self.executor.spin_once(timeout_sec=min(0.05, left))
            if until is not None and until():
                return True
        return until is None

    def answer(self, send: Callable[[], Any], seconds: float = 60.0,
               resend_after: float = 5.0) -> Any:
        """The result of the service call `send` starts, sent again every `resend_after` seconds
        until answered: a service can be discovered before its reply reaches this participant,
        and the first request is then lost."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            future = send()
            if self.spin(min(resend_after, deadline - time.monotonic()), future.done):
                return future.result()
            future.cancel()
        raise AssertionError(f"no answer to the service call within {seconds:.0f} s")

    def wait_connected(self, timeout: float = 15.0) -> None:
        outputs = [f"{self.namespace}/potholes", "/diagnostics"]

        def connected() -> bool:
            return all(p.get_subscription_count() for p in self.inputs.values()) and all(
                self.node.count_publishers(t) for t in outputs)

        assert self.spin(timeout, connected), "the node did not appear in the ROS graph"
        self.spin(0.5)

    def publish(self, frame: dict[str, Any], stamp: int, infos: bool = True,
                right_stamp: int | None = None, **replace: Any) -> None:
        messages = {**frame, **replace}
        for role in (("left_info", "right_info") if infos else ()) + ("left", "right"):
            msg = messages[role]
            msg.header = header_at(right_stamp if role.startswith("right") and right_stamp
                                   is not None else stamp)
            self.inputs[role].publish(msg)

    def stamps(self, output: str = "potholes") -> list[int]:
        return [stamp_ns(m.markers[0].header if output == "pothole_markers" else m.header)
                for m in self.received[output]]

    def diagnostics(self) -> dict[str, str]:
        """Key values and message of the newest diagnostics status."""
        if not self.received["diagnostics"]:
            return {}
        status = self.received["diagnostics"][-1].status[0]
        return {"message": status.message, "level": int.from_bytes(status.level, "little")
                if isinstance(status.level, bytes) else int(status.level),
                **{kv.key: kv.value for kv in status.values}}

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def labels_of(msg: Image) -> np.ndarray:
    return decode_raw(msg, allowed=("mono16",))
