"""Bags in the ROS graph and the node's outputs in bags: play a recording into the live graph,
record topics from it, and ``process``: a recording run through the pipeline into a bag of
every output topic the node publishes. rclpy is loaded by play and record only, so that
``process`` runs where ROS is not installed."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable, Sequence

from rosbags.interfaces import Connection

from ..backend import get_backend
from ..errors import InputError, PotholeError
from ..imageio import write_rgb
from ..params import Config
from ..recordings.bags import cdr_bytes, open_bag
from ..recordings.messages import message, serialize, typestore
from ..recordings.topics import find_stereo_topics
from ..recordings.bagwriter import BagWriter
from ..recordings.writing import copy_messages
from ..replay import ProcessSummary, frame_results
from .outputs import OFFLINE_OUTPUTS, OUTPUT_TYPES, failure_messages, output_messages
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
           should_stop: Callable[[], bool] = lambda: False,
           compression: str = "zstd") -> dict[str, int]:
    """Record live ``topics`` (raw CDR, receive time) into a new bag until Ctrl-C, ``duration``
    s or ``should_stop()``; an mcap bag's chunks compressed by ``compression`` (BagWriter).
    Topic types are discovered from the graph. Returns counts."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    # the output path checked before the graph is joined
    writer = BagWriter(out, storage, compression)
    store = typestore()
    own_context = not rclpy.ok()
    if own_context:
        large_image_transport()
        rclpy.init(args=[])
    node = rclpy.create_node("pothole_detector_recorder")
    counts = {topic: 0 for topic in topics}
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE
                     if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
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


def process(bag: str | Path, out: str | Path, config: Config, storage: str = "mcap",
            keep_inputs: bool = True, left: str | None = None, right: str | None = None,
            left_info: str | None = None, right_info: str | None = None,
            progress: Callable[[int, int], None] | None = None,
            pictures: str | Path | None = None,
            compression: str = "zstd_fast") -> ProcessSummary:
    """Run the pipeline on every synchronized stereo set of ``bag`` and write a new bag at
    ``out`` with the inputs (``keep_inputs``) and every output topic of the node, stamped with
    the input stamps, under the input's namespace (raw inputs: the outputs are in the
    rectified frame); an mcap bag's chunks compressed by ``compression`` (BagWriter: zstd,
    zstd_fast, lz4 or none). ``pictures``: also write overlay PNGs. The topics used are
    logged in one line. A bag damaged part way keeps the frames before the damage; the
    InputError that says where is raised once they are written."""
    reader = open_bag(bag)
    summary = ProcessSummary()
    try:
        bag_topics = {c.topic: c.msgtype for c in reader.connections}
        stereo = find_stereo_topics(bag_topics, left, right, left_info, right_info)
        _log.info(stereo.describe())
        namespace = stereo.namespace
        writer = BagWriter(out, storage, compression)
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

