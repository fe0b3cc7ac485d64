"""Bags on rosbags: play into the live graph, record, offline processing, our own drives."""

from __future__ import annotations

import copy
import itertools
import logging
import math
import re
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from . import conversions, msgtypes
from .backend import get_backend
from .calibration import StereoCamera
from .errors import InputError, PotholeError
from .imageio import write_rgb
from .geodesy import latlon_of
from .msgtypes import message, serialize, typestore
from .outputs import OFFLINE_OUTPUTS, OUTPUT_TYPES, failure_messages, output_messages
from .params import Config
from .pipeline import Pipeline
from .recordings.bags import (BagFrame, LogSpan, SetCounts, cdr_bytes, convert_set,
                              message_count, open_bag, read_sets_ahead, stereo_sets)
from .recordings.camera import pipeline_inputs
from .recordings.images import COMPRESSED_TYPE, IMAGE_TYPE, encode_raw
from .recordings.readahead import decoded_frames
from .recordings.topics import INFO_TYPE, StereoTopics, find_stereo_topics
from .transport import large_image_transport

_log = logging.getLogger(__name__)


def parse_remaps(remaps: Sequence[str]) -> dict[str, str]:
    """``OLD:=NEW`` strings as a mapping; raises InputError on a malformed one."""
    mapping = {}
    for remap in remaps:
        old, sep, new = remap.partition(":=")
        if not sep or not old or not new:
            raise InputError(f"remap {remap!r} must look like /old/topic:=/new/topic")
        mapping[old] = new
    return mapping


def writer_for(path: str | Path, storage: str) -> Writer:
    """A new ROS 2 bag (version 9) in ``storage`` mcap (zstd chunks) or sqlite3."""
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
    if plugin is None:
        raise InputError(f"storage must be mcap or sqlite3, got {storage!r}")
    if Path(path).exists():
        raise InputError(f"{path} exists already; choose a new output path")
    writer = Writer(Path(path), version=9, storage_plugin=plugin)
    if plugin == StoragePlugin.MCAP:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    return writer


# --- play --------------------------------------------------------------------------------

