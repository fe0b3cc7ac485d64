"""The ROS 2 node: synchronized stereo in; disparity, potholes, points, markers, overlay out."""

from __future__ import annotations

import gc
import signal
import sys
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import OccupancyGrid, Odometry
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.event_handler import PublisherEventCallbacks, QoSRequestedIncompatibleQoSInfo
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSPolicyKind, QoSProfile, \
    ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_msgs.msg import Header
from stereo_msgs.msg import DisparityImage
from visualization_msgs.msg import MarkerArray

from pothole_detector_msgs.msg import PotholeArray

from .conversions import map_cloud_message, occupancy_grid_message
from ..backend import Backend, get_backend
from ..calibration import StereoCalibration, StereoCamera
from ..errors import ConfigError, InputError, PotholeError
from .outputs import ON_REQUEST, failure_messages, output_messages
from ..params import NODE_NAME, PARAMETER_BY_NAME, PARAMETERS, Config, Param
from ..pipeline import Pipeline
from ..recordings.messages import stamp_ns as stamp_of
from ..recordings.camera import pipeline_inputs, stereo_camera
from ..recordings.images import COMPRESSED_TYPE, IMAGE_TYPE, decode
from ..stages import host_kernels
from ..recordings.sync import StereoSynchronizer
from ..survey.motion import Pose2, RoadFrame, interpolate_poses, planar_pose, road_frame
from ..survey.roadmap import LiveMap, compile_map_kernels
from ..survey.tracking import MAX_ID, PotholeTracker, sightings_of
from .transport import large_image_transport

PIPELINE_PARAMETERS = frozenset(p.name for p in PARAMETERS if p.group in ("pipeline", "input"))
QOS_PARAMETERS = frozenset({"qos_depth", "use_odometry", "image_transport"})
# sets that may wait while the worker compiles the CPU kernels at start (a fresh installation)
WARM_UP_WAITING_SETS = 32
# what the diagnostics say while the worker warms up
WARMING_UP = "starting: compiling the CPU kernels (the first start after installation)"
ODOMETRY_HISTORY = 400
# the road map's outputs (published while somebody subscribes, at map_publish_rate_hz)
MAP_OUTPUTS = ("map_cloud", "map_potholes")
MAP_PARAMETERS = frozenset({"map_cell_m", "map_radius_m", "map_publish_rate_hz",
                            "local_road_radius_m", "threshold_noise_sigmas", "delta_pd_m",
                            "min_pothole_area_m2", "min_pothole_depth_m", "use_odometry"})
SYNC_PARAMETERS = frozenset({"approximate_sync", "approximate_sync_tolerance_seconds",
                             "queue_size"})
INFO_HISTORY = 32
GIL_SWITCH_INTERVAL_S = 0.0005


def image_topic(side: str, config: Config) -> str:
    """The relative image topic of ``side`` (left, right) under ``config``'s image_transport:
    ``<side>/image_rect``, or image_transport's ``<side>/image_rect/compressed``."""
    suffix = "/compressed" if config.image_transport == "compressed" else ""
    return f"{side}/image_rect{suffix}"


def descriptor(param: Param) -> ParameterDescriptor:
    """The ROS parameter descriptor of one table row (type, range, description)."""
    kinds = {bool: Parameter.Type.BOOL, int: Parameter.Type.INTEGER,
             float: Parameter.Type.DOUBLE, str: Parameter.Type.STRING}
    result = ParameterDescriptor(name=param.name, type=kinds[param.type].value,
                                 description=param.description)
    if param.choices:
        result.additional_constraints = "one of " + ", ".join(param.choices)
    if param.type is int and param.low is not None and param.high is not None:
        result.integer_range = [IntegerRange(from_value=int(param.low),
                                             to_value=int(param.high), step=0)]
    elif param.type is float and param.low is not None and param.high is not None:
        result.floating_point_range = [FloatingPointRange(from_value=float(param.low),
                                                          to_value=float(param.high), step=0.0)]
    return result


@dataclass
class StereoSet:
    """One synchronized pair with its camera infos and the time it was complete."""

    stamp_ns: int
    left: Image | CompressedImage
    right: Image | CompressedImage
    left_info: CameraInfo | None
    right_info: CameraInfo | None
    received: float


