"""Reading a bag ahead of the pipeline in worker processes (the ``read_processes`` parameter).

Each worker reads the bag with readers of its own (kept from block to block, as every
process keeps them: :data:`.bags.READERS`) and decompresses and decodes blocks of its log time
(as the read threads of :func:`.bags.read_sets_ahead` do); it writes each set's pixels
into a slot of a ring of shared memory that this process reads in place, so the process that
runs the pipeline takes no part in decoding and copies no pixels. A slot returns to the ring
when the last array on it is gone. Where the ring has no free slot, or a pair does not fit in
one, the pixels come back pickled instead."""

from __future__ import annotations

import logging
import math
import multiprocessing.util
import shutil
import weakref
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from ..errors import PotholeError
from .messages import deserialize, header_at, serialize
from ..params import Config
from .bags import (BagFrame, LogSpan, SetCounts, block_sets, cdr_bytes, convert_set,
                   read_blocks, reading)
from .images import decode
from .topics import StereoTopics

_log = logging.getLogger(__name__)

SLOT_ALIGN_BYTES = 64
# read_processes -1 (the default) on the GPU backend: a decoding process per this many of the
# pipeline process's host cores, at most MOST_DECODERS
CORES_PER_DECODER = 4
MOST_DECODERS = 4
# The share of the free shared memory (/dev/shm) that the ring may take.
SHARED_MEMORY_SHARE = 0.5

# (stamp ns, left image's log time ns, frame_id, pixels, calibration, error): pixels are
# (slot, left shape, left dtype, right shape, right dtype) or the (left, right) arrays.
DecodedSet = tuple[int, int, str, Any, Any, PotholeError | None]

_WORKER: dict[str, Any] = {}