def play(bag: str | Path, rate: float = 1.0, loop: bool = False,
         remaps: Sequence[str] = (), reliability: str = "reliable",
         wait_for_subscribers: float = 0.0, clock: bool = True,
         should_stop: Callable[[], bool] = lambda: False) -> int:
    """Publish a recorded bag into the live graph on its recorded clock (scaled by ``rate``),
    optionally publishing /clock and waiting up to ``wait_for_subscribers`` s for every topic
    to have a subscriber. Returns the number of messages published."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    if rate <= 0:
        raise InputError(f"--rate must be positive, got {rate}")
    mapping = parse_remaps(remaps)
    reader = open_bag(bag)
    own_context = not rclpy.ok()
    if own_context:
        large_image_transport()
        rclpy.init(args=[])
    node = rclpy.create_node("pothole_detector_player")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE
                     if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT)
    published = 0
    try:
        publishers = {
            c.id: node.create_publisher(message(c.msgtype),
                                        mapping.get(c.topic, c.topic), qos)
            for c in reader.connections
        }
        clock_publisher = node.create_publisher(Clock, "/clock", 10) if clock else None
        deadline = time.monotonic() + wait_for_subscribers
        while time.monotonic() < deadline and \
                not all(p.get_subscription_count() for p in publishers.values()):
            time.sleep(0.05)
        if wait_for_subscribers > 0:
            time.sleep(min(1.0, wait_for_subscribers))  # let the readers match us in turn
        while True:
            start_wall, start_bag = time.monotonic(), reader.start_time
            for connection, timestamp, rawdata in reader.messages():
                if should_stop():
                    return published
                delay = start_wall + (timestamp - start_bag) / 1e9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                if clock_publisher is not None:
                    clock_msg = Clock()
                    clock_msg.clock.sec, clock_msg.clock.nanosec = divmod(timestamp, 10**9)
                    clock_publisher.publish(clock_msg)
                publishers[connection.id].publish(cdr_bytes(reader, connection, rawdata))
                published += 1
            if not loop:
                break
        time.sleep(0.2)
    finally:
        reader.close()
        node.destroy_node()
        if own_context:
            rclpy.try_shutdown()
    return published


# --- record ------------------------------------------------------------------------------

def record(out: str | Path, topics: Sequence[str], storage: str = "mcap",
           duration: float | None = None, discovery_timeout: float = 10.0,
           reliability: str = "reliable",
           should_stop: Callable[[], bool] = lambda: False) -> dict[str, int]:
    """Record live ``topics`` (raw CDR, receive time) into a new bag until Ctrl-C, ``duration``
    s or ``should_stop()``. Topic types are discovered from the graph. Returns counts."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    store = typestore()
    own_context = not rclpy.ok()
    if own_context:
        large_image_transport()
        rclpy.init(args=[])
    node = rclpy.create_node("pothole_detector_recorder")
    writer = writer_for(out, storage)
    counts = {topic: 0 for topic in topics}
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE
                     if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    writer.open()
    try:
        connections: dict[str, Connection] = {}
        subscriptions = []
        deadline = time.monotonic() + discovery_timeout
        start = time.monotonic()
        while True:
            known = dict(node.get_topic_names_and_types())
            for topic in topics:
                if topic in connections or topic not in known:
                    continue
                msgtype = known[topic][0]
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)

                def on_message(data: bytes, topic: str = topic) -> None:
                    writer.write(connections[topic], time.time_ns(), data)
                    counts[topic] += 1

                subscriptions.append(node.create_subscription(
                    message(msgtype), topic, on_message, qos, raw=True))
            if len(connections) < len(topics) and time.monotonic() > deadline:
                missing = sorted(set(topics) - set(connections))
                raise InputError(f"no publisher of {', '.join(missing)} appeared within "
                                 f"{discovery_timeout:.0f} s; is the graph running?")
            executor.spin_once(timeout_sec=0.05)
            if should_stop() or (duration is not None and time.monotonic() - start > duration):
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # Ctrl-C or SIGTERM: close the bag properly
    finally:
        writer.close()
        executor.shutdown()
        node.destroy_node()
        if own_context:
            rclpy.try_shutdown()
    return counts


# --- process -----------------------------------------------------------------------------

def _reason_kind(reason: str) -> str:
    """A failure's reason with its numbers left out: failures alike count together."""
    return re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "#", reason)


@dataclass
class FailureTally:
    """Frames that could not be processed: per kind of reason (the reason with its numbers
    left out) how many, the first one's reason and stamp (ns)."""

    kinds: dict[str, list[Any]] = field(default_factory=dict)

    def add(self, stamp_ns: int, reason: str) -> None:
        entry = self.kinds.setdefault(_reason_kind(reason), [0, reason, stamp_ns])
        entry[0] += 1

    @property
    def total(self) -> int:
        return sum(entry[0] for entry in self.kinds.values())

    def rows(self) -> list[tuple[int, str, int]]:
        """(count, first reason, first stamp ns) per kind, most frequent first."""
        return sorted(((count, reason, stamp) for count, reason, stamp in self.kinds.values()),
                      key=lambda row: (-row[0], row[2]))

    def lines(self) -> list[str]:
        """One line per kind of reason."""
        return [f"{count} frame{'s' if count != 1 else ''} failed: {reason} (first at stamp "
                f"{stamp})" for count, reason, stamp in self.rows()]


