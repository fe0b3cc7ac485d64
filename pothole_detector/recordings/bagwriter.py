"""Writing a ROS 2 bag in a thread of its own (rosbags' Writer), so that compressing and
writing it run beside the work that makes the messages."""

from __future__ import annotations

import os
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any, Callable

import lz4.frame
from rosbags.interfaces import Connection
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from ..errors import InputError

try:  # the zstd that rosbags reads and writes mcap chunks with (repair.py's too)
    from compression import zstd  # type: ignore[import-not-found]
except ImportError:
    from backports import zstd

# Serialized messages a BagWriter lets wait for its thread before ``write`` waits (bytes).
WRITE_BACKLOG_BYTES = 256 << 20
# zstd's level for the zstd chunks (zstd's own default, the level rosbags writes) and for the
# zstd_fast ones
ZSTD_LEVEL = 3
ZSTD_FAST_LEVEL = 1
# zstd's threads for one chunk: at most this many, and the part of the chunk each compresses
# (bytes; zstd's least)
ZSTD_MOST_WORKERS = 8
ZSTD_JOB_BYTES = 512 << 10
# An mcap bag's chunk compression by name: the compression its chunks record ("": none) and
# zstd's level (None: lz4 or none).
MCAP_COMPRESSIONS: dict[str, tuple[str, int | None]] = {
    "zstd": ("zstd", ZSTD_LEVEL),
    "zstd_fast": ("zstd", ZSTD_FAST_LEVEL),
    "lz4": ("lz4", None),
    "none": ("", None),
}


def compression_workers(cores: int | None = None) -> int:
    """zstd's threads for each chunk on a host of ``cores`` (default: those this process may
    run on): half of them, at most ZSTD_MOST_WORKERS; 0 (the writer's thread compresses alone)
    below four cores, which the pipeline's own threads need."""
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
            else os.cpu_count() or 1
    return 0 if cores < 4 else min(cores // 2, ZSTD_MOST_WORKERS)


def chunk_compressor(compression: str, workers: int) -> Callable[[bytes], bytes] | None:
    """The function that compresses one mcap chunk's bytes as ``compression`` asks (None where
    nothing is compressed): one zstd frame, made by ``workers`` threads of zstd's own that
    take ZSTD_JOB_BYTES of the chunk at a time (0: by the calling thread alone; as many as
    the zstd library can run, none where it was built without threads), or one lz4 frame."""
    name, level = MCAP_COMPRESSIONS[compression]
    if name == "lz4":
        return lz4.frame.compress
    if level is None:
        return None
    workers = min(workers, zstd.CompressionParameter.nb_workers.bounds()[1])
    options = {zstd.CompressionParameter.compression_level: level}
    if workers:
        options |= {zstd.CompressionParameter.nb_workers: workers,
                    zstd.CompressionParameter.job_size: ZSTD_JOB_BYTES}
    compressor = zstd.ZstdCompressor(options=options)
    return partial(compressor.compress, mode=zstd.ZstdCompressor.FLUSH_FRAME)


class BagWriter:
    """A new ROS 2 bag (version 9) in ``storage`` mcap or sqlite3, written by a thread of its
    own, in the order of the calls: ``write`` hands a serialized message over and returns, so
    that compressing and writing the bag (the compressors and file writes release the GIL) run
    beside the caller's next frame. At most ``backlog_bytes`` of messages wait; ``write`` then
    waits for the oldest. ``add_connection`` and ``close`` wait for the messages before them.
    An error of a write is raised by a later ``write`` or by ``close``, which closes the bag
    whatever happened (a second ``close`` does nothing).

    ``compression`` (mcap; a sqlite3 bag is written uncompressed): each chunk of about 1 MB of
    messages (or one larger message) by zstd at level ZSTD_LEVEL (the default: the smallest
    bag), zstd_fast (zstd at level ZSTD_FAST_LEVEL: less than half the time, about a fifth
    more bytes), lz4 (faster and larger still) or none; zstd by ``workers`` threads of its
    own (default: compression_workers)."""

    def __init__(self, path: str | Path, storage: str, compression: str = "zstd",
                 backlog_bytes: int = WRITE_BACKLOG_BYTES, workers: int | None = None
                 ) -> None:
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
        if plugin is None:
            raise InputError(f"storage must be mcap or sqlite3, got {storage!r}")
        if compression not in MCAP_COMPRESSIONS:
            raise InputError(f"compression must be one of {', '.join(MCAP_COMPRESSIONS)}, "
                             f"got {compression!r}")
        if Path(path).exists():
            raise InputError(f"{path} exists already; choose a new output path")
        self._bag = Writer(Path(path), version=9, storage_plugin=plugin)
        name = MCAP_COMPRESSIONS[compression][0] if plugin == StoragePlugin.MCAP else ""
        compressor = chunk_compressor(compression, compression_workers()
                                      if workers is None else workers) if name else None
        if name:
            self._bag.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._backlog_bytes = backlog_bytes
        self._waiting: deque[tuple[Future[None], int]] = deque()
        self.waiting_bytes = 0
        self._closed = False
        # one thread: the calls run in order, and sqlite3's connection stays in its thread
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="bag-writer")
        try:
            self._thread.submit(self._open, name, compressor).result()
        except BaseException:
            self._thread.shutdown()
            raise

    def _open(self, name: str, compressor: Callable[[bytes], bytes] | None) -> None:
        """Open the bag; a ``compressor`` and its compression's ``name`` take the place of
        rosbags' zstd in its mcap storage (McapWriter's ``compressor`` and ``compression``,
        with which it writes each chunk)."""
        self._bag.open()
        if compressor is not None:
            storage: Any = self._bag.storage
            storage.compression, storage.compressor = name, compressor

    def add_connection(self, topic: str, msgtype: str, **options: Any) -> Connection:
        """The bag's connection for ``topic`` of ``msgtype`` (rosbags' Writer.add_connection
        options), once the messages written before are."""
        self._settle(-1)
        return self._thread.submit(self._bag.add_connection, topic, msgtype,
                                   **options).result()

    def write(self, connection: Connection, timestamp: int, data: bytes) -> None:
        """Queue CDR ``data`` of ``connection`` logged at ``timestamp`` ns."""
        self._settle(self._backlog_bytes - len(data))
        self._waiting.append((self._thread.submit(self._bag.write, connection, timestamp,
                                                  data), len(data)))
        self.waiting_bytes += len(data)

    def close(self) -> None:
        """Write what waits and close the bag (metadata.yaml written); once."""
        if self._closed:
            return
        self._closed = True
        try:
            self._settle(-1)
        finally:
            try:
                self._thread.submit(self._bag.close).result()
            finally:
                self._thread.shutdown()

    def _settle(self, most_bytes: int) -> None:
        """Take the finished writes off the queue, and wait for the oldest until at most
        ``most_bytes`` wait (-1: none); a failed write's error is raised, and the writes
        after it are dropped."""
        while self._waiting and (self.waiting_bytes > most_bytes
                                 or self._waiting[0][0].done()):
            written, size = self._waiting.popleft()
            self.waiting_bytes -= size
            error = written.exception()
            if error is not None:
                for later, _ in self._waiting:
                    later.cancel()
                self._waiting.clear()
                self.waiting_bytes = 0
                raise error