class Statistics:
    """Counters and sliding windows behind /diagnostics (thread safe)."""

    def __init__(self, window_seconds: float = 5.0) -> None:
        self.lock = threading.Lock()
        self.window = window_seconds
        self.inputs: deque[float] = deque()
        # per processed set: (when, latency, work, conversion CPU, pipeline CPU, decoding), ms
        self.processed: deque[tuple[float, float, float, float, float, float]] = deque()
        self.dropped = 0
        self.unpaired = 0
        self.errors = 0
        self.last_error = ""
        self.last_error_time = 0.0
        self.road_inlier_fraction = float("nan")
        self.potholes = 0
        self.frames = 0
        self.started = time.monotonic()
        self.last_image: float | None = None
        self.camera_frame = ""
        self.failures_in_a_row = 0
        self.last_failure = ""

    def _trim(self, now: float) -> None:
        while self.inputs and self.inputs[0] < now - self.window:
            self.inputs.popleft()
        while self.processed and self.processed[0][0] < now - self.window:
            self.processed.popleft()

    def input_set(self) -> None:
        with self.lock:
            self.inputs.append(time.monotonic())

    def image(self, frame_id: str) -> None:
        with self.lock:
            self.last_image = time.monotonic()
            self.camera_frame = frame_id or self.camera_frame

    def failed(self, reason: str) -> None:
        with self.lock:
            self.failures_in_a_row += 1
            self.last_failure = reason

    def drop(self, count: int = 1) -> None:
        with self.lock:
            self.dropped += count

    def unpaired_images(self, count: int) -> None:
        with self.lock:
            self.unpaired += count

    def error(self, message: str) -> None:
        with self.lock:
            self.errors += 1
            self.last_error = message
            self.last_error_time = time.monotonic()

    def done(self, latency_ms: float, work_ms: float, inlier_fraction: float, potholes: int,
             conversion_cpu_ms: float, pipeline_cpu_ms: float, decode_ms: float) -> None:
        """A processed set: receipt-to-published latency, the worker's wall time on it, the
        worker thread's CPU time (ms) in message conversion (images in, messages out) and in
        the pipeline, and the wall time of decoding its two images (ms)."""
        now = time.monotonic()
        with self.lock:
            self.processed.append((now, latency_ms, work_ms, conversion_cpu_ms,
                                   pipeline_cpu_ms, decode_ms))
            self.road_inlier_fraction = inlier_fraction
            self.potholes = potholes
            self.frames += 1
            self.failures_in_a_row = 0

    def keeping_up(self) -> bool:
        """Whether the worker's mean time per set (over the window) is shorter than the mean
        time between arriving sets: then waiting sets are bursts that it works off."""
        now = time.monotonic()
        with self.lock:
            self._trim(now)
            if not self.processed:
                return True
            work_s = sum(timed[2] for timed in self.processed) / len(self.processed) / 1e3
            return work_s * len(self.inputs) / self.window < 1.0

    def snapshot(self) -> dict[str, Any]:
        now = time.monotonic()
        with self.lock:
            self._trim(now)
            timed = np.array(self.processed, dtype=np.float64).reshape(-1, 6)
            latencies, work, conversion, pipeline, decoding = timed[:, 1:].T
            some = len(timed) > 0
            span = self.window
            return {
                "input_rate_hz": len(self.inputs) / span,
                "processed_rate_hz": len(self.processed) / span,
                "dropped_sets": self.dropped,
                "unpaired_images": self.unpaired,
                "latency_p50_ms": float(np.percentile(latencies, 50)) if some else 0.0,
                "latency_p95_ms": float(np.percentile(latencies, 95)) if some else 0.0,
                "work_p95_ms": float(np.percentile(work, 95)) if some else 0.0,
                "work_max_ms": float(work.max()) if some else 0.0,
                "decode_p95_ms": float(np.percentile(decoding, 95)) if some else 0.0,
                "conversion_cpu_ms_per_frame": float(conversion.mean()) if some else 0.0,
                "pipeline_cpu_ms_per_frame": float(pipeline.mean()) if some else 0.0,
                "road_inlier_fraction": self.road_inlier_fraction,
                "potholes_last_frame": self.potholes,
                "frames_processed": self.frames,
                "input_errors": self.errors,
                "last_error": self.last_error,
                "seconds_since_error": now - self.last_error_time if self.errors else -1.0,
                "seconds_since_input": now - (self.last_image or self.started),
                "failures_in_a_row": self.failures_in_a_row,
                "last_failure": self.last_failure,
                "camera_frame": self.camera_frame,
            }