@dataclass
class ProcessSummary:
    """What :func:`process` did: frames processed, failed (by reason), potholes found, images
    without a partner, messages that could not be read, time per processed frame."""

    frames: int = 0
    potholes: int = 0
    counts: SetCounts = field(default_factory=SetCounts)
    failures: FailureTally = field(default_factory=FailureTally)
    milliseconds: list[float] = field(default_factory=list)

    @property
    def failed(self) -> int:
        return self.failures.total

    @property
    def unpaired(self) -> int:
        return self.counts.unpaired

    def text(self) -> str:
        per_frame = float(np.mean(self.milliseconds)) if self.milliseconds else 0.0
        corrupt = (f", {self.counts.corrupt} corrupt messages skipped"
                   if self.counts.corrupt else "")
        return (f"{self.frames} frames, {self.potholes} potholes found, {per_frame:.0f} ms per "
                f"frame, {self.failed} failed, {self.unpaired} unpaired images{corrupt}")


def frame_results(reader: AnyReader, stereo: StereoTopics, config: Config, backend: Any,
                  summary: ProcessSummary,
                  progress: Callable[[int, int], None] | None = None,
                  span: LogSpan | None = None, read_threads: int = 1,
                  others: Sequence[str] = (), collected: list | None = None,
                  read_processes: int = 0, colour: bool = False
                  ) -> Iterator[tuple[BagFrame, Any]]:
    """(frame, PipelineResult or the PotholeError that stopped it) for the synchronized sets
    of a bag, or of a :class:`LogSpan` of it (with the sets of its lead before it: their
    ``logged_ns`` is before the span's start), in order; each frame carries the rectified
    pair's calibration and, where its images come raw, the rectification (the ``rectify``
    parameter). One pipeline per run of frames with the same stereo camera (its notes and
    whether it rectifies are logged once); within a run the host prepares the next pair while
    the device works (Pipeline.run_stream). ``progress(done, total)`` is called per set (of
    the whole bag's left images, or of a span's share of them). ``read_threads`` > 1: the bag
    is read ahead in that many threads (recordings.bags.read_sets_ahead; ``summary`` then
    counts no unpaired images) where its camera_info topics hold a message per image or so (a
    block then finds its infos in itself; a bag with latched infos is read in this thread);
    ``read_processes`` > 0: read and decoded by that many worker processes instead
    (recordings.readahead, on the same condition). The messages of the ``others`` topics
    logged in the span go into ``collected`` in the same pass (complete once the frames
    are). The pipeline takes the images as the matcher does (recordings.images.decode's
    ``grey``); ``colour``: each frame also keeps its left image in colour, for pictures (not
    with ``read_processes``)."""
    images = total = message_count(reader, stereo.left)
    if span is not None:
        bag_ns = max(reader.end_time - reader.start_time + 1, 1)
        total = round(total * min(span.stop_ns - span.start_ns, bag_ns) / bag_ns)

    def prepared() -> Iterator[BagFrame | tuple[BagFrame, PotholeError]]:
        streamed_infos = all(2 * message_count(reader, topic) >= images
                             for topic in (stereo.left_info, stereo.right_info))
        if read_processes > 0 and streamed_infos and not colour:
            for index, item in enumerate(decoded_frames(reader, stereo, config, span,
                                                        read_processes, others, collected,
                                                        summary.counts)):
                if progress is not None:
                    progress(min(index, total), total)
                yield item
            return
        sets = read_sets_ahead(reader, stereo, config, span, read_threads, others,
                               collected, summary.counts) \
            if read_threads > 1 and streamed_infos \
            else stereo_sets(reader, stereo, config, summary.counts, span, others, collected)
        for index, (stamp, logged, left_msg, right_msg, left_cal, right_cal) in enumerate(sets):
            if progress is not None:
                progress(min(index, total), total)
            try:
                left_px, right_px, camera, left_colour = convert_set(
                    stereo, left_msg, right_msg, left_cal, right_cal, config, colour)
            except PotholeError as exc:
                yield BagFrame(stamp, left_msg.header, None, None, None, logged), exc
                continue
            yield BagFrame(stamp, left_msg.header, left_px, right_px, camera, logged,
                           left_colour=left_colour)

    def key(item: BagFrame | tuple[BagFrame, PotholeError]) -> Any:
        return None if isinstance(item, tuple) else item.camera

    for camera, run in itertools.groupby(prepared(), key):
        if camera is None:
            yield from run
            continue
        try:
            calibration, rectification = pipeline_inputs(camera, config.rectify)
        except PotholeError as exc:
            for frame in run:
                yield frame, exc
            continue
        for note in camera.notes():
            _log.info(note)
        if rectification is not None:
            _log.info(f"raw images ({camera.left.distortion_model}): rectifying them from "
                      "camera_info")
        frames, streamed = itertools.tee(run)
        outcomes = Pipeline(config, calibration, backend, rectification).run_stream(
            (frame.left, frame.right) for frame in streamed)
        for frame in frames:
            yield replace(frame, calibration=calibration, rectification=rectification), \
                next(outcomes)
    if progress is not None:
        progress(total, total)


