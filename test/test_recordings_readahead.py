"""Reading a bag in worker processes: the frames one reader gives, their pixels through the
shared-memory ring and back to it, pickled where the ring has no room, and a set that cannot
be converted."""

from __future__ import annotations

import gc
import time
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("rosbags")

from pothole_detector.recordings.writing import write_stereo_bag  # noqa: E402
from pothole_detector.recordings import bags, readahead  # noqa: E402
from pothole_detector.errors import InputError  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.evaluation.synthetic import drive_scenes, render  # noqa: E402

from conftest import rewrite_bag  # noqa: E402

START = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000
STEREO = ["/cam/left/image_rect", "/cam/right/image_rect", "/cam/left/camera_info",
          "/cam/right/camera_info"]
TOPICS = bags.StereoTopics(*STEREO)


@pytest.fixture(scope="module")
def samples():
    """Three frames of the driving sequence at 640x360 (mono8)."""
    return [render(scene) for scene in drive_scenes(frames=3)]


def _bag(folder, samples, count, colour=False, infos_from=0):
    """``count`` sets 0.1 s apart, the right image and both camera_infos logged 30 ms after the
    left (partners across block edges); no camera_info before set ``infos_from``."""
    if colour:
        samples = [replace(s, left=np.repeat(s.left[..., None], 3, 2) // [1, 2, 3],
                           right=np.repeat(s.right[..., None], 3, 2) // [1, 2, 3])
                   for s in samples]
        samples = [replace(s, left=s.left.astype(np.uint8), right=s.right.astype(np.uint8))
                   for s in samples]
    source, bag = folder / "source", folder / "bag"
    frames = [(START + i * PERIOD_NS, samples[i % len(samples)]) for i in range(count)]
    assert write_stereo_bag(source, frames, namespace="/cam") == count

    def logged(topic, timestamp):
        if topic.endswith("camera_info") and timestamp < START + infos_from * PERIOD_NS:
            return None
        return timestamp + (0 if topic == STEREO[0] else 30_000_000)

    rewrite_bag(source, bag, logged)
    return bag


def _one_reader(reader, span):
    """(stamp, log time, left, right, calibration or the error) as one reader converts them."""
    sets = []
    for stamp, logged, left, right, left_info, right_info in bags.stereo_sets(
            reader, TOPICS, Config(), bags.SetCounts(), span):
        try:
            sets.append((stamp, logged, *bags.convert_set(TOPICS, left, right, left_info,
                                                          right_info, Config())[:3]))
        except InputError as exc:
            sets.append((stamp, logged, None, None, str(exc)))
    return sets


def _as_sets(frames):
    return [(item[0].stamp, item[0].logged_ns, None, None, str(item[1]))
            if isinstance(item, tuple) else
            (item.stamp, item.logged_ns, item.left, item.right, item.camera)
            for item in frames]


def _assert_same(got, expected):
    assert [s[:2] for s in got] == [s[:2] for s in expected]
    for (_, _, left, right, calibration), (_, _, left_0, right_0, calibration_0) in zip(
            got, expected):
        assert calibration == calibration_0
        if left_0 is not None:
            np.testing.assert_array_equal(left, left_0)
            np.testing.assert_array_equal(right, right_0)
            assert left.dtype == left_0.dtype and right.shape == right_0.shape


@pytest.fixture
def fresh_decoders():
    readahead._close_decoders()
    yield
    readahead._close_decoders()


@pytest.fixture
def decoders_up(fresh_decoders):
    """Two worker processes, each started and ready to decode."""
    decoders = readahead.start(2)
    for started in decoders._started:
        started.result(timeout=120)
    return decoders


@pytest.mark.parametrize("colour", [False, True], ids=["mono8", "rgb8"])
def test_worker_processes_give_the_frames_one_reader_gives(tmp_path, samples, colour,
                                                           monkeypatch, decoders_up):
    """Twenty sets read in blocks of two, then three, by two worker processes that are up, of
    the whole bag and of a span with its lead: the sets, pixels and calibrations one reader
    gives, in order, each set's pixels on a slot of the ring; every slot is back once the
    frames are gone."""
    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 3)
    reader = bags.open_bag(_bag(tmp_path, samples, 20, colour))
    try:
        for span in (None, bags.LogSpan(START + 450_000_000, START + 1_650_000_000,
                                            250_000_000)):
            got, on_slots = [], []
            for frame in readahead.decoded_frames(reader, TOPICS, Config(), span, 2):
                ring = readahead._DECODERS[0].ring
                on_slots.append(frame.left.base is frame.right.base
                                and frame.left.base.size == ring.slot_bytes)
                got.append((frame.stamp, frame.logged_ns, frame.left.copy(),
                            frame.right.copy(), frame.camera))
                if not got[1:]:
                    assert frame.header.frame_id == "stereo_left_optical_frame"
            expected = _one_reader(reader, span)
            assert len(expected) == (20 if span is None else 15)
            _assert_same(got, expected)
            assert all(on_slots)
            del frame
            gc.collect()
            assert ring.slots > 0 and len(ring.free) == ring.slots
    finally:
        reader.close()