def processes_for(setting: int, backend: str, cores: int) -> int:
    """The decoding processes of a ``read_processes`` ``setting``: itself where it is 0 or
    more; for -1, with a pipeline on the ``backend`` named ``gpu`` one per CORES_PER_DECODER of
    the ``cores`` its process has (at most MOST_DECODERS; 0: the read threads), on the CPU none
    (its pipeline takes the cores, and decoding is a small share of its frame)."""
    if setting >= 0:
        return setting
    return min(MOST_DECODERS, cores // CORES_PER_DECODER) if backend == "gpu" else 0


def _aligned(size: int) -> int:
    return -(-size // SLOT_ALIGN_BYTES) * SLOT_ALIGN_BYTES


def _worker_ring(name: str) -> memoryview:
    """The buffer of the shared-memory ring ``name``, attached once per worker."""
    if _WORKER.get("ring_name") != name:
        if "ring" in _WORKER:
            _WORKER.pop("ring").close()
        _WORKER["ring"] = SharedMemory(name=name)
        _WORKER["ring_name"] = name
    return _WORKER["ring"].buf


def _converted_sets(reader: Any, topics: StereoTopics, config: Config, block: LogSpan,
                    first: bool, others: Sequence[str],
                    place: Callable[[np.ndarray, np.ndarray], Any]
                    ) -> tuple[list[DecodedSet], list[tuple[str, int, Any]], SetCounts]:
    """The sets whose left image was logged in ``block`` (the first block also its lead),
    converted, each set's pixels as ``place(left, right)`` gives them; the ``others`` messages
    logged in the block as (topic, log time ns, message); and the corrupt messages
    counted."""
    decoded: list[DecodedSet] = []
    extras: list[tuple[str, int, Any]] = []
    counts = SetCounts()
    for stamp, logged, left_msg, right_msg, left_info, right_info in block_sets(
            reader, topics, config, block, first, others, extras, counts):
        frame_id = left_msg.header.frame_id
        try:
            left, right, calibration, _ = convert_set(topics, left_msg, right_msg, left_info,
                                                      right_info, config)
        except PotholeError as exc:
            decoded.append((stamp, logged, frame_id, None, None, exc))
            continue
        decoded.append((stamp, logged, frame_id, place(left, right), calibration, None))
    return decoded, extras, counts


def decode_block(path: str, topics: StereoTopics, values: dict[str, Any],
                 block: LogSpan, first: bool, others: Sequence[str], ring: str,
                 slot_bytes: int, slots: Sequence[int]
                 ) -> tuple[list[DecodedSet], list[tuple[str, int, bytes]], list[int],
                            SetCounts]:
    """A worker's task: the converted sets of ``block`` (:func:`_converted_sets`), their
    pixels written into the granted ``slots`` of the ring (each ``slot_bytes`` long) while
    they last; the ``others`` messages logged in the block as (topic, log time ns, CDR bytes);
    the slots left unused; and the corrupt messages counted."""
    free = deque(slots)

    def place(left: np.ndarray, right: np.ndarray) -> Any:
        if not free or _aligned(left.nbytes) + right.nbytes > slot_bytes:
            return left, right
        slot = free.popleft()
        buffer = _worker_ring(ring)
        offset = slot * slot_bytes
        for part, start in ((left, offset), (right, offset + _aligned(left.nbytes))):
            np.ndarray(part.nbytes, np.uint8, buffer, start)[:] = part.reshape(-1).view(np.uint8)
        return slot, left.shape, left.dtype.str, right.shape, right.dtype.str

    with reading(path) as reader:
        types = {connection.topic: connection.msgtype for connection in reader.connections}
        decoded, extras, counts = _converted_sets(reader, topics, Config(values), block, first,
                                                  others, place)
    messages = [(topic, logged, serialize(msg, types[topic])) for topic, logged, msg in extras]
    return decoded, messages, list(free), counts


def _read_here(path: str, topics: StereoTopics, config: Config, block: LogSpan, first: bool,
               others: Sequence[str]
               ) -> tuple[list[DecodedSet], list[tuple[str, int, Any]], list[int], SetCounts]:
    """:func:`decode_block` in a thread of this process, with a reader of its pool, before the
    workers are up: the pixels as arrays, the messages as messages, no slots."""
    with reading(path) as reader:
        decoded, extras, counts = _converted_sets(reader, topics, config, block, first, others,
                                                  lambda left, right: (left, right))
    return decoded, extras, [], counts


def _ready() -> None:
    """A worker's first task: it has started and imported what decoding needs."""


class Ring:
    """A ring of ``slots`` shared-memory slots of ``slot_bytes`` each (fewer, or none, where
    shared memory is short or cannot be made) and which of them are free."""

    def __init__(self, slot_bytes: int, slots: int) -> None:
        self.slot_bytes, self.wanted = slot_bytes, slots
        try:
            free_bytes = shutil.disk_usage("/dev/shm").free
        except OSError:
            free_bytes = slot_bytes * slots
        self.slots = max(0, min(slots, int(free_bytes * SHARED_MEMORY_SHARE) // slot_bytes))
        self.memory: SharedMemory | None = None
        if self.slots > 0:
            try:
                self.memory = SharedMemory(create=True, size=slot_bytes * self.slots)
            except OSError as exc:
                _log.warning(f"no shared memory for the decoded images ({exc}): they come "
                             "back pickled")
                self.slots = 0
        self.free: deque[int] = deque(range(self.slots))
        self._closing = False

    @property
    def name(self) -> str:
        return self.memory.name if self.memory is not None else ""

    def grant(self, count: int) -> list[int]:
        """Up to ``count`` free slots, taken off the ring."""
        taken = []
        while self.free and len(taken) < count:
            taken.append(self.free.popleft())
        return taken

    def give_back(self, slots: Iterable[int]) -> None:
        """Return ``slots`` to the ring (a closing ring lets its memory go with the last)."""
        self.free.extend(slots)
        if self._closing and len(self.free) == self.slots:
            self._unmap()

    def frame(self, decoded: DecodedSet) -> BagFrame | tuple[BagFrame, PotholeError]:
        """The frame of a decoded set, its arrays on its slot (which returns to the ring when
        they are gone), or the frame and the error that its conversion raised."""
        stamp, logged, frame_id, pixels, calibration, error = decoded
        header = header_at(stamp, frame_id)
        if error is not None:
            return BagFrame(stamp, header, None, None, None, logged), error
        if isinstance(pixels[0], np.ndarray):
            left, right = pixels
        else:
            slot, left_shape, left_dtype, right_shape, right_dtype = pixels
            assert self.memory is not None
            whole = np.ndarray(self.slot_bytes, np.uint8, self.memory.buf,
                               slot * self.slot_bytes)
            weakref.finalize(whole, self.give_back, (slot,))
            left_bytes = math.prod(left_shape) * np.dtype(left_dtype).itemsize
            right_bytes = math.prod(right_shape) * np.dtype(right_dtype).itemsize
            start = _aligned(left_bytes)
            left = whole[:left_bytes].view(left_dtype).reshape(left_shape)
            right = whole[start:start + right_bytes].view(right_dtype).reshape(right_shape)
        return BagFrame(stamp, header, left, right, calibration, logged)

    def close(self) -> None:
        """Free the ring: its name now, its memory once every slot is back (NumPy arrays on
        a slot do not keep the mapping; each keeps the ring until it is gone)."""
        if self.memory is not None and not self._closing:
            self._closing = True
            self.memory.unlink()
            if len(self.free) == self.slots:
                self._unmap()

    def _unmap(self) -> None:
        assert self.memory is not None
        try:
            self.memory.close()
        except BufferError:
            pass


class Decoders:
    """``processes`` worker processes, all started at once, and the ring they write into."""

    def __init__(self, processes: int) -> None:
        self.processes = processes
        self.ring: Ring | None = None
        self._start()

    def _start(self) -> None:
        self.pool = ProcessPoolExecutor(self.processes, mp_context=get_context("spawn"))
        self._started = [self.pool.submit(_ready) for _ in range(self.processes)]

    def restart(self) -> None:
        """New workers in place of a pool that a worker died in; the ring stays (the sets
        decoded before lie on it)."""
        self.pool.shutdown(wait=False, cancel_futures=True)
        self._start()

    def ready(self) -> bool:
        """Whether a worker has started and imported what decoding needs (a worker's start,
        a new interpreter's imports, takes about a second or more)."""
        return any(started.done() for started in self._started)

    def ring_of(self, slot_bytes: int, slots: int) -> Ring:
        """This process's ring, made anew where it holds fewer or smaller slots."""
        if self.ring is None or self.ring.slot_bytes < slot_bytes or self.ring.wanted < slots:
            if self.ring is not None:
                self.ring.close()
            self.ring = Ring(slot_bytes, slots)
        return self.ring

    def close(self) -> None:
        """Stop the workers and free the ring."""
        self.pool.shutdown(cancel_futures=True)
        if self.ring is not None:
            self.ring.close()


_DECODERS: list[Decoders] = []


def start(processes: int) -> Decoders:
    """This process's ``processes`` workers, started now where they are not running (those
    of another count are stopped)."""
    if _DECODERS and _DECODERS[0].processes != processes:
        _DECODERS.pop().close()
    if not _DECODERS:
        _DECODERS.append(Decoders(processes))
    return _DECODERS[0]


def _close_decoders() -> None:
    while _DECODERS:
        _DECODERS.pop().close()


# At this interpreter's exit, and in a worker process (survey --jobs) before multiprocessing
# closes its queues and joins its children: before the queues of our own workers close.
multiprocessing.util.Finalize(None, _close_decoders, exitpriority=100)


def _pair_bytes(reader: Any, topics: StereoTopics) -> int:
    """The bytes a slot needs for a pair of the bag's first left image as decoded; a slot of
    the least size where it cannot be decoded."""
    connections = [c for c in reader.connections if c.topic == topics.left]
    for connection, _, rawdata in reader.messages(connections=connections):
        try:
            image = decode(deserialize(cdr_bytes(reader, connection, rawdata),
                                       topics.image_type), topics.image_type, grey=True)
        except (PotholeError, ValueError, TypeError):
            break
        return 2 * _aligned(image.nbytes)
    return SLOT_ALIGN_BYTES


def decoded_frames(reader: Any, topics: StereoTopics, config: Config, span: LogSpan | None,
                   processes: int, others: Sequence[str] = (), collected: list | None = None,
                   counts: SetCounts | None = None
                   ) -> Iterator[BagFrame | tuple[BagFrame, PotholeError]]:
    """The frames of the sets of ``span`` (or the whole bag) in order, converted as
    :func:`.bags.convert_set` does (without the colour image), read and decoded by
    ``processes`` worker processes a block at a time (the blocks of :func:`.bags.read_blocks`),
    at most ``processes`` + 1 blocks ahead; the blocks taken before any worker is up (its
    start takes a second or more) are read by read_threads threads of this process instead,
    and so are the block a worker died on and every block after it (with a warning). The
    ``others`` messages logged in the span go into ``collected``, the corrupt messages into
    ``counts``."""
    blocks, period_ns = read_blocks(reader, topics, config, span)
    lead_sets = math.ceil(blocks[0].lead_ns / period_ns) + 2
    sets_in = [math.ceil((block.stop_ns - block.start_ns) / period_ns) + 2
               for block in blocks]
    decoders = start(processes)
    ring = decoders.ring_of(_pair_bytes(reader, topics),
                            (processes + 2) * max(sets_in) + lead_sets)
    path = str(Path(list(reader.paths)[0]))
    values = config.as_dict()
    here = ThreadPoolExecutor(config.read_threads, thread_name_prefix="bag-read")

    broken: list[BrokenProcessPool] = []

    def read_here(index: int) -> Future:
        return here.submit(_read_here, path, topics, config, blocks[index], index == 0,
                           tuple(others))

    def stopped(exc: BrokenProcessPool) -> None:
        """A worker died: new workers start for the next reading, and this one goes on in
        threads here."""
        if not broken:
            broken.append(exc)
            _log.warning(f"a decoding process stopped ({exc}): reading the rest of the bag "
                         "in this process's threads")
            decoders.restart()

    def submit(index: int) -> tuple[Future, list[int], bool, int]:
        if not broken and decoders.ready():
            slots = ring.grant(sets_in[index] + (lead_sets if index == 0 else 0))
            try:
                return decoders.pool.submit(decode_block, path, topics, values, blocks[index],
                                            index == 0, tuple(others), ring.name,
                                            ring.slot_bytes, slots), slots, True, index
            except BrokenProcessPool as exc:
                ring.give_back(slots)
                stopped(exc)
        return read_here(index), [], False, index

    def take(future: Future, slots: list[int], serialized: bool, index: int
             ) -> Iterator[BagFrame | tuple]:
        try:
            decoded, messages, unused, found = future.result()
        except BrokenProcessPool as exc:
            ring.give_back(slots)
            stopped(exc)
            decoded, messages, unused, found = read_here(index).result()
            serialized = False
        ring.give_back(unused)
        if counts is not None:
            counts.add(found)
        if collected is not None:
            collected.extend((topic, logged, deserialize(data, types[topic]) if serialized
                              else data) for topic, logged, data in messages)
        remaining = deque(decoded)
        try:
            while remaining:
                yield ring.frame(remaining.popleft())
        finally:
            ring.give_back(pixels[0] for *_, pixels, _, _ in remaining
                             if pixels is not None and isinstance(pixels[0], int))

    types = {connection.topic: connection.msgtype for connection in reader.connections}
    pending: deque[tuple[Future, list[int], bool, int]] = deque()
    try:
        for index in range(len(blocks)):
            pending.append(submit(index))
            if len(pending) > processes:
                yield from take(*pending.popleft())
        while pending:
            yield from take(*pending.popleft())
    finally:
        for future, slots, _, _ in pending:
            future.cancel()
            future.add_done_callback(lambda _, taken=slots: ring.give_back(taken))
        here.shutdown(wait=False, cancel_futures=True)