def process(bag: str | Path, out: str | Path, config: Config, storage: str = "mcap",
            keep_inputs: bool = True, left: str | None = None, right: str | None = None,
            left_info: str | None = None, right_info: str | None = None,
            progress: Callable[[int, int], None] | None = None,
            pictures: str | Path | None = None) -> ProcessSummary:
    """Run the pipeline on every synchronized stereo set of ``bag`` and write a new bag at
    ``out`` with the inputs (``keep_inputs``) and every output topic of the node, stamped with
    the input stamps, under the input's namespace (raw inputs: the outputs are in the
    rectified frame). ``pictures``: also write overlay PNGs. The topics used are logged in one
    line. A bag damaged part way keeps the frames before the damage; the InputError that
    says where is raised once they are written."""
    reader = open_bag(bag)
    summary = ProcessSummary()
    try:
        bag_topics = {c.topic: c.msgtype for c in reader.connections}
        stereo = find_stereo_topics(bag_topics, left, right, left_info, right_info)
        _log.info(stereo.describe())
        namespace = stereo.namespace
        writer = writer_for(out, storage)
        writer.open()
        store = typestore()
        try:
            output = {name: writer.add_connection(f"{namespace}/{name}", msgtype,
                                                  typestore=store)
                      for name, msgtype in OUTPUT_TYPES.items() if name in OFFLINE_OUTPUTS}
            if keep_inputs:
                copy_messages(reader, writer, (stereo.left, stereo.right, stereo.left_info,
                                               stereo.right_info))
            backend = get_backend(config.backend)
            if pictures is not None:
                Path(pictures).mkdir(parents=True, exist_ok=True)
            started = time.perf_counter()
            for frame, outcome in frame_results(reader, stereo, config, backend, summary,
                                                progress, colour=True):
                if isinstance(outcome, PotholeError):
                    summary.failures.add(frame.stamp, str(outcome))
                    for name, made in failure_messages(frame.header, str(outcome)).items():
                        writer.write(output[name], frame.stamp,
                                     serialize(made, OUTPUT_TYPES[name]))
                    started = time.perf_counter()
                    continue
                result = outcome
                made = output_messages(result, frame.left_view(), frame.calibration,
                                       frame.header, OFFLINE_OUTPUTS)
                summary.frames += 1
                summary.potholes += len(result.potholes)
                for name, msg in made.messages.items():
                    writer.write(output[name], frame.stamp, serialize(msg, OUTPUT_TYPES[name]))
                if pictures is not None:
                    write_rgb(Path(pictures) / f"overlay_{frame.stamp}.png", made.overlay)
                summary.milliseconds.append((time.perf_counter() - started) * 1e3)
                started = time.perf_counter()
        finally:
            writer.close()
    finally:
        reader.close()
    return summary


def copy_messages(reader: AnyReader, writer: Writer, topics: Sequence[str]) -> None:
    """Copy the messages of ``topics`` from a bag into a new one (ROS 2 CDR), up to where
    the bag is damaged, if it is."""
    store = typestore()
    bag_topics = {c.topic: c.msgtype for c in reader.connections}
    connections = {topic: writer.add_connection(topic, bag_topics[topic], typestore=store)
                   for topic in topics}
    messages = reader.messages(connections=[c for c in reader.connections
                                            if c.topic in connections])
    while True:
        try:
            connection, timestamp, rawdata = next(messages)
        except StopIteration:
            return
        except Exception:  # noqa: BLE001 - a damaged bag: reading the sets will say where
            return
        writer.write(connections[connection.topic], timestamp,
                     cdr_bytes(reader, connection, rawdata))


ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
GNSS_TYPE = "sensor_msgs/msg/NavSatFix"


