from __future__ import annotations

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, ConnectionExtRosbag2
from rosbags.rosbag2 import WriterError

from pothole_detector.errors import InputError
from pothole_detector.recordings.bagwriter import (ZSTD_FAST_LEVEL, ZSTD_JOB_BYTES,
                                                    ZSTD_MOST_WORKERS, BagWriter,
                                                    chunk_compressor, compression_workers, zstd)
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


@pytest.mark.parametrize("compression, recorded, workers", [
    ("zstd", "zstd", 0), ("zstd", "zstd", 2), ("zstd_fast", "zstd", 0),
    ("zstd_fast", "zstd", 3), ("lz4", "lz4", 2), ("none", "", 2)])
def test_mcap_chunks_are_compressed_as_asked(tmp_path, compression, recorded, workers):
    """Each chunk records its compression; rosbags and the mcap library read every one back
    to the same messages, made by zstd's threads or not, and the repetitive text shrinks
    wherever it is compressed."""
    writer = BagWriter(tmp_path / "bag", "mcap", compression, workers=workers)
    texts = writer.add_connection("/texts", STRING, typestore=typestore())
    written = [f"road {index % 7} " * 2000 for index in range(300)] + ["pothole " * 300_000]
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
    with path.open("rb") as stream:
        assert [bytes(message.data) for _, _, message in make_reader(stream).iter_messages()] \
            == [_string(text) for text in written]


def test_zstd_threads_make_the_same_frame_as_one_another_and_their_share_follows_the_cores():
    """A chunk of several of zstd's jobs comes out the same by two threads as by five, and
    decompresses to itself; the writer takes half the cores for them, none below four."""
    chunk = bytes(range(256)) * 12_000 + bytes(3 * ZSTD_JOB_BYTES)
    two, five = (chunk_compressor("zstd_fast", workers)(chunk) for workers in (2, 5))
    assert two == five and len(two) < len(chunk) / 10
    assert zstd.decompress(two) == zstd.decompress(chunk_compressor("zstd", 0)(chunk)) == chunk
    assert [compression_workers(cores) for cores in (1, 2, 3, 4, 6, 16, 128)] == \
        [0, 0, 0, 2, 3, 8, ZSTD_MOST_WORKERS]
    assert 0 <= compression_workers() <= ZSTD_MOST_WORKERS


def test_a_zstd_built_without_threads_compresses_alone(monkeypatch):
    """Where the zstd library has no threads (nb_workers bounded to 0), the chunks are
    compressed by the writer's thread, not refused."""
    class Unthreaded:
        @staticmethod
        def bounds() -> tuple[int, int]:
            return (0, 0)

    parameters = zstd.CompressionParameter
    made = []

    real = zstd.ZstdCompressor

    class Recording:
        FLUSH_FRAME = real.FLUSH_FRAME

        def __new__(cls, options):
            made.append(options)
            return real(options=options)

    monkeypatch.setattr(zstd, "ZstdCompressor", Recording)
    monkeypatch.setattr(zstd, "CompressionParameter", type(
        "Parameters", (), {"nb_workers": Unthreaded, "job_size": parameters.job_size,
                           "compression_level": parameters.compression_level}))
    chunk = bytes(range(256)) * 8_000
    assert zstd.decompress(chunk_compressor("zstd_fast", 8)(chunk)) == chunk
    assert made == [{parameters.compression_level: ZSTD_FAST_LEVEL}]


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