def test_without_room_in_shared_memory_the_pixels_come_pickled(tmp_path, samples, monkeypatch,
                                                               fresh_decoders):
    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 4)
    monkeypatch.setattr(readahead, "SHARED_MEMORY_SHARE", 0.0)
    reader = bags.open_bag(_bag(tmp_path, samples, 9))
    try:
        frames = list(readahead.decoded_frames(reader, TOPICS, Config(), None, 2))
        assert readahead._DECODERS[0].ring.memory is None
        _assert_same(_as_sets(frames), _one_reader(reader, None))
    finally:
        reader.close()


def test_a_set_without_camera_info_comes_back_as_its_error(tmp_path, samples, monkeypatch,
                                                           fresh_decoders):
    """No camera_info for the first two of twelve sets: those two are errors that say what is
    missing, and the sets after them are read."""
    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 4)
    reader = bags.open_bag(_bag(tmp_path, samples, 12, infos_from=2))
    try:
        frames = list(readahead.decoded_frames(reader, TOPICS, Config(), None, 2))
        got = _as_sets(frames)
        assert [s[4] for s in got[:2]] == ["no camera_info on /cam/left/camera_info and "
                                           "/cam/right/camera_info yet"] * 2
        assert all(isinstance(item, bags.BagFrame) for item in frames[2:])
        _assert_same(got, _one_reader(reader, None))
    finally:
        reader.close()


def test_a_reading_stopped_early_gives_its_slots_back(tmp_path, samples, monkeypatch,
                                                      decoders_up):
    """Two frames taken of twenty, then the reading is closed: the blocks read ahead give
    their slots back as they finish."""
    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 3)
    reader = bags.open_bag(_bag(tmp_path, samples, 20))
    try:
        frames = readahead.decoded_frames(reader, TOPICS, Config(), None, 2)
        taken = [next(frames).stamp for _ in range(2)]
        ring = readahead._DECODERS[0].ring
        assert len(ring.free) < ring.slots
        frames.close()
        gc.collect()
        deadline = time.monotonic() + 30
        while len(ring.free) < ring.slots and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(ring.free) == ring.slots
        assert taken == [START, START + PERIOD_NS]
    finally:
        reader.close()


def test_blocks_taken_before_the_workers_are_up_are_read_here(tmp_path, samples, monkeypatch,
                                                               fresh_decoders):
    """The first three blocks (2, 3 and 3 frames long) are taken while no worker is up: this
    process reads them, the workers the rest; the frames are those one reader gives, in order, the
    later ones on slots of the ring."""
    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 3)
    asked = []
    monkeypatch.setattr(readahead.Decoders, "ready", lambda self: asked.append(1) or
                        len(asked) > 3)
    reader = bags.open_bag(_bag(tmp_path, samples, 20))
    try:
        got, on_slots = [], []
        for frame in readahead.decoded_frames(reader, TOPICS, Config(), None, 2):
            ring = readahead._DECODERS[0].ring
            on_slots.append(frame.left.base is frame.right.base is not None
                            and frame.left.base.size == ring.slot_bytes)
            got.append((frame.stamp, frame.logged_ns, frame.left.copy(), frame.right.copy(),
                        frame.camera))
        _assert_same(got, _one_reader(reader, None))
        fourth = bags.read_blocks(reader, TOPICS, Config(), None)[0][3]
        read_here = sum(logged < fourth.start_ns for _, logged, *_ in got)
        assert read_here >= 8 and on_slots == [False] * read_here + [True] * (20 - read_here)
    finally:
        reader.close()