def odometry_message(stamp_ns: int, x: float, y: float, yaw: float,
                     frame_id: str = "odom", child_frame_id: str = "base_link") -> Any:
    """nav_msgs/Odometry of a planar pose (m, rad)."""
    msg = message(ODOMETRY_TYPE)(header=msgtypes.header_at(stamp_ns, frame_id),
                                 child_frame_id=child_frame_id)
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x), float(y)
    msg.pose.pose.orientation.z = math.sin(yaw / 2)
    msg.pose.pose.orientation.w = math.cos(yaw / 2)
    return msg


def gnss_message(stamp_ns: int, lat_deg: float, lon_deg: float,
                 frame_id: str = "gnss") -> Any:
    """sensor_msgs/NavSatFix of a fix (status FIX, GPS)."""
    msg = message(GNSS_TYPE)(header=msgtypes.header_at(stamp_ns, frame_id),
                             latitude=float(lat_deg), longitude=float(lon_deg))
    msg.status.status, msg.status.service = 0, 1
    return msg


@dataclass(frozen=True)
class RecordingForm:
    """How a camera driver records a stereo camera, for :func:`write_stereo_bag`: its topics
    (None: ``<namespace>/left/image_rect`` and so on; CompressedImage topics end in
    ``/compressed``), how its images are stored (``encoding``: one a camera publishes, made
    from the samples' grey or RGB by recordings.images.encode_raw; None: mono8 or rgb8 as the
    samples are) or compressed (``compression``: jpeg or png), the calibrated camera they come
    from (raw images: its camera_info, with distortion and R; None: the rectified camera of
    the samples) and whether the right camera_info leaves the baseline out (Tx = 0)."""

    topics: StereoTopics | None = None
    encoding: str | None = None
    compression: str | None = None
    camera: StereoCamera | None = None
    no_baseline: bool = False


DRIVE_MOTIONS = ("none", "odom", "gnss")


def write_drive_bag(out: str | Path, forward_m: Sequence[float], samples: Sequence[Any],
                    motion: str = "none", origin_latlon: tuple[float, float] = (48.137, 11.575),
                    start_ns: int = 1_700_000_000_000_000_000, rate_hz: float = 10.0,
                    ground_truth: bool = True, form: RecordingForm | None = None) -> int:
    """A stereo bag of a straight drive of our generator: frame i (StereoSample) taken
    ``forward_m[i]`` m along the road from the first, at ``rate_hz``; with ``motion`` "odom"
    also /odom (the road point below the camera, x forward), with "gnss" /gnss/fix (driving
    north from ``origin_latlon``); the label images as write_stereo_bag's ``ground_truth``, the
    camera's topics and images as ``form`` says (write_stereo_bag)."""
    if motion not in DRIVE_MOTIONS:
        raise ValueError(f"motion must be one of {DRIVE_MOTIONS}")

    def extras(index: int, stamp: int, sample: Any) -> dict[str, Any]:
        if motion == "odom":
            return {"/odom": odometry_message(stamp, forward_m[index], 0.0, 0.0)}
        if motion == "gnss":
            lat, lon = latlon_of(np.array([[0.0, forward_m[index]]]), *origin_latlon)[0]
            return {"/gnss/fix": gnss_message(stamp, lat, lon)}
        return {}

    return write_stereo_bag(out, ((start_ns + round(i * 1e9 / rate_hz), sample)
                                  for i, sample in enumerate(samples)),
                            ground_truth=ground_truth, extras=extras,
                            form=form or RecordingForm())


