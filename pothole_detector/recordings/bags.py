"""Reading bags: ROS 2 bags (mcap, sqlite3) and ROS 1 .bag files through rosbags, their
synchronized stereo sets with camera_info, converted (decoded, with the stereo camera they
were taken with), in one pass or ahead of the caller in threads; the bag's other messages."""

from __future__ import annotations

import atexit
import bisect
import logging
import math
import threading
from collections import OrderedDict, deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np
from rosbags.convert.converter import generate_message_converter
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection

from ..calibration import StereoCalibration, StereoCamera
from ..errors import InputError
from .messages import deserialize, stamp_ns, typestore
from ..params import Config
from ..stages.rectify import Rectification
from .sync import StereoSynchronizer
from .camera import rectification, rectifies, stereo_camera
from .images import decode
from .repair import repaired_copy
from .topics import INFO_TYPE, StereoTopics

_log = logging.getLogger(__name__)


def open_bag(path: str | Path) -> AnyReader:
    """An opened AnyReader on a ROS 2 bag directory (mcap or sqlite3) or a ROS 1 .bag. An mcap
    bag cut off before its footer (an interrupted recording) is read from its repaired copy
    (:mod:`.repair`), and a warning says so once per process."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"bag {path} does not exist")
    try:
        return _opened(path)
    except Exception as exc:  # rosbags raises several unrelated error types
        if "end magic" not in str(exc) and "footer" not in str(exc).lower():
            raise InputError(f"{path} is not a bag that can be read ({exc}): give a ROS 2 bag "
                             "directory (mcap or sqlite3) or a ROS 1 .bag file") from None
    repaired, count, stop = repaired_copy(path)
    if path not in _REPAIRED:
        _REPAIRED.add(path)
        _log.warning(f"{path} is cut off (its recording was interrupted): reading the {count} "
                     f"messages before the cut ({stop}) from a repaired copy, {repaired}")
    try:
        return _opened(repaired)
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{path} is cut off and its repaired copy cannot be read ({exc})"
                         ) from None


_REPAIRED: set[Path] = set()


def _opened(path: Path) -> AnyReader:
    reader = AnyReader([path], default_typestore=typestore())
    reader.open()
    return reader


# Idle open readers that this process keeps per bag for its next reads, and the bags it keeps
# them for (the most recently used).
POOLED_READERS_PER_BAG = 8
POOLED_BAGS = 2


class ReaderPool:
    """Open readers of bags kept for reuse: opening a bag reads its whole index, which for an
    mcap recording is a record per chunk of it (about a tenth of a second per 4 GB), so a
    survey's chunks, each read by its own readers, would read a long recording's index again
    and again. A reader taken is the caller's alone until given back. Readers are kept per bag
    as it is on disk (its files' sizes, modification times and inodes): a bag written anew at
    the same path is opened anew."""

    def __init__(self, per_bag: int = POOLED_READERS_PER_BAG, bags: int = POOLED_BAGS) -> None:
        self.per_bag, self.bags = per_bag, bags
        self._lock = threading.Lock()
        self._idle: OrderedDict[Path, tuple[tuple, list[AnyReader]]] = OrderedDict()

    def take(self, path: str | Path) -> tuple[AnyReader, tuple]:
        """An open reader of the bag at ``path`` (an idle one, else :func:`open_bag`) and the
        bag's identity to give it back with."""
        path = Path(path).absolute()
        identity = _identity(path)
        stale: list[AnyReader] = []
        reader = None
        with self._lock:
            kept = self._idle.get(path)
            if kept is not None and kept[0] != identity:
                stale = self._idle.pop(path)[1]
            elif kept is not None and kept[1]:
                reader = kept[1].pop()
                self._idle.move_to_end(path)
        _close_all(stale)
        return (reader if reader is not None else open_bag(path)), identity

    def give(self, path: str | Path, reader: AnyReader, identity: tuple) -> None:
        """Keep ``reader``, taken with ``identity``, idle for the next :meth:`take` of the bag
        (or close it where the pool holds enough of that bag's or the bag has changed since)."""
        path = Path(path).absolute()
        closing: list[AnyReader] = []
        with self._lock:
            kept = self._idle.get(path)
            if kept is None or kept[0] != identity:
                if kept is not None:
                    closing += kept[1]
                kept = self._idle[path] = (identity, [])
            if len(kept[1]) < self.per_bag and identity == _identity(path):
                kept[1].append(reader)
            else:
                closing.append(reader)
            self._idle.move_to_end(path)
            while len(self._idle) > self.bags:
                closing += self._idle.popitem(last=False)[1][1]
        _close_all(closing)

    def idle(self, path: str | Path) -> int:
        """How many idle readers of the bag at ``path`` the pool keeps."""
        kept = self._idle.get(Path(path).absolute())
        return len(kept[1]) if kept is not None else 0

    def clear(self) -> None:
        """Close every idle reader."""
        with self._lock:
            closing = [reader for _, readers in self._idle.values() for reader in readers]
            self._idle.clear()
        _close_all(closing)


def _identity(path: Path) -> tuple:
    """The bag at ``path`` as it is on disk: (name, size, modification time ns, inode) of the
    file or of each file of the directory; () where there is none."""
    try:
        files = sorted(path.iterdir()) if path.is_dir() else [path]
        stats = [(file.name, file.stat()) for file in files]
    except OSError:
        return ()
    return tuple((name, stat.st_size, stat.st_mtime_ns, stat.st_ino) for name, stat in stats)


def _close_all(readers: Iterable[AnyReader]) -> None:
    for reader in readers:
        reader.close()


READERS = ReaderPool()
atexit.register(READERS.clear)


@contextmanager
def reading(path: str | Path) -> Iterator[AnyReader]:
    """An open reader of the bag at ``path`` from this process's :class:`ReaderPool`, given
    back to it after the block (closed instead where the block raised or was left by a
    generator's close)."""
    reader, identity = READERS.take(path)
    try:
        yield reader
    except BaseException:
        reader.close()
        raise
    READERS.give(path, reader, identity)


_CONVERTERS: dict[tuple[str, str], Callable[[bytes], Any]] = {}


def cdr_bytes(reader: AnyReader, connection: Connection, rawdata: bytes) -> bytes:
    """The message as ROS 2 (Jazzy) CDR bytes, whatever the bag's own serialization; ROS 1
    messages are migrated field by field (Header.seq dropped, CameraInfo.D -> d ...)."""
    if reader.is2:
        return bytes(rawdata)
    key = (connection.msgtype, connection.msgdef.data)
    if key not in _CONVERTERS:
        _CONVERTERS[key] = generate_message_converter(
            reader.typestore, typestore(), connection.msgtype, connection.msgtype, {},
            src_is2=False, dst_is2=True)
    return bytes(_CONVERTERS[key](rawdata))


@dataclass(frozen=True)
class BagFrame:
    """One synchronized stereo set of a bag, converted: images as arrays (HxW or HxWx3, as
    recorded: raw or rectified) and the stereo camera they were taken with; None where the set
    could not be converted. Once processed (replay.frame_results) it also carries the
    rectified pair's calibration and, for raw images, the rectification."""

    stamp: int
    header: Any
    left: np.ndarray | None
    right: np.ndarray | None
    camera: StereoCamera | None
    logged_ns: int = 0
    calibration: StereoCalibration | None = None
    rectification: Rectification | None = None
    left_colour: np.ndarray | None = None

    def left_view(self) -> np.ndarray:
        """The left image (its colour where it was kept, else as the matcher took it) in the
        rectified frame that the results are in (rectified here for display where it came
        raw)."""
        image = self.left if self.left_colour is None else self.left_colour
        assert image is not None
        if self.rectification is None:
            return image
        return self.rectification.left_view(image)


@dataclass(frozen=True)
class LogSpan:
    """A part of a bag by log time (ns): the sets whose left image was logged in
    [``start_ns``, ``stop_ns``), read with ``lead_ns`` more on both sides (earlier sets, for
    visual odometry, and partners logged after the span)."""

    start_ns: int
    stop_ns: int
    lead_ns: int


@dataclass
class SetCounts:
    """What reading the sets of a bag counted: images that found no partner, messages that
    could not be read (skipped) and the last such problem."""

    unpaired: int = 0
    corrupt: int = 0
    last_problem: str = ""

    def add(self, other: "SetCounts") -> None:
        self.unpaired += other.unpaired
        self.corrupt += other.corrupt
        self.last_problem = other.last_problem or self.last_problem


INFO_WAIT_NS = 1_000_000_000


def stereo_sets(reader: AnyReader, topics: StereoTopics, config: Config,
                counts: SetCounts, span: LogSpan | None = None,
                others: Sequence[str] = (), collected: list | None = None
                ) -> Iterator[tuple[int, int, Any, Any, Any, Any]]:
    """Synchronized (stamp, left image's log time, left, right, left_info, right_info)
    messages of a bag, or of the sets whose left image was logged before ``span``'s stop
    (reading from its lead before its start), in one pass. Each pair takes the camera_info of
    its own stamp where the bag holds it (logged before the images or up to INFO_WAIT_NS
    after), else the newest one before it (for a span, also one logged before it: a latched
    camera_info); the infos are None for a pair before any. Images that found no partner
    are counted in ``counts``. The messages of the ``others`` topics logged in the span (not
    its lead) go into ``collected`` as (topic, log time ns, message), in the same pass. A bag
    damaged part way (cut off mid-chunk) raises InputError saying where, after the sets read
    before it."""
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
    messages = reader.messages(connections=connections, **window)
    last_logged = window.get("start", reader.start_time)
    while True:
        try:
            connection, logged, rawdata = next(messages)
        except StopIteration:
            break
        except Exception as exc:  # noqa: BLE001 - rosbags raises many kinds on a damaged bag
            yield from release(None)
            raise InputError(f"{list(reader.paths)[0]} is damaged after log time {last_logged} "
                             f"ns ({type(exc).__name__}: {exc}); the sets before it were "
                             "read") from None
        last_logged = logged
        role = roles[connection.topic]
        try:
            msg = deserialize(cdr_bytes(reader, connection, rawdata),
                              topics.image_type if role in ("left", "right")
                              else INFO_TYPE if role in infos else connection.msgtype)
        except Exception as exc:  # noqa: BLE001 - a corrupt message, whatever broke
            counts.corrupt += 1
            counts.last_problem = (f"a corrupt {connection.topic} message at log time "
                                   f"{logged} ns was skipped ({type(exc).__name__})")
            continue
        if role == "other":
            if collected is not None and (span is None
                                          or span.start_ns <= logged < span.stop_ns):
                collected.append((connection.topic, logged, msg))
            continue
        if role in infos:
            stamp = stamp_ns(msg.header)
            if stamp not in infos[role]:
                bisect.insort(stamps[role], stamp)
            infos[role][stamp] = msg
        else:
            outcome = synchronizer.add(role, stamp_ns(msg.header), (logged, msg))
            counts.unpaired += outcome.dropped
            waiting.extend((pair_stamp, left_logged, left, right)
                           for pair_stamp, (left_logged, left), (_, right) in outcome.pairs
                           if span is None or left_logged < span.stop_ns)
        yield from release(logged)
    yield from release(None)
    counts.unpaired += synchronizer.reset()


# Sets per slice of log time that a read thread takes at a time (read_sets_ahead).
READ_BLOCK_FRAMES = 24
# Sets of a span's first slice; each slice after it twice as long, up to READ_BLOCK_FRAMES,
# so that the pipeline's first set comes after a few sets' reading, not a whole slice's
# beside the other readers' slices.
FIRST_READ_BLOCK_FRAMES = 2


def message_count(reader: AnyReader, topic: str) -> int:
    """How many messages the bag holds on ``topic`` (0 where it has no such topic)."""
    return sum(c.msgcount for c in reader.connections if c.topic == topic)


def mean_period_ns(reader: AnyReader, topic: str) -> float:
    """The mean time (ns) between the bag's messages on ``topic``, over its whole log time."""
    return (reader.end_time - reader.start_time) / max(message_count(reader, topic) - 1, 1)


def read_blocks(reader: AnyReader, topics: StereoTopics, config: Config,
                span: LogSpan | None) -> tuple[list[LogSpan], float]:
    """``span``'s log time (or the whole bag's) cut into blocks of sets at the bag's mean rate
    (FIRST_READ_BLOCK_FRAMES, then each block twice as many up to READ_BLOCK_FRAMES), each
    with a lead of two frames and the sync tolerance (for partners logged across its edges;
    the first block at least the span's own lead), and the mean period (ns) of the left
    images."""
    outer = span or LogSpan(reader.start_time, reader.end_time + 1, 0)
    period_ns = mean_period_ns(reader, topics.left)
    lead_ns = math.ceil(2 * period_ns + config.approximate_sync_tolerance_seconds * 1e9)
    blocks: list[LogSpan] = []
    first, frames = outer.start_ns, min(FIRST_READ_BLOCK_FRAMES, READ_BLOCK_FRAMES)
    while first < outer.stop_ns or not blocks:
        stop = min(first + max(1, math.ceil(period_ns * frames)), outer.stop_ns)
        blocks.append(LogSpan(first, stop, max(outer.lead_ns, lead_ns) if not blocks
                              else lead_ns))
        first, frames = stop, min(2 * frames, READ_BLOCK_FRAMES)
    return blocks, max(period_ns, 1.0)


def block_sets(reader: AnyReader, topics: StereoTopics, config: Config, block: LogSpan,
               first: bool, others: Sequence[str] = (), collected: list | None = None,
               counts: SetCounts | None = None
               ) -> Iterator[tuple[int, int, Any, Any, Any, Any]]:
    """The sets of :func:`stereo_sets` over a block of :func:`read_blocks` whose left image
    was logged in it (the ``first`` block's also those of its lead); corrupt messages are
    counted in ``counts`` (those of the block's lead too)."""
    return (item for item in stereo_sets(reader, topics, config, counts or SetCounts(), block,
                                         others, collected)
            if first or item[1] >= block.start_ns)


def convert_set(topics: StereoTopics, left_msg: Any, right_msg: Any, left_info: Any,
                right_info: Any, config: Config, colour: bool = False
                ) -> tuple[np.ndarray, np.ndarray, StereoCamera, np.ndarray | None]:
    """The left and right pixels as the matcher takes them (HxW, as recorded: raw or
    rectified; images.decode's ``grey``), the stereo camera of a synchronized set (with
    ``config``'s baseline_m and focal_px where the camera_info lacks them) and, with
    ``colour``, the left image in colour (HxWx3, for pictures; None without). Raises
    InputError or CalibrationError where it cannot be converted."""
    if left_info is None or right_info is None:
        raise InputError(f"no camera_info on {topics.left_info} and {topics.right_info} yet")
    sizes = [(int(info.width), int(info.height)) for info in (left_info, right_info)]
    left = decode(left_msg, topics.image_type, sizes[0], grey=True)
    right = decode(right_msg, topics.image_type, sizes[1], grey=True)
    if left.shape[:2] != right.shape[:2]:
        raise InputError(f"left image is {left.shape[1]}x{left.shape[0]} but the right one "
                         f"{right.shape[1]}x{right.shape[0]}")
    height, width = left.shape[:2]
    camera = stereo_camera(left_info, right_info, width, height, config.baseline_m,
                           config.focal_px)
    return left, right, camera, decode(left_msg, topics.image_type) if colour else None


def read_sets_ahead(reader: AnyReader, topics: StereoTopics, config: Config,
                    span: LogSpan | None, threads: int, others: Sequence[str] = (),
                    collected: list | None = None, counts: SetCounts | None = None
                    ) -> Iterator[tuple[int, int, Any, Any, Any, Any]]:
    """The sets of :func:`stereo_sets` over ``span`` (or the whole bag) in order, and its
    ``others`` messages into ``collected``, read by ``threads`` threads ahead of the caller,
    each with its own reader on the bag (from :data:`READERS`): the span's log time is cut
    into blocks of sets (read_blocks: a few, then up to READ_BLOCK_FRAMES), a thread reads a
    block with a lead of two frames and the sync tolerance on both sides (for partners logged
    across its edges) and keeps the sets whose left image was logged in it (the first block
    also its span's lead).
    The bag's decompression, which releases the GIL, runs beside the pipeline; at most
    ``threads`` + 1 blocks are held. Unpaired images are not counted; corrupt messages are,
    in ``counts``."""

    blocks, _ = read_blocks(reader, topics, config, span)
    path = list(reader.paths)[0]
    local = threading.local()
    held: list[tuple[AnyReader, tuple]] = []

    def read(block: LogSpan, first: bool) -> tuple[list, list, SetCounts]:
        if not hasattr(local, "reader"):
            local.reader, identity = READERS.take(path)
            held.append((local.reader, identity))
        extras: list = []
        found = SetCounts()
        return list(block_sets(local.reader, topics, config, block, first, others,
                               extras, found)), extras, found

    def take(future: Any) -> list:
        sets, extras, found = future.result()
        if collected is not None:
            collected.extend(extras)
        if counts is not None:
            counts.add(found)
        return sets

    read_through = False
    try:
        with ThreadPoolExecutor(threads, thread_name_prefix="bag-read") as pool:
            pending: deque = deque()
            for index, block in enumerate(blocks):
                pending.append(pool.submit(read, block, index == 0))
                if len(pending) > threads:
                    yield from take(pending.popleft())
            while pending:
                yield from take(pending.popleft())
        read_through = True
    finally:
        for own, identity in held:
            if read_through:
                READERS.give(path, own, identity)
            else:
                own.close()


def topics_of(bag: str | Path) -> dict[str, str]:
    """Topic name -> type of a bag."""
    with reading(bag) as reader:
        return {c.topic: c.msgtype for c in reader.connections}


def read_messages(bag: str | Path, topics: Iterable[str] | None = None,
                  span: LogSpan | None = None) -> Iterator[tuple[str, int, Any]]:
    """(topic, bag time ns, message) of a bag, or of those logged in a span (its lead
    left out), in time order."""

    with reading(bag) as reader:
        wanted = None if topics is None else set(topics)
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        window = {} if span is None else {"start": span.start_ns, "stop": span.stop_ns}
        for connection, timestamp, rawdata in reader.messages(connections=connections,
                                                              **window):
            yield connection.topic, timestamp, deserialize(
                cdr_bytes(reader, connection, rawdata), connection.msgtype)


def left_view_at(bag: str | Path, topics: StereoTopics, stamp: int, config: Config
                 ) -> np.ndarray:
    """The left image of ``bag`` stamped ``stamp`` (ns) in the frame results are in:
    rectified (the ``rectify`` parameter) with the camera_info of the set where it comes raw.
    Raises InputError where the bag has no such image."""
    with reading(bag) as reader:
        sides = {topics.left: "left", topics.left_info: "left_info",
                 topics.right_info: "right_info"}
        connections = [c for c in reader.connections if c.topic in sides]
        found: dict[str, Any] = {}
        # logged at most 0.1 s before its stamp and within 1 s after, as recorders do; else
        # anywhere from 1 s before it on
        for window in ({"start": stamp - 100_000_000, "stop": stamp + 1_000_000_000},
                       {"start": stamp - 1_000_000_000}):
            for connection, _, rawdata in reader.messages(connections=connections, **window):
                role = sides[connection.topic]
                msg = deserialize(cdr_bytes(reader, connection, rawdata),
                                  topics.image_type if role == "left" else INFO_TYPE)
                if role != "left":
                    found.setdefault(role, msg)
                elif stamp_ns(msg.header) == stamp:
                    found["left"] = msg
                if len(found) == 3:
                    break
            if "left" in found:
                break
        else:
            raise InputError(f"{bag} has no left image at {stamp}")
    image = decode(found["left"], topics.image_type)
    if "left_info" not in found or "right_info" not in found:
        return image
    camera = stereo_camera(found["left_info"], found["right_info"], image.shape[1],
                           image.shape[0], config.baseline_m, config.focal_px)
    if not rectifies(camera, config.rectify):
        return image
    return rectification(camera).left_view(image)