def test_a_decoder_that_dies_leaves_the_reading_to_threads_here(tmp_path, samples,
                                                                monkeypatch, decoders_up,
                                                                caplog):
    """The workers are killed after the first frame: the reading goes on in this process's
    threads, with a warning, and gives every frame one reader gives; new workers take the
    next reading."""
    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 3)
    reader = bags.open_bag(_bag(tmp_path, samples, 20))
    try:
        frames = readahead.decoded_frames(reader, TOPICS, Config(), None, 2)
        got = [next(frames)]
        killed = decoders_up.pool
        for process in list(killed._processes.values()):
            process.kill()
            process.join()
        got.extend(frames)
        _assert_same(_as_sets(got), _one_reader(reader, None))
        assert "a decoding process stopped" in caplog.text
        assert readahead._DECODERS == [decoders_up] and decoders_up.pool is not killed
        del got
        gc.collect()
        assert len(decoders_up.ring.free) == decoders_up.ring.slots
        for started in decoders_up._started:
            started.result(timeout=120)
        again = list(readahead.decoded_frames(reader, TOPICS, Config(), None, 2))
        _assert_same(_as_sets(again), _one_reader(reader, None))
        ring = decoders_up.ring
        assert all(frame.left.base is frame.right.base
                   and frame.left.base.size == ring.slot_bytes for frame in again)
    finally:
        reader.close()


def test_without_shared_memory_the_pixels_come_pickled(tmp_path, samples, monkeypatch,
                                                       decoders_up, caplog):
    """Where shared memory cannot be made (no /dev/shm, say), the ring has no slots and the
    workers' pixels come back pickled, with a warning."""
    def refused(*args, **kwargs):
        raise PermissionError("no /dev/shm here")

    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 4)
    monkeypatch.setattr(readahead, "SharedMemory", refused)
    reader = bags.open_bag(_bag(tmp_path, samples, 9))
    try:
        frames = list(readahead.decoded_frames(reader, TOPICS, Config(), None, 2))
        assert readahead._DECODERS[0].ring.memory is None
        assert "no shared memory" in caplog.text
        _assert_same(_as_sets(frames), _one_reader(reader, None))
    finally:
        reader.close()


def test_a_closed_ring_keeps_its_memory_while_a_frame_lies_on_it():
    """A ring closed (a new one made, the workers stopped) while a frame lies on one of its
    slots: the frame's pixels stay readable; the memory goes with the frame."""
    ring = readahead.Ring(128, 4)
    slot, = ring.grant(1)
    np.ndarray(128, np.uint8, ring.memory.buf, slot * 128)[:] = np.arange(128, dtype=np.uint8)
    frame = ring.frame((START, START, "left", (slot, (8, 8), "|u1", (4, 8), "|u1"), None, None))
    shared = ring.memory
    ring.close()
    del ring
    gc.collect()
    assert shared.buf is not None
    np.testing.assert_array_equal(frame.left.ravel(), np.arange(64))
    np.testing.assert_array_equal(frame.right.ravel(), np.arange(64, 96))
    del frame
    gc.collect()
    assert shared.buf is None


@pytest.mark.parametrize("setting, backend, cores, expected", [
    (3, "cpu", 16, 3), (0, "gpu", 16, 0), (-1, "gpu", 16, 4), (-1, "gpu", 64, 4),
    (-1, "gpu", 8, 2), (-1, "gpu", 3, 0), (-1, "cpu", 64, 0)])
def test_decoding_processes_by_default_only_for_a_gpu_pipeline(setting, backend, cores,
                                                                 expected):
    assert readahead.processes_for(setting, backend, cores) == expected
