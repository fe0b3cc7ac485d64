"""Writing a ROS 2 bag in a thread of its own (rosbags' Writer), so that compressing and
writing it run beside the work that makes the messages."""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from rosbags.interfaces import Connection
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from ..errors import InputError

# Serialized messages a BagWriter lets wait for its thread before ``write`` waits (bytes).
WRITE_BACKLOG_BYTES = 256 << 20


class BagWriter:
    """A new ROS 2 bag (version 9) in ``storage`` mcap (zstd chunks) or sqlite3, written by a
    thread of its own, in the order of the calls: ``write`` hands a serialized message over
    and returns, so that compressing and writing the bag (zstd and file writes release the
    GIL) run beside the caller's next frame. At most ``backlog_bytes`` of messages wait;
    ``write`` then waits for the oldest. ``add_connection`` and ``close`` wait for the
    messages before them. An error of a write is raised by a later ``write`` or by ``close``,
    which closes the bag whatever happened (a second ``close`` does nothing)."""

    def __init__(self, path: str | Path, storage: str,
                 backlog_bytes: int = WRITE_BACKLOG_BYTES) -> None:
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
        if plugin is None:
            raise InputError(f"storage must be mcap or sqlite3, got {storage!r}")
        if Path(path).exists():
            raise InputError(f"{path} exists already; choose a new output path")
        self._bag = Writer(Path(path), version=9, storage_plugin=plugin)
        if plugin == StoragePlugin.MCAP:
            self._bag.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._backlog_bytes = backlog_bytes
        self._waiting: deque[tuple[Future[None], int]] = deque()
        self.waiting_bytes = 0
        self._closed = False
        # one thread: the calls run in order, and sqlite3's connection stays in its thread
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="bag-writer")
        try:
            self._thread.submit(self._bag.open).result()
        except BaseException:
            self._thread.shutdown()
            raise

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

