from __future__ import annotations

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, ConnectionExtRosbag2
from rosbags.rosbag2 import WriterError

from pothole_detector.errors import InputError
from pothole_detector.recordings.bagwriter import BagWriter
from pothole_detector.recordings.messages import header_at, message, serialize, typestore

STRING = "std_msgs/msg/String"
HEADER = "std_msgs/msg/Header"


def _string(text: str) -> bytes:
    return serialize(message(STRING)(data=text), STRING)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_messages_arrive_in_the_order_written(tmp_path, storage):
    """Writes run in the writer's thread (sqlite3's connection lives there too); connections
    added between writes find the messages before them written."""
    writer = BagWriter(tmp_path / "bag", storage)
    store = typestore()
    texts = writer.add_connection("/texts", STRING, typestore=store)
    for index in range(50):
        writer.write(texts, 1_000 + index, _string(f"text {index}"))
    stamps = writer.add_connection("/stamps", HEADER, typestore=store)
    writer.write(stamps, 2_000, serialize(header_at(2_000, "here"), HEADER))
    writer.close()
    with AnyReader([tmp_path / "bag"], default_typestore=store) as reader:
        read = [(c.topic, t, reader.deserialize(raw, c.msgtype))
                for c, t, raw in reader.messages()]
    assert [t for _, t, _ in read] == [1_000 + i for i in range(50)] + [2_000]
    assert [m.data for topic, _, m in read if topic == "/texts"] == \
        [f"text {i}" for i in range(50)]
    assert read[-1][2].frame_id == "here"


@pytest.mark.parametrize("compression, recorded", [("zstd", "zstd"), ("zstd_fast", "zstd"),
                                                   ("lz4", "lz4"), ("none", "")])
def test_mcap_chunks_are_compressed_as_asked(tmp_path, compression, recorded):
    """Each chunk records its compression; rosbags reads every one back to the same messages,
    and the repetitive text shrinks wherever it is compressed."""
    writer = BagWriter(tmp_path / "bag", "mcap", compression)
    texts = writer.add_connection("/texts", STRING, typestore=typestore())
    written = [f"road {index % 7} " * 2000 for index in range(300)]
    for index, text in enumerate(written):
        writer.write(texts, 1_000 + index, _string(text))
    writer.close()
    (path,) = (tmp_path / "bag").glob("*.mcap")
    with path.open("rb") as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    assert len(chunks) > 1 and {chunk.compression for chunk in chunks} == {recorded}
    packed = sum(chunk.compressed_size for chunk in chunks)
    raw = sum(chunk.uncompressed_size for chunk in chunks)
    assert packed == raw if compression == "none" else packed < raw / 20
    with AnyReader([tmp_path / "bag"], default_typestore=typestore()) as reader:
        assert [reader.deserialize(data, c.msgtype).data
                for c, _, data in reader.messages()] == written


def test_the_backlog_bounds_the_bytes_waiting(tmp_path):
    writer = BagWriter(tmp_path / "bag", "mcap", backlog_bytes=4096)
    texts = writer.add_connection("/texts", STRING, typestore=typestore())
    data = _string("x" * 1000)
    for index in range(200):
        writer.write(texts, index, data)
        assert writer.waiting_bytes <= 4096
    writer.close()
    assert writer.waiting_bytes == 0
    with AnyReader([tmp_path / "bag"], default_typestore=typestore()) as reader:
        assert reader.message_count == 200


def test_a_failed_write_is_raised_and_the_bag_still_closes(tmp_path):
    """A write the thread could not make (a connection of another bag) is raised by a later
    call; the writes queued after it are dropped, the bag is closed with what came before."""
    writer = BagWriter(tmp_path / "bag", "mcap")
    texts = writer.add_connection("/texts", STRING, typestore=typestore())
    writer.write(texts, 1, _string("kept"))
    stranger = Connection(7, "/elsewhere", STRING, texts.msgdef, texts.digest, 0,
                          ConnectionExtRosbag2("cdr", []), None)
    writer.write(stranger, 2, _string("lost"))
    with pytest.raises(WriterError, match="unknown connection"):
        for index in range(1000):
            writer.write(texts, 3 + index, _string("after"))
        writer.close()
    writer.close()
    with AnyReader([tmp_path / "bag"], default_typestore=typestore()) as reader:
        kept = [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages()]
    assert kept[0] == "kept" and "lost" not in kept


def test_an_existing_path_or_unknown_storage_is_refused(tmp_path):
    (tmp_path / "taken").mkdir()
    with pytest.raises(InputError, match="exists already"):
        BagWriter(tmp_path / "taken", "mcap")
    with pytest.raises(InputError, match="mcap or sqlite3"):
        BagWriter(tmp_path / "new", "db3")
    with pytest.raises(InputError, match="zstd, zstd_fast, lz4, none"):
        BagWriter(tmp_path / "new", "mcap", "brotli")