class PotholeDetectorNode(Node):
    """Subscribes ``left/image_rect``, ``right/image_rect``, ``left/camera_info``,
    ``right/camera_info``; publishes ``disparity``, ``disparity_transformed``,
    ``pothole_labels``, ``pothole_points``, ``points2``, ``potholes``, ``pothole_markers``,
    ``overlay`` and ``/diagnostics``. Image outputs are computed only while subscribed; a
    worker thread takes the newest synchronized set, older waiting sets are dropped and
    counted. A pothole keeps its label while it stays in view (tracking.PotholeTracker, as in
    the survey)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        for param in PARAMETERS:
            self.declare_parameter(param.name, param.default, descriptor(param))
        values = {p.name: self.get_parameter(p.name).value for p in PARAMETERS}
        try:
            self._config = Config(values)
        except ConfigError as exc:
            raise ConfigError(f"{exc}; fix the parameter file or --ros-args -p value") from None
        self._lock = threading.Condition()
        self._stats = Statistics()
        self._log_times: dict[str, float] = {}
        self._pending: deque[StereoSet] = deque()
        self._waiting: StereoSet | None = None
        self._infos: dict[str, deque[CameraInfo]] = {"left": deque(maxlen=INFO_HISTORY),
                                                    "right": deque(maxlen=INFO_HISTORY)}
        self._reset_requested = False
        self._ids = self._tracker(self._config)
        self._odometry: deque[tuple[int, Pose2]] = deque(maxlen=ODOMETRY_HISTORY)
        self._odometry_frame = "odom"
        self._map: LiveMap | None = None
        self._pipeline: Pipeline | None = None
        self._pipeline_key: tuple[Any, ...] | None = None
        self._backend: Backend | None = None
        self._backend_choice = ""
        self._stopping = False
        self._synchronizer = StereoSynchronizer.from_config(self._config)
        self._inputs: list[Any] = []
        self._outputs: dict[str, Any] = {}
        self._noted_cameras: set[StereoCamera] = set()
        self._warming_up = True
        self._decoder = ThreadPoolExecutor(1, thread_name_prefix="pothole_decoder")
        self._make_io(self._config)
        self._diagnostics_timer = self._wall_timer(self._config.diagnostics_period_seconds)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._worker = threading.Thread(target=self._work, name="pothole_worker", daemon=True)
        self._worker.start()

    # --- parameters -------------------------------------------------------------------------

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        try:
            self._config.replace(**{p.name: p.value for p in parameters
                                    if p.name in PARAMETER_BY_NAME})
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        parameters = [p for p in parameters if p.name in PARAMETER_BY_NAME]
        if not parameters:
            return
        changed = {p.name for p in parameters}
        with self._lock:
            self._config = self._config.replace(**{p.name: p.value for p in parameters})
            config = self._config
            if changed & SYNC_PARAMETERS:
                self._stats.unpaired_images(self._synchronizer.reset())
                self._synchronizer = StereoSynchronizer.from_config(config)
            self._ids.match_distance_m = config.track_match_distance_m
            self._ids.forget_frames = config.track_forget_frames
            if changed & MAP_PARAMETERS:
                self._map = None
        if changed & QOS_PARAMETERS:
            self._make_io(config)
        if "diagnostics_period_seconds" in changed:
            self._diagnostics_timer.cancel()
            self.destroy_timer(self._diagnostics_timer)
            self._diagnostics_timer = self._wall_timer(config.diagnostics_period_seconds)
        self.get_logger().info(f"parameters changed: {', '.join(sorted(changed))}")

    # --- topics -----------------------------------------------------------------------------

    def _warm_up(self) -> None:
        """The worker's start: the backend made and, on the CPU, the kernels compiled (or
        loaded from Numba's cache) before the first frame, the road map's too where the map
        is on; sets arriving meanwhile wait (up to WARM_UP_WAITING_SETS) and the diagnostics
        say so."""
        config = self._config
        if not self._backend_for(config).is_gpu:
            host_kernels.compile_cpu_kernels(census=config.matcher == "census")
        if config.map_cell_m > 0:
            compile_map_kernels()
        with self._lock:
            self._warming_up = False

    def _waiting_limit(self) -> int:
        """How many synchronized sets may wait for the worker (more while it warms up)."""
        return max(self._config.max_waiting_sets,
                   WARM_UP_WAITING_SETS if self._warming_up else 0)

    def _make_io(self, config: Config) -> None:
        for subscription in self._inputs:
            self.destroy_subscription(subscription)
        for publisher in self._outputs.values():
            self.destroy_publisher(publisher)
        # inputs as camera drivers publish (sensor data: best effort, which takes reliable
        # publishers too), outputs reliable; each per topic through the standard
        # qos_overrides.<topic>.subscription|publisher.<policy> parameters
        # (a profile of its own for each topic: the overrides change it in place)
        def profile(reliability: ReliabilityPolicy) -> QoSProfile:
            return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=config.qos_depth,
                              reliability=reliability, durability=DurabilityPolicy.VOLATILE)

        overrides = QoSOverridingOptions.with_default_policies()

        def subscribe(kind: Any, topic: str, callback: Any) -> Any:
            return self.create_subscription(kind, topic, callback,
                                            profile(ReliabilityPolicy.BEST_EFFORT),
                                            qos_overriding_options=overrides)

        def publish(kind: Any, topic: str) -> Any:
            events = PublisherEventCallbacks(
                incompatible_qos=lambda info: self._incompatible_subscriber(topic, info))
            return self.create_publisher(kind, topic, profile(ReliabilityPolicy.RELIABLE),
                                         event_callbacks=events,
                                         qos_overriding_options=overrides)

        kind = CompressedImage if config.image_transport == "compressed" else Image
        self._inputs = [
            subscribe(kind, image_topic("left", config), lambda m: self._on_image("left", m)),
            subscribe(kind, image_topic("right", config), lambda m: self._on_image("right", m)),
            subscribe(CameraInfo, "left/camera_info", lambda m: self._on_info("left", m)),
            subscribe(CameraInfo, "right/camera_info", lambda m: self._on_info("right", m)),
        ]
        if config.use_odometry:
            self._inputs.append(subscribe(Odometry, "odom", self._on_odometry))
        self._outputs = {
            "disparity": publish(DisparityImage, "disparity"),
            "disparity_transformed": publish(Image, "disparity_transformed"),
            "pothole_labels": publish(Image, "pothole_labels"),
            "pothole_points": publish(PointCloud2, "pothole_points"),
            "points2": publish(PointCloud2, "points2"),
            "potholes": publish(PotholeArray, "potholes"),
            "pothole_markers": publish(MarkerArray, "pothole_markers"),
            "overlay": publish(Image, "overlay"),
            "map_cloud": publish(PointCloud2, "map_cloud"),
            "map_potholes": publish(OccupancyGrid, "map_potholes"),
            "diagnostics": self.create_publisher(DiagnosticArray, "/diagnostics", 10),
        }

    def _incompatible_subscriber(self, topic: str,
                                 info: QoSRequestedIncompatibleQoSInfo) -> None:
        """A subscriber asked for QoS that an output does not offer: say what it offers and how
        to match, once per topic and throttle period."""
        policy = QoSPolicyKind(info.last_policy_kind).name.lower()
        name = self.resolve_topic_name(topic)
        offered = self._outputs[topic].qos_profile if topic in self._outputs else None
        offer = "" if offered is None else (
            f"it offers {offered.reliability.name.lower()}, "
            f"{offered.durability.name.lower()} durability (no history for late joiners), "
            f"keep last {offered.depth}; ")
        self._problem(f"qos:{name}",
                      f"a subscriber of {name} asks for QoS the publisher does not offer (DDS "
                      f"names the {policy} policy), so it gets nothing; {offer}subscribe with "
                      f"volatile durability, or set qos_overrides.{name}.publisher.* to match")

    def _on_odometry(self, msg: Odometry) -> None:
        pose = planar_pose(msg.pose.pose.position, msg.pose.pose.orientation)
        with self._lock:
            self._odometry.append((stamp_of(msg.header), pose))
            self._odometry_frame = msg.header.frame_id or self._odometry_frame

    def _on_info(self, side: str, msg: CameraInfo) -> None:
        with self._lock:
            self._infos[side].append(msg)
            waiting = self._waiting
            if waiting is None or not self._infos_reached(waiting.stamp_ns):
                return
            self._waiting = None
        self._complete(waiting.stamp_ns, waiting.left, waiting.right, waiting.received)

    def _infos_reached(self, stamp_ns: int) -> bool:
        """Both camera_info streams have reached ``stamp_ns`` (ns, less the sync tolerance)."""
        earliest = stamp_ns - self._synchronizer.tolerance_ns
        return all(history and stamp_of(history[-1].header) >= earliest
                   for history in self._infos.values())

    def _on_image(self, side: str, msg: Image) -> None:
        stamp_ns = stamp_of(msg.header)
        self._stats.image(msg.header.frame_id)
        with self._lock:
            outcome = self._synchronizer.add(side, stamp_ns, msg)
            if outcome.backwards:
                self._reset_requested = True
            stalled = not outcome.pairs and min(
                self._synchronizer.waiting(s) for s in ("left", "right")) >= 2
        if stalled:
            mode = ("differ by more than approximate_sync_tolerance_seconds"
                    if self._config.approximate_sync else
                    "never match exactly; set approximate_sync:=true unless the cameras are "
                    "hardware-triggered")
            self._problem("sync", f"left and right images arrive but their stamps {mode}")
        if outcome.dropped:
            self._stats.unpaired_images(outcome.dropped)
        if outcome.duplicate:
            self._problem("duplicate", outcome.duplicate)
        elif outcome.dropped:
            self._problem("unpaired", f"{outcome.dropped} image(s) found no partner and were "
                          "dropped; are both cameras publishing at the same rate?")
        if outcome.backwards:
            self._problem("stamps", outcome.backwards)
        now = time.monotonic()
        for pair_stamp, left, right in outcome.pairs:
            self._stats.input_set()
            self._complete(pair_stamp, left, right, now)

    def _complete(self, stamp_ns: int, left: Image, right: Image, received: float) -> None:
        """Pair a synchronized set with camera infos: those of its own stamp, else the newest
        once both info streams have passed its stamp. A set whose infos may still be in
        flight waits (one slot); the next set releases it with the newest infos."""
        ready: list[StereoSet] = []
        with self._lock:
            missing = [side for side, history in self._infos.items() if not history]
            held = self._waiting
            self._waiting = None
            if held is not None and not missing:
                ready.append(self._with_infos(held))
            elif held is not None:
                self._stats.drop()
            current = StereoSet(stamp_ns, left, right, None, None, received)
            exact = all(self._exact_info(side, stamp_ns) for side in ("left", "right"))
            if not missing and (exact or self._infos_reached(stamp_ns)):
                ready.append(self._with_infos(current))
            else:
                self._waiting = current
            for job in ready:
                self._pending.append(job)
                while len(self._pending) > self._waiting_limit():
                    self._pending.popleft()
                    self._stats.drop()
            if ready:
                self._lock.notify()
        if missing:
            topics = " and ".join(f"{side}/camera_info" for side in missing)
            self._problem("camera_info", f"no camera_info received on {topics} yet; holding "
                                         "the newest stereo pair until it arrives")

    def _exact_info(self, side: str, stamp_ns: int) -> CameraInfo | None:
        """The camera_info of ``side`` stamped ``stamp_ns`` (within the sync tolerance)."""
        tolerance = self._synchronizer.tolerance_ns
        for info in reversed(self._infos[side]):
            if abs(stamp_of(info.header) - stamp_ns) <= tolerance:
                return info
        return None

    def _with_infos(self, job: StereoSet) -> StereoSet:
        infos = [self._exact_info(side, job.stamp_ns) or self._infos[side][-1]
                 for side in ("left", "right")]
        return StereoSet(job.stamp_ns, job.left, job.right, infos[0], infos[1], job.received)

    # --- processing -------------------------------------------------------------------------

    def _work(self) -> None:
        try:
            self._warm_up()
        except Exception as exc:  # noqa: BLE001 - frames will say what is wrong
            self._problem("warm-up", f"could not prepare the pipeline: {exc}")
            with self._lock:
                self._warming_up = False
        while True:
            with self._lock:
                while not self._pending and not self._stopping:
                    self._lock.wait()
                if self._stopping:
                    return
                if len(self._pending) > 1 and not self._stats.keeping_up():
                    self._stats.drop(len(self._pending) - 1)
                    self._pending = deque([self._pending[-1]])
                job = self._pending.popleft()
                config = self._config
                reset, self._reset_requested = self._reset_requested, False
            try:
                self._process(job, config, reset)
            except PotholeError as exc:
                self._problem(type(exc).__name__, str(exc))
                self._stats.failed(str(exc))
                self._publish_failure(job, str(exc))
            except Exception as exc:  # noqa: BLE001 - the node must survive any frame
                reason = f"frame failed with {type(exc).__name__}: {exc}"
                self._problem("internal", reason)
                self._stats.failed(reason)
                self._publish_failure(job, f"internal error: {type(exc).__name__}: {exc}")

    def _publish_failure(self, job: StereoSet, reason: str) -> None:
        for name, message in failure_messages(job.left.header, reason).items():
            self._outputs[name].publish(message)

    def _backend_for(self, config: Config) -> Backend:
        """The backend ``config`` asks for, made on first use and when the choice changes."""
        if self._backend is None or self._backend_choice != config.backend:
            self._backend = get_backend(config.backend)
            self._backend_choice = config.backend
            self.get_logger().info(f"backend: {self._backend.name}")
        return self._backend

    def _pipeline_for(self, config: Config, camera: StereoCamera) -> Pipeline:
        """The pipeline of ``camera`` (rectifying its images where config's rectify says so),
        made anew when the camera or a pipeline parameter changes; a new camera's notes
        (a baseline or focal length taken from the parameters, rectification) are logged
        once."""
        key = (tuple(sorted((k, v) for k, v in config.as_dict().items()
                            if k in PIPELINE_PARAMETERS or k == "backend")), camera)
        if self._pipeline is None or key != self._pipeline_key:
            calibration, rectification = pipeline_inputs(camera, config.rectify)
            if camera not in self._noted_cameras:
                self._noted_cameras.add(camera)
                for note in camera.notes():
                    self.get_logger().info(note)
                if rectification is not None:
                    self.get_logger().info(
                        f"raw images ({camera.left.distortion_model}): rectifying them from "
                        "camera_info; outputs are in the rectified frame")
            self._pipeline = Pipeline(config, calibration, self._backend_for(config),
                                      rectification)
            self._pipeline_key = key
            gc.freeze()  # the backend's modules and the pipeline, as at start-up (main)
        return self._pipeline

    def _process(self, job: StereoSet, config: Config, reset: bool) -> None:
        began = time.monotonic()
        started = time.thread_time()
        image_type = IMAGE_TYPE if isinstance(job.left, Image) else COMPRESSED_TYPE
        sizes = [(int(info.width), int(info.height)) for info in (job.left_info, job.right_info)]
        # as the matcher takes them; the right image decodes on a thread of its own (OpenCV's
        # decoders release the GIL)
        right_future = self._decoder.submit(decode, job.right, image_type, sizes[1], True)
        try:
            left = decode(job.left, image_type, sizes[0], grey=True)
        finally:
            right = right_future.result()
        decoded = time.monotonic()
        if left.shape[:2] != right.shape[:2]:
            raise InputError(f"left image is {left.shape[1]}x{left.shape[0]} but the right one "
                             f"{right.shape[1]}x{right.shape[0]}")
        height, width = left.shape[:2]
        camera = stereo_camera(job.left_info, job.right_info, width, height, config.baseline_m,
                               config.focal_px)
        pipeline = self._pipeline_for(config, camera)
        calibration = pipeline.calibration
        if reset:
            pipeline.reset()
            self._ids.reset()
            self._map = None
        converted = time.thread_time()
        result = pipeline.run(left, right)
        ran = time.thread_time()
        header = job.left.header
        publishers = self._outputs
        wanted = [name for name in ON_REQUEST if publishers[name].get_subscription_count() > 0]
        height, width = pipeline.output_shape(left.shape)
        plane = self._road_frame(result, calibration, width, height)
        pose = self._pose_at(job.stamp_ns)
        ids = self._ids.update(sightings_of(job.stamp_ns, result, plane, width, height),
                               pose or Pose2())
        view = left
        if {"overlay", "points2"} & set(wanted):  # pictures in colour, as the camera took them
            view = pipeline.view(decode(job.left, image_type, sizes[0]))
        for name, message in output_messages(result, view, calibration, header, wanted,
                                             ids).messages.items():
            publishers[name].publish(message)
        self._publish_map(result, plane, calibration, pipeline.view(left), pose, header, config)
        published = time.thread_time()
        finished = time.monotonic()
        self._stats.done((finished - job.received) * 1e3, (finished - began) * 1e3,
                         result.road.inlier_fraction, len(result.potholes),
                         (converted - started + published - ran) * 1e3, (ran - converted) * 1e3,
                         (decoded - began) * 1e3)

    @staticmethod
    def _tracker(config: Config) -> PotholeTracker:
        return PotholeTracker(config.track_match_distance_m, config.track_forget_frames,
                              max_id=MAX_ID, keep_history=False)

    @staticmethod
    def _road_frame(result: Any, calibration: StereoCalibration, width: int,
                    height: int) -> RoadFrame:
        """The frame's road frame; NaN where the road gives none (no pothole then matches a
        track, and the map skips the frame)."""
        try:
            return road_frame(result.road, calibration, width, height)
        except ValueError:
            return RoadFrame(np.full(3, np.nan), np.full((3, 3), np.nan))

    def _pose_at(self, stamp_ns: int) -> Pose2 | None:
        """The odometry's pose at the frame's stamp (use_odometry), else None."""
        if not self._config.use_odometry:
            return None
        with self._lock:
            history = list(self._odometry)
        found = interpolate_poses(np.array([t for t, _ in history], dtype=np.int64),
                                  [p for _, p in history], stamp_ns) if history else None
        if found is None:
            self._problem("odometry", "no odometry on odom within 0.5 s of the stereo "
                                      "stamp; tracking potholes without the motion")
        return found

    def _publish_map(self, result: Any, plane: RoadFrame, calibration: StereoCalibration,
                     gray: np.ndarray, pose: Pose2 | None, header: Header,
                     config: Config) -> None:
        """Fuse the frame into the live road map while somebody subscribes to it, and publish
        the map around the camera when a view is due: in the odometry's frame (use_odometry),
        else in the first frame's road frame (``<camera frame>_road_map``), placed by visual
        odometry."""
        publishers = [self._outputs[name] for name in MAP_OUTPUTS]
        listening = [p.get_subscription_count() > 0 for p in publishers]
        if config.map_cell_m <= 0 or config.map_publish_rate_hz <= 0 or not any(listening) \
                or not np.isfinite(plane.axes).all():
            return
        if self._map is None:
            self._map = LiveMap(config)
        if config.use_odometry and pose is None:
            return
        self._map.add(result, plane, calibration, gray, pose)
        view = self._map.due(time.monotonic())
        if view is None:
            return
        frame_id = self._odometry_frame if config.use_odometry \
            else f"{header.frame_id}_road_map"
        stamped = Header(stamp=header.stamp, frame_id=frame_id)
        for publisher, wanted, make in zip(publishers, listening,
                                           (map_cloud_message, occupancy_grid_message)):
            if wanted:
                publisher.publish(make(view, stamped))

    # --- reporting --------------------------------------------------------------------------

    def _problem(self, kind: str, message: str) -> None:
        self._stats.error(message)
        now = time.monotonic()
        if now - self._log_times.get(kind, -1e18) >= self._config.log_throttle_seconds:
            self._log_times[kind] = now
            self.get_logger().warning(message)

    def _publish_diagnostics(self) -> None:
        """The node's health: ERROR after error_after_failed_frames failed frames in a row
        (with the last reason), WARN when no stereo image came for input_timeout_seconds or
        after a recent input problem, else OK; named after the node's full name, with the
        camera's frame as hardware id."""
        snapshot = self._stats.snapshot()
        config = self._config
        recent_error = 0 <= snapshot["seconds_since_error"] < 2 * self._stats.window
        level, message = DiagnosticStatus.OK, WARMING_UP if self._warming_up else "ok"
        if recent_error:
            level, message = DiagnosticStatus.WARN, snapshot["last_error"]
        if snapshot["seconds_since_input"] > config.input_timeout_seconds:
            level, message = DiagnosticStatus.WARN, (
                f"no stereo image for {snapshot['seconds_since_input']:.1f} s on "
                f"{self.resolve_topic_name(image_topic('left', config))} and "
                f"{self.resolve_topic_name(image_topic('right', config))}"
                + (f"; the last input problem: {snapshot['last_error']}" if recent_error
                   else ""))
        if snapshot["failures_in_a_row"] >= config.error_after_failed_frames:
            level, message = DiagnosticStatus.ERROR, (
                f"{snapshot['failures_in_a_row']} frames in a row failed; the last: "
                f"{snapshot['last_failure']}")
        status = DiagnosticStatus(
            name=f"{self.get_fully_qualified_name()}: pipeline",
            hardware_id=snapshot["camera_frame"] or "stereo camera",
            level=level, message=message,
            values=[KeyValue(key="backend",
                             value=self._backend.name if self._backend else "not started")]
            + [KeyValue(key=key, value=f"{value:.3f}" if isinstance(value, float) else str(value))
               for key, value in snapshot.items()],
        )
        self._outputs["diagnostics"].publish(
            DiagnosticArray(header=self._header_now(), status=[status]))

    def _wall_timer(self, period: float) -> Any:
        """The diagnostics timer, on the steady clock: it keeps firing while a simulated
        /clock (use_sim_time) pauses."""
        return self.create_timer(period, self._publish_diagnostics,
                                 clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _header_now(self) -> Header:
        return Header(stamp=self.get_clock().now().to_msg())

    def destroy_node(self) -> None:
        with self._lock:
            self._stopping = True
            self._lock.notify_all()
        self._worker.join(timeout=5.0)
        self._decoder.shutdown(wait=False, cancel_futures=True)
        super().destroy_node()


USAGE = """usage: pothole_detector_node [--ros-args -r __ns:=NAMESPACE -p NAME:=VALUE ...
                              --params-file config/pothole_detector.yaml]

The pothole detector as a ROS 2 node. Subscribes to left/image_rect, right/image_rect (with
image_transport:=compressed, left/image_rect/compressed and right/image_rect/compressed; raw
images are rectified from camera_info), left/camera_info and right/camera_info (relative to
its namespace; remap with -r) and publishes
potholes, disparity, disparity_transformed, pothole_labels, pothole_points, points2,
pothole_markers, overlay and /diagnostics. Every parameter, with its range, is in
config/pothole_detector.yaml; the README lists the topics and their types."""


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``pothole_detector_node``: spin the node until Ctrl-C (``--help`` before
    any ``--ros-args``: print the usage and exit)."""
    args = list(sys.argv if argv is None else argv)
    ours = args[1:args.index("--ros-args")] if "--ros-args" in args else args[1:]
    if "-h" in ours or "--help" in ours:
        print(USAGE)
        return 0
    large_image_transport()
    # The executor thread takes each camera message under the GIL while the worker runs
    # Python between kernels; at the default 5 ms hand-over, sets queue up and arrive in bursts.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    # Ctrl-C and SIGTERM stop the spin here, not the ROS context: the worker finishes and
    # publishes its frame before the context goes. Both handlers are set explicitly: a node
    # started in the background of a script inherits SIGINT ignored.
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        node = PotholeDetectorNode()
    except PotholeError as exc:
        print(f"pothole_detector_node: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    except KeyboardInterrupt:
        rclpy.try_shutdown()
        return 0
    # start-up's objects (modules, the node) leave the collector's view: a full collection
    # then scans only what frames allocate, instead of pausing both threads for tens of ms
    gc.freeze()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()
    return 0


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":
    sys.exit(main())
