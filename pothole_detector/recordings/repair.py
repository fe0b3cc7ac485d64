"""Recordings cut off mid-way: an mcap bag whose recorder stopped before writing its summary
and footer (a crash, a full disk, a pulled cable) cannot be opened by index. Its records are
read in order with the mcap library's stream reader up to the cut, and the messages before it
are written into a repaired copy (a ROS 2 bag of their own, in the system's temporary folder,
made once per recording and reused while the recording is unchanged). Messages of types that
neither ROS 2 Jazzy nor our messages define are left out of it."""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from ..errors import InputError
from .bagwriter import BagWriter, zstd
from .messages import typestore

_log = logging.getLogger(__name__)
# a record larger than this is taken for damage, not read (bytes)
RECORD_SIZE_LIMIT = 1 << 30


def mcap_files(path: Path) -> list[Path]:
    """The .mcap files of a bag (a directory of them, or one file)."""
    if path.is_dir():
        return sorted(path.glob("*.mcap"))
    return [path] if path.suffix == ".mcap" else []


def _key(files: list[Path]) -> str:
    digest = hashlib.sha1()
    for file in files:
        stat = file.stat()
        digest.update(f"{file.resolve()}:{stat.st_size}:{stat.st_mtime_ns}".encode())
    return digest.hexdigest()[:16]


def _records(reader: StreamReader) -> Iterator[object]:
    """The records of an mcap stream in order, those of its chunks too (zstd chunks through
    the zstd rosbags uses; the others through the mcap library)."""
    for record in reader.records:
        if not isinstance(record, Chunk):
            yield record
            continue
        if record.compression == "zstd":
            record = dataclasses.replace(record, compression="",
                                         data=zstd.decompress(record.data))
        yield from breakup_chunk(record)


def repaired_copy(path: Path) -> tuple[Path, int, str]:
    """The repaired copy of the cut-off mcap bag at ``path``: (its directory, the messages it
    holds, what stopped the reading). Raises InputError where nothing before the cut can be
    read."""
    files = mcap_files(path)
    if not files:
        raise InputError(f"{path} holds no mcap file to repair")
    target = Path(tempfile.gettempdir()) / "pothole_detector_repaired" / _key(files)
    done = target / "done"
    if done.exists():
        count, stop = done.read_text().split("\n", 1)
        return target / "bag", int(count), stop
    work = target.with_name(target.name + f".{id(target)}")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    writer = BagWriter(work / "bag", "mcap")
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    connections: dict[int, object] = {}
    store = typestore()
    count, stop = 0, "the end of the file"
    try:
        for file in files:
            with file.open("rb") as stream:
                try:
                    for record in _records(StreamReader(
                            stream, emit_chunks=True, record_size_limit=RECORD_SIZE_LIMIT)):
                        if isinstance(record, Schema):
                            schemas[record.id] = record
                        elif isinstance(record, Channel):
                            channels[record.id] = record
                        elif isinstance(record, Message) and record.channel_id in channels:
                            if record.channel_id not in connections:
                                channel = channels[record.channel_id]
                                name = schemas[channel.schema_id].name
                                connections[record.channel_id] = writer.add_connection(
                                    channel.topic, name, typestore=store) \
                                    if name in store.fielddefs else None
                            if connections[record.channel_id] is not None:
                                writer.write(connections[record.channel_id],
                                             record.log_time, record.data)
                                count += 1
                except (McapError, EOFError, ValueError, KeyError, OSError) as exc:
                    stop = f"{type(exc).__name__} in {file.name}: {exc}"
    finally:
        writer.close()
    if count == 0:
        shutil.rmtree(work, ignore_errors=True)
        raise InputError(f"{path} is cut off and holds no readable message before the cut "
                         f"({stop})")
    (work / "done").write_text(f"{count}\n{stop}")
    try:
        work.rename(target)
    except OSError:  # another process repaired it at the same time
        shutil.rmtree(work, ignore_errors=True)
    return target / "bag", count, stop
