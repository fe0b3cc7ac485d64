"""Bags on rosbags: our typestore, play into the live graph, record, offline processing."""

from __future__ import annotations

import bisect
import itertools
import math
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from .errors import InputError, PotholeError
from .msgtypes import deserialize, message, serialize, typestore
from .outputs import OFFLINE_OUTPUTS, OUTPUT_TYPES
from .transport import large_image_transport
from .params import Config

IMAGE_TYPE = "sensor_msgs/msg/Image"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"


def open_bag(path: str | Path) -> AnyReader:
    """An opened AnyReader on a ROS 2 bag directory (mcap or sqlite3) or a ROS 1 .bag."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"bag {path} does not exist")
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises several unrelated error types
        raise InputError(f"{path} is not a bag that can be read ({exc}): give a ROS 2 bag "
                         "directory (mcap or sqlite3) or a ROS 1 .bag file") from None
    return reader


_CONVERTERS: dict[tuple[str, str], Callable[[bytes], Any]] = {}


def cdr_bytes(reader: AnyReader, connection: Connection, rawdata: bytes) -> bytes:
    """The message as ROS 2 (Jazzy) CDR bytes, whatever the bag's own serialization; ROS 1
    messages are migrated field by field (Header.seq dropped, CameraInfo.D -> d ...)."""
    if reader.is2:
        return bytes(rawdata)
    key = (connection.msgtype, connection.msgdef.data)
    if key not in _CONVERTERS:
        from rosbags.convert.converter import generate_message_converter
        _CONVERTERS[key] = generate_message_converter(
            reader.typestore, typestore(), connection.msgtype, connection.msgtype, {},
            src_is2=False, dst_is2=True)
    return bytes(_CONVERTERS[key](rawdata))


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

@dataclass
class StereoTopics:
    """The four input topics of one stereo camera."""

    left: str
    right: str
    left_info: str
    right_info: str

    @property
    def namespace(self) -> str:
        """The common parent of the left and right image topics ('' for the root)."""
        left, right = self.left.strip("/").split("/"), self.right.strip("/").split("/")
        common = []
        for a, b in zip(left, right):
            if a != b:
                break
            common.append(a)
        return "/" + "/".join(common) if common else ""


def find_stereo_topics(topics: dict[str, str], left: str | None = None,
                       right: str | None = None, left_info: str | None = None,
                       right_info: str | None = None) -> StereoTopics:
    """The stereo topics of a bag (``topics``: name -> type): given ones are checked, missing
    ones are found when the bag holds one image and one camera_info topic per side."""

    def pick(given: str | None, side: str, msgtype: str, what: str) -> str:
        if given is not None:
            if topics.get(given) != msgtype:
                raise InputError(f"the bag has no {msgtype} topic {given}; it has "
                                 f"{', '.join(sorted(topics))}")
            return given
        found = [t for t, k in topics.items() if k == msgtype and f"/{side}" in t
                 and not t.rstrip("/").endswith(tuple(OUTPUT_TYPES))]
        if len(found) != 1:
            option = f"--{side}-topic" if what == "image" else f"--{side}-info-topic"
            raise InputError(f"cannot tell the {side} {what} topic among {found or 'none'}; "
                             f"name it with {option}")
        return found[0]

    return StereoTopics(pick(left, "left", IMAGE_TYPE, "image"),
                        pick(right, "right", IMAGE_TYPE, "image"),
                        pick(left_info, "left", INFO_TYPE, "camera_info"),
                        pick(right_info, "right", INFO_TYPE, "camera_info"))


@dataclass(frozen=True)
class BagFrame:
    """One synchronized stereo set of a bag, converted: images as arrays (HxW or HxWxC); None
    where the set could not be converted."""

    stamp: int
    header: Any
    left: np.ndarray | None
    right: np.ndarray | None
    calibration: Any
    logged_ns: int = 0


@dataclass(frozen=True)
class LogSpan:
    """A part of a bag by log time (ns): the sets whose left image was logged in
    [``start_ns``, ``stop_ns``), read with ``lead_ns`` more on both sides (earlier sets, for
    visual odometry, and partners logged after the span)."""

    start_ns: int
    stop_ns: int
    lead_ns: int


@dataclass
class ProcessSummary:
    """What :func:`process` did."""

    frames: int = 0
    failed: int = 0
    potholes: int = 0
    unpaired: int = 0
    milliseconds: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def text(self) -> str:
        per_frame = float(np.mean(self.milliseconds)) if self.milliseconds else 0.0
        return (f"{self.frames} frames, {self.potholes} potholes found, {per_frame:.0f} ms per "
                f"frame, {self.failed} failed, {self.unpaired} unpaired images")


INFO_WAIT_NS = 1_000_000_000


def stereo_sets(reader: AnyReader, topics: StereoTopics, config: Config,
                summary: ProcessSummary, span: LogSpan | None = None,
                others: Sequence[str] = (), collected: list | None = None
                ) -> Iterator[tuple[int, int, Any, Any, Any, Any]]:
    """Synchronized (stamp, left image's log time, left, right, left_info, right_info)
    messages of a bag, or of the sets whose left image was logged before ``span``'s stop
    (reading from its lead before its start), in one pass. Each pair takes the camera_info of
    its own stamp where the bag holds it (logged before the images or up to INFO_WAIT_NS
    after), else the newest one before it (for a span, also one logged before it: a latched
    camera_info); the infos are None for a pair before any. Images that found no partner
    are counted in ``summary``. The messages of the ``others`` topics logged in the span (not
    its lead) go into ``collected`` as (topic, log time ns, message), in the same pass."""
    from . import conversions
    from .sync import StereoSynchronizer

    roles = {topics.left: "left", topics.right: "right", topics.left_info: "left_info",
             topics.right_info: "right_info"}
    roles.update({topic: "other" for topic in others if topic not in roles})
    connections = [c for c in reader.connections if c.topic in roles]
    window = {} if span is None else {"start": span.start_ns - span.lead_ns,
                                      "stop": span.stop_ns + span.lead_ns}
    infos: dict[str, dict[int, Any]] = {"left_info": {}, "right_info": {}}
    stamps: dict[str, list[int]] = {"left_info": [], "right_info": []}
    latched: dict[str, Any] = {}

    def logged_before_window(role: str) -> Any:
        """The newest info of ``role`` logged before the span's window: looked for in the
        INFO_WAIT_NS before it, then anywhere before it."""
        if role not in latched:
            newest = None
            ends = (window["start"] - INFO_WAIT_NS, None) if span is not None else ()
            for start in ends:
                for connection, _, rawdata in reader.messages(
                        connections=[c for c in connections if roles[c.topic] == role],
                        start=start, stop=window["start"]):
                    newest = (connection, rawdata)
                if newest is not None:
                    break
            latched[role] = None if newest is None else deserialize(
                cdr_bytes(reader, *newest), INFO_TYPE)
        return latched[role]

    def info_at(role: str, stamp: int) -> Any:
        if stamp in infos[role]:
            return infos[role][stamp]
        before = bisect.bisect_right(stamps[role], stamp)
        if before:
            return infos[role][stamps[role][before - 1]]
        return logged_before_window(role)

    waiting: deque[tuple[int, int, Any, Any]] = deque()

    def release(now_ns: int | None) -> Iterator[tuple[int, int, Any, Any, Any, Any]]:
        """The waiting pairs whose infos have come (both streams past their stamp), waited
        INFO_WAIT_NS of log time, or all (``now_ns`` None: the end of the bag)."""
        while waiting:
            pair_stamp, logged, left, right = waiting[0]
            if now_ns is not None and now_ns - logged < INFO_WAIT_NS and not all(
                    stamps[role] and stamps[role][-1] >= pair_stamp for role in stamps):
                return
            waiting.popleft()
            left_info, right_info = (info_at(role, pair_stamp)
                                     for role in ("left_info", "right_info"))
            if left_info is None or right_info is None:
                left_info = right_info = None
            yield pair_stamp, logged, left, right, left_info, right_info
            for role, kept in stamps.items():
                while len(kept) > 1 and kept[1] <= pair_stamp:
                    del infos[role][kept.pop(0)]

    synchronizer: StereoSynchronizer[Any] = StereoSynchronizer.from_config(config)
    for connection, logged, rawdata in reader.messages(connections=connections, **window):
        role = roles[connection.topic]
        if role == "other":
            if collected is not None and (span is None
                                          or span.start_ns <= logged < span.stop_ns):
                collected.append((connection.topic, logged, deserialize(
                    cdr_bytes(reader, connection, rawdata), connection.msgtype)))
            continue
        if role in infos:
            info = deserialize(cdr_bytes(reader, connection, rawdata), INFO_TYPE)
            stamp = conversions.stamp_ns(info.header)
            if stamp not in infos[role]:
                bisect.insort(stamps[role], stamp)
            infos[role][stamp] = info
        else:
            msg = deserialize(cdr_bytes(reader, connection, rawdata), IMAGE_TYPE)
            outcome = synchronizer.add(role, conversions.stamp_ns(msg.header), (logged, msg))
            summary.unpaired += outcome.dropped
            waiting.extend((pair_stamp, left_logged, left, right)
                           for pair_stamp, (left_logged, left), (_, right) in outcome.pairs
                           if span is None or left_logged < span.stop_ns)
        yield from release(logged)
    yield from release(None)
    summary.unpaired += synchronizer.reset()


# Sets per slice of log time that a read thread takes at a time (read_sets_ahead).
READ_BLOCK_FRAMES = 24


def message_count(reader: AnyReader, topic: str) -> int:
    """How many messages the bag holds on ``topic`` (0 where it has no such topic)."""
    return sum(c.msgcount for c in reader.connections if c.topic == topic)


def mean_period_ns(reader: AnyReader, topic: str) -> float:
    """The mean time (ns) between the bag's messages on ``topic``, over its whole log time."""
    return (reader.end_time - reader.start_time) / max(message_count(reader, topic) - 1, 1)


def read_blocks(reader: AnyReader, topics: StereoTopics, config: Config,
                span: LogSpan | None) -> tuple[list[LogSpan], float]:
    """``span``'s log time (or the whole bag's) cut into blocks of about READ_BLOCK_FRAMES
    sets at the bag's mean rate, each with a lead of two frames and the sync tolerance (for
    partners logged across its edges; the first block at least the span's own lead), and the
    mean period (ns) of the left images."""
    outer = span or LogSpan(reader.start_time, reader.end_time + 1, 0)
    period_ns = mean_period_ns(reader, topics.left)
    block_ns = max(1, math.ceil(period_ns * READ_BLOCK_FRAMES))
    lead_ns = math.ceil(2 * period_ns + config.approximate_sync_tolerance_seconds * 1e9)
    starts = list(range(outer.start_ns, outer.stop_ns, block_ns)) or [outer.start_ns]
    return [LogSpan(first, min(first + block_ns, outer.stop_ns),
                    max(outer.lead_ns, lead_ns) if index == 0 else lead_ns)
            for index, first in enumerate(starts)], max(period_ns, 1.0)


def block_sets(reader: AnyReader, topics: StereoTopics, config: Config, block: LogSpan,
               first: bool, others: Sequence[str] = (), collected: list | None = None
               ) -> Iterator[tuple[int, int, Any, Any, Any, Any]]:
    """The sets of :func:`stereo_sets` over a block of :func:`read_blocks` whose left image
    was logged in it (the ``first`` block's also those of its lead)."""
    return (item for item in stereo_sets(reader, topics, config, ProcessSummary(), block,
                                         others, collected)
            if first or item[1] >= block.start_ns)


def convert_set(topics: StereoTopics, left_msg: Any, right_msg: Any, left_info: Any,
                right_info: Any) -> tuple[np.ndarray, np.ndarray, Any]:
    """The left and right pixels (HxW or HxWx3) and the calibration of a synchronized set;
    raises InputError where it cannot be converted."""
    from . import conversions

    if left_info is None:
        raise InputError(f"no camera_info on {topics.left_info} and {topics.right_info} yet")
    left = conversions.image_to_array(left_msg)
    right = conversions.image_to_array(right_msg)
    height, width = left.shape[:2]
    return left, right, conversions.calibration_from_camera_info(left_info, right_info, width,
                                                                 height)


def read_sets_ahead(reader: AnyReader, topics: StereoTopics, config: Config,
                    span: LogSpan | None, threads: int, others: Sequence[str] = (),
                    collected: list | None = None
                    ) -> Iterator[tuple[int, int, Any, Any, Any, Any]]:
    """The sets of :func:`stereo_sets` over ``span`` (or the whole bag) in order, and its
    ``others`` messages into ``collected``, read by ``threads`` threads ahead of the caller,
    each with its own reader on the bag: the span's log time is cut into blocks of about
    READ_BLOCK_FRAMES sets (at the bag's mean rate), a thread reads a block with a lead of two
    frames and the sync tolerance on both sides (for partners logged across its edges) and
    keeps the sets whose left image was logged in it (the first block also its span's lead).
    The bag's decompression, which releases the GIL, runs beside the pipeline; at most
    ``threads`` + 1 blocks are held. Unpaired images are not counted."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    blocks, _ = read_blocks(reader, topics, config, span)
    path = list(reader.paths)[0]
    local = threading.local()
    opened: list[AnyReader] = []

    def read(block: LogSpan, first: bool) -> tuple[list, list]:
        if not hasattr(local, "reader"):
            local.reader = open_bag(path)
            opened.append(local.reader)
        extras: list = []
        return list(block_sets(local.reader, topics, config, block, first, others,
                               extras)), extras

    def take(future: Any) -> list:
        sets, extras = future.result()
        if collected is not None:
            collected.extend(extras)
        return sets

    try:
        with ThreadPoolExecutor(threads, thread_name_prefix="bag-read") as pool:
            pending: deque = deque()
            for index, block in enumerate(blocks):
                pending.append(pool.submit(read, block, index == 0))
                if len(pending) > threads:
                    yield from take(pending.popleft())
            while pending:
                yield from take(pending.popleft())
    finally:
        for own in opened:
            own.close()


def frame_results(reader: AnyReader, stereo: StereoTopics, config: Config, backend: Any,
                  summary: ProcessSummary,
                  progress: Callable[[int, int], None] | None = None,
                  span: LogSpan | None = None, read_threads: int = 1,
                  others: Sequence[str] = (), collected: list | None = None,
                  read_processes: int = 0) -> Iterator[tuple[BagFrame, Any]]:
    """(frame, PipelineResult or the PotholeError that stopped it) for the synchronized sets
    of a bag, or of a :class:`LogSpan` of it (with the sets of its lead before it: their
    ``logged_ns`` is before the span's start), in order. One pipeline per run of frames with
    the same calibration; within a run the host prepares the next pair while the device works
    (Pipeline.run_stream). ``progress(done, total)`` is called per set (of the whole bag's
    left images, or of a span's share of them). ``read_threads`` > 1: the bag is read ahead
    in that many threads (:func:`read_sets_ahead`; ``summary`` then counts no unpaired
    images) where its camera_info topics hold a message per image or so (a block then finds
    its infos in itself; a bag with latched infos is read in this thread); ``read_processes``
    > 0: read and decoded by that many worker processes instead (:mod:`.decoding`, on the
    same condition). The messages of the ``others`` topics logged in the span go into
    ``collected`` in the same pass (complete once the frames are)."""
    from .pipeline import Pipeline

    images = total = message_count(reader, stereo.left)
    if span is not None:
        bag_ns = max(reader.end_time - reader.start_time + 1, 1)
        total = round(total * min(span.stop_ns - span.start_ns, bag_ns) / bag_ns)

    def prepared() -> Iterator[BagFrame | tuple[BagFrame, PotholeError]]:
        streamed_infos = all(2 * message_count(reader, topic) >= images
                             for topic in (stereo.left_info, stereo.right_info))
        if read_processes > 0 and streamed_infos:
            from .decoding import decoded_frames
            for index, item in enumerate(decoded_frames(reader, stereo, config, span,
                                                        read_processes, others, collected)):
                if progress is not None:
                    progress(min(index, total), total)
                yield item
            return
        sets = read_sets_ahead(reader, stereo, config, span, read_threads, others,
                               collected) if read_threads > 1 and streamed_infos \
            else stereo_sets(reader, stereo, config, summary, span, others, collected)
        for index, (stamp, logged, left_msg, right_msg, left_cal, right_cal) in enumerate(sets):
            if progress is not None:
                progress(min(index, total), total)
            try:
                left_px, right_px, calibration = convert_set(stereo, left_msg, right_msg,
                                                             left_cal, right_cal)
            except PotholeError as exc:
                yield BagFrame(stamp, left_msg.header, None, None, None, logged), exc
                continue
            yield BagFrame(stamp, left_msg.header, left_px, right_px, calibration, logged)

    def key(item: BagFrame | tuple[BagFrame, PotholeError]) -> Any:
        return None if isinstance(item, tuple) else item.calibration

    for calibration, run in itertools.groupby(prepared(), key):
        if calibration is None:
            yield from run
            continue
        frames, streamed = itertools.tee(run)
        outcomes = Pipeline(config, calibration, backend).run_stream(
            (frame.left, frame.right) for frame in streamed)
        for frame in frames:
            yield frame, next(outcomes)
    if progress is not None:
        progress(total, total)


def process(bag: str | Path, out: str | Path, config: Config, storage: str = "mcap",
            keep_inputs: bool = True, left: str | None = None, right: str | None = None,
            left_info: str | None = None, right_info: str | None = None,
            progress: Callable[[int, int], None] | None = None,
            pictures: str | Path | None = None) -> ProcessSummary:
    """Run the pipeline on every synchronized stereo set of ``bag`` and write a new bag at
    ``out`` with the inputs (``keep_inputs``) and every output topic of the node, stamped with
    the input stamps, under the input's namespace. ``pictures``: also write overlay PNGs."""
    from .backend import get_backend
    from .imageio import write_rgb
    from .outputs import failure_messages, output_messages

    reader = open_bag(bag)
    summary = ProcessSummary()
    try:
        bag_topics = {c.topic: c.msgtype for c in reader.connections}
        stereo = find_stereo_topics(bag_topics, left, right, left_info, right_info)
        namespace = stereo.namespace
        writer = writer_for(out, storage)
        writer.open()
        store = typestore()
        try:
            output = {name: writer.add_connection(f"{namespace}/{name}", msgtype,
                                                  typestore=store)
                      for name, msgtype in OUTPUT_TYPES.items() if name in OFFLINE_OUTPUTS}
            inputs = {}
            if keep_inputs:
                for topic in (stereo.left, stereo.right, stereo.left_info, stereo.right_info):
                    inputs[topic] = writer.add_connection(topic, bag_topics[topic],
                                                          typestore=store)
                for connection, timestamp, rawdata in reader.messages(
                        connections=[c for c in reader.connections if c.topic in inputs]):
                    writer.write(inputs[connection.topic], timestamp,
                                 cdr_bytes(reader, connection, rawdata))
            backend = get_backend(config.backend)
            if pictures is not None:
                Path(pictures).mkdir(parents=True, exist_ok=True)
            started = time.perf_counter()
            for frame, outcome in frame_results(reader, stereo, config, backend, summary,
                                                progress):
                if isinstance(outcome, PotholeError):
                    summary.failed += 1
                    summary.errors.append(f"stamp {frame.stamp}: {outcome}")
                    for name, made in failure_messages(frame.header, str(outcome)).items():
                        writer.write(output[name], frame.stamp,
                                     serialize(made, OUTPUT_TYPES[name]))
                    started = time.perf_counter()
                    continue
                result = outcome
                made = output_messages(result, frame.left, frame.calibration, frame.header,
                                       OFFLINE_OUTPUTS)
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


def topics_of(bag: str | Path) -> dict[str, str]:
    """Topic name -> type of a bag."""
    reader = open_bag(bag)
    try:
        return {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()


def read_messages(bag: str | Path, topics: Iterable[str] | None = None,
                  span: LogSpan | None = None) -> Iterator[tuple[str, int, Any]]:
    """(topic, bag time ns, message) of a bag, or of those logged in a span (its lead
    left out), in time order."""

    reader = open_bag(bag)
    try:
        wanted = None if topics is None else set(topics)
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        window = {} if span is None else {"start": span.start_ns, "stop": span.stop_ns}
        for connection, timestamp, rawdata in reader.messages(connections=connections,
                                                              **window):
            yield connection.topic, timestamp, deserialize(
                cdr_bytes(reader, connection, rawdata), connection.msgtype)
    finally:
        reader.close()



ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
GNSS_TYPE = "sensor_msgs/msg/NavSatFix"


def odometry_message(stamp_ns: int, x: float, y: float, yaw: float,
                     frame_id: str = "odom", child_frame_id: str = "base_link") -> Any:
    """nav_msgs/Odometry of a planar pose (m, rad)."""
    from . import conversions

    msg = message(ODOMETRY_TYPE)(header=conversions.header_at(stamp_ns, frame_id),
                                 child_frame_id=child_frame_id)
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x), float(y)
    msg.pose.pose.orientation.z = math.sin(yaw / 2)
    msg.pose.pose.orientation.w = math.cos(yaw / 2)
    return msg


def gnss_message(stamp_ns: int, lat_deg: float, lon_deg: float,
                 frame_id: str = "gnss") -> Any:
    """sensor_msgs/NavSatFix of a fix (status FIX, GPS)."""
    from . import conversions

    msg = message(GNSS_TYPE)(header=conversions.header_at(stamp_ns, frame_id),
                             latitude=float(lat_deg), longitude=float(lon_deg))
    msg.status.status, msg.status.service = 0, 1
    return msg


DRIVE_MOTIONS = ("none", "odom", "gnss")


def write_drive_bag(out: str | Path, forward_m: Sequence[float], samples: Sequence[Any],
                    motion: str = "none", origin_latlon: tuple[float, float] = (48.137, 11.575),
                    start_ns: int = 1_700_000_000_000_000_000, rate_hz: float = 10.0,
                    ground_truth: bool = True) -> int:
    """A stereo bag of a straight drive of our generator: frame i (StereoSample) taken
    ``forward_m[i]`` m along the road from the first, at ``rate_hz``; with ``motion`` "odom"
    also /odom (the road point below the camera, x forward), with "gnss" /gnss/fix (driving
    north from ``origin_latlon``); the label images as write_stereo_bag's ``ground_truth``."""
    from .motion import latlon_of

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
                            ground_truth=ground_truth, extras=extras)


def write_stereo_bag(out: str | Path, frames: Iterable[tuple[int, Any]],
                     namespace: str = "/stereo",
                     frame_id: str = "stereo_left_optical_frame", storage: str = "mcap",
                     ground_truth: bool = True,
                     extras: Callable[[int, int, Any], dict[str, Any]] | None = None) -> int:
    """Write (stamp ns, StereoSample) frames as a stereo bag: ``left/image_rect``,
    ``right/image_rect`` (mono8, or rgb8 for colour samples), both camera_info and, with
    ``ground_truth``, ``ground_truth/pothole_labels`` (mono16) under ``namespace``.
    ``extras(index, stamp, sample)`` gives more messages per frame by topic (``/odom``:
    nav_msgs/Odometry, ``/gnss/fix``: sensor_msgs/NavSatFix). Returns the number of frames
    written."""
    from . import conversions

    store = typestore()
    writer = writer_for(out, storage)
    writer.open()
    topics = {"left": (f"{namespace}/left/image_rect", IMAGE_TYPE),
              "right": (f"{namespace}/right/image_rect", IMAGE_TYPE),
              "left_info": (f"{namespace}/left/camera_info", INFO_TYPE),
              "right_info": (f"{namespace}/right/camera_info", INFO_TYPE)}
    if ground_truth:
        topics["truth"] = (f"{namespace}/ground_truth/pothole_labels", IMAGE_TYPE)
    connections = {key: writer.add_connection(topic, msgtype, typestore=store)
                   for key, (topic, msgtype) in topics.items()}
    extra_types = {"/odom": ODOMETRY_TYPE, "/gnss/fix": GNSS_TYPE}
    count = 0
    try:
        for index, (stamp_ns, sample) in enumerate(frames):
            for topic, extra in (extras(index, stamp_ns, sample) if extras else {}).items():
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, extra_types[topic],
                                                               typestore=store)
                writer.write(connections[topic], int(stamp_ns),
                             serialize(extra, extra_types[topic]))
            header = conversions.header_at(stamp_ns, frame_id)
            height, width = sample.left.shape[:2]
            encoding = "mono8" if sample.left.ndim == 2 else "rgb8"
            messages = {
                "left": conversions.array_to_image(sample.left, encoding, header),
                "right": conversions.array_to_image(sample.right, encoding, header),
                "left_info": conversions.camera_info_message(sample.calibration, width, height,
                                                             header),
                "right_info": conversions.camera_info_message(sample.calibration, width,
                                                              height, header, right=True),
            }
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