def write_stereo_bag(out: str | Path, frames: Iterable[tuple[int, Any]],
                     namespace: str = "/stereo",
                     frame_id: str = "stereo_left_optical_frame", storage: str = "mcap",
                     ground_truth: bool = True,
                     extras: Callable[[int, int, Any], dict[str, Any]] | None = None,
                     form: RecordingForm = RecordingForm()) -> int:
    """Write (stamp ns, StereoSample) frames as a stereo bag: ``left/image_rect``,
    ``right/image_rect`` (mono8, or rgb8 for colour samples), both camera_info and, with
    ``ground_truth``, ``ground_truth/pothole_labels`` (mono16) under ``namespace``; or in the
    topics, encoding or compression and calibration of ``form`` (raw images: the samples'
    images must be the camera's raw ones, synthetic.render_raw). ``extras(index, stamp,
    sample)`` gives more messages per frame by topic (``/odom``: nav_msgs/Odometry,
    ``/gnss/fix``: sensor_msgs/NavSatFix). Returns the number of frames written."""
    store = typestore()
    writer = writer_for(out, storage)
    writer.open()
    image_type = COMPRESSED_TYPE if form.compression else IMAGE_TYPE
    names = form.topics or StereoTopics(
        *(f"{namespace}/{side}/image_rect" + ("/compressed" if form.compression else "")
          for side in ("left", "right")),
        f"{namespace}/left/camera_info", f"{namespace}/right/camera_info")
    topics = {"left": (names.left, image_type), "right": (names.right, image_type),
              "left_info": (names.left_info, INFO_TYPE),
              "right_info": (names.right_info, INFO_TYPE)}
    if ground_truth:
        topics["truth"] = (f"{names.namespace or namespace}/ground_truth/pothole_labels",
                           IMAGE_TYPE)
    connections = {key: writer.add_connection(topic, msgtype, typestore=store)
                   for key, (topic, msgtype) in topics.items()}
    extra_types = {"/odom": ODOMETRY_TYPE, "/gnss/fix": GNSS_TYPE}
    count = 0

    stored: dict[int, tuple[np.ndarray, Any]] = {}

    def image(pixels: np.ndarray, header: Any) -> Any:
        """The image message of ``pixels``, encoded once per array (a drive may cycle a few
        samples) and stamped ``header``."""
        if id(pixels) not in stored:
            if form.compression:
                made = conversions.compressed_image(pixels, form.compression, header)
            else:
                encoding = form.encoding or ("mono8" if pixels.ndim == 2 else "rgb8")
                made = conversions.array_to_image(encode_raw(pixels, encoding), encoding, header)
            stored[id(pixels)] = (pixels, made)
        made = copy.copy(stored[id(pixels)][1])
        made.header = header
        return made

    try:
        for index, (stamp_ns, sample) in enumerate(frames):
            for topic, extra in (extras(index, stamp_ns, sample) if extras else {}).items():
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, extra_types[topic],
                                                               typestore=store)
                writer.write(connections[topic], int(stamp_ns),
                             serialize(extra, extra_types[topic]))
            header = msgtypes.header_at(stamp_ns, frame_id)
            height, width = sample.left.shape[:2]
            if form.camera is not None:
                infos = [conversions.camera_info_of(model, header)
                         for model in (form.camera.left, form.camera.right)]
            else:
                infos = [conversions.camera_info_message(sample.calibration, width, height,
                                                         header, right=right)
                         for right in (False, True)]
            if form.no_baseline:
                infos[1].p[3] = 0.0
            messages = {"left": image(sample.left, header),
                        "right": image(sample.right, header),
                        "left_info": infos[0], "right_info": infos[1]}
            if ground_truth:
                messages["truth"] = conversions.array_to_image(
                    sample.labels.astype(np.uint16), "mono16", header)
            for key in ("left_info", "right_info", "left", "right", "truth"):
                if key in messages:
                    writer.write(connections[key], int(stamp_ns),
                                 serialize(messages[key], topics[key][1]))
            count += 1
    finally:
        writer.close()
    return count
