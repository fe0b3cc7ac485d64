"""Recordings as people make them, through `process`: small drives of our generator stored
compressed (jpeg, png), raw with lens distortion and R (plumb_bob, rational_polynomial,
fisheye), in Bayer and YUV, under driver topic layouts, with Tx = 0. No flags where a person
would need none, and the pothole labels as good as the same drive stored rectified and
uncompressed (pixel F within 0.05). Also: a bag's sets in one pass, by span and in threads,
and damaged or corrupt bags read up to where they break."""

from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("rosbags")

from pothole_detector.ros import bagtools  # noqa: E402
from pothole_detector.recordings.writing import RecordingForm, write_stereo_bag  # noqa: E402
from pothole_detector.calibration import CameraModel, StereoCamera  # noqa: E402
from pothole_detector.errors import InputError  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.recordings import bags  # noqa: E402
from pothole_detector.recordings.images import COMPRESSED_TYPE, IMAGE_TYPE, decode_raw  # noqa
from pothole_detector.recordings.topics import StereoTopics  # noqa: E402
from pothole_detector.evaluation.synthetic import (drive_scenes, raw_camera, render,
                                                   render_raw)  # noqa

from conftest import rewrite_bag  # noqa: E402

START = 1_700_000_000_000_000_000
FRAMES = 2
CPU = Config({"backend": "cpu"})


@pytest.fixture(scope="module")
def drive():
    """Two frames of the driving sequence (640x360): scenes and their rectified renders."""
    scenes = [replace(scene, supersample=1) for scene in drive_scenes(frames=FRAMES)]
    return scenes, [render(scene) for scene in scenes]


@pytest.fixture(scope="module")
def raw_drives(drive):
    """The same frames as each lens model's raw camera takes them: model -> (camera,
    samples with the raw images)."""
    scenes, samples = drive
    out = {}
    for model in ("plumb_bob", "rational_polynomial", "equidistant"):
        camera = raw_camera(samples[0].calibration, 640, 360, model, seed=5)
        raw = [render_raw(scene, camera) for scene in scenes]
        out[model] = camera, [replace(sample, left=left, right=right)
                              for sample, (left, right) in zip(samples, raw)]
    return out


def _labels_f(out, namespace, samples):
    """Pooled pixel F of the labels `process` wrote against the samples' ground truth."""
    found = {stamp: decode_raw(msg, ("mono16",)) for _, stamp, msg in
             bags.read_messages(out, [f"{namespace}/pothole_labels"])}
    assert len(found) == len(samples)
    tp = fp = fn = 0
    for stamp, sample in zip(sorted(found), samples):
        ours, truth = found[stamp] > 0, sample.labels > 0
        tp += int((ours & truth).sum())
        fp += int((ours & ~truth).sum())
        fn += int((~ours & truth).sum())
    return 2 * tp / max(2 * tp + fp + fn, 1)


def _process(folder, name, samples, form=RecordingForm(), config=CPU):
    bag = folder / name
    frames = [(START + i * 100_000_000, sample) for i, sample in enumerate(samples)]
    assert write_stereo_bag(bag, frames, ground_truth=False, form=form) == len(samples)
    summary = bagtools.process(bag, folder / f"{name}_out", config, keep_inputs=False)
    return summary, folder / f"{name}_out"


@pytest.fixture(scope="module")
def reference_f(drive, tmp_path_factory):
    """Pixel F of the drive stored rectified and uncompressed (mono8, our own layout)."""
    summary, out = _process(tmp_path_factory.mktemp("reference"), "rectified", drive[1])
    assert (summary.frames, summary.failed) == (FRAMES, 0)
    f = _labels_f(out, "/stereo", drive[1])
    assert f > 0.8
    return f


def _topics(left, right, left_info, right_info, compressed=False):
    return StereoTopics(left, right, left_info, right_info,
                        COMPRESSED_TYPE if compressed else IMAGE_TYPE)


ZED = _topics("/zed/zed_node/left/image_rect_color/compressed",
              "/zed/zed_node/right/image_rect_color/compressed",
              "/zed/zed_node/left/camera_info", "/zed/zed_node/right/camera_info", True)
REALSENSE = _topics("/camera/infra1/image_rect_raw", "/camera/infra2/image_rect_raw",
                    "/camera/infra1/camera_info", "/camera/infra2/camera_info")
OAK = _topics("/oak/left/image_raw", "/oak/right/image_raw", "/oak/left/camera_info",
              "/oak/right/camera_info")
KALIBR = _topics("/cam0/image_raw/compressed", "/cam1/image_raw/compressed",
                 "/cam0/camera_info", "/cam1/camera_info", True)
CAMERA_LEFT = _topics("/camera_left/image_raw", "/camera_right/image_raw",
                      "/camera_left/camera_info", "/camera_right/camera_info")


@pytest.mark.parametrize("name, form", [
    ("jpeg", RecordingForm(topics=ZED, compression="jpeg")),
    ("png", RecordingForm(compression="png")),
    ("bayer", RecordingForm(topics=REALSENSE, encoding="bayer_rggb8")),
    ("yuv422", RecordingForm(encoding="yuv422")),
    ("yuy2", RecordingForm(encoding="yuv422_yuy2")),
])
def test_rectified_forms_need_no_flags_and_keep_the_labels(tmp_path, drive, reference_f, name,
                                                           form):
    summary, out = _process(tmp_path, name, drive[1], form)
    assert (summary.frames, summary.failed) == (FRAMES, 0)
    namespace = (form.topics.namespace if form.topics else "/stereo")
    assert abs(_labels_f(out, namespace, drive[1]) - reference_f) <= 0.05


@pytest.mark.parametrize("model, topics, compression", [
    ("plumb_bob", OAK, None), ("rational_polynomial", CAMERA_LEFT, None),
    ("equidistant", KALIBR, "jpeg")])
def test_raw_forms_are_rectified_and_keep_the_labels(tmp_path, raw_drives, drive, reference_f,
                                                     model, topics, compression):
    camera, samples = raw_drives[model]
    form = RecordingForm(topics=topics, compression=compression, camera=camera)
    summary, out = _process(tmp_path, model, samples, form)
    assert (summary.frames, summary.failed) == (FRAMES, 0)
    f = _labels_f(out, topics.namespace, drive[1])
    assert abs(f - reference_f) <= 0.05, (f, reference_f)
    unrectified, out = _process(tmp_path, f"{model}_off", samples, form,
                                CPU.replace(rectify="off"))
    assert unrectified.frames == 0 or _labels_f(out, topics.namespace, drive[1]) < f - 0.1


def test_a_camera_info_without_the_baseline_fails_every_frame_until_one_is_given(
        tmp_path, drive, reference_f):
    form = RecordingForm(no_baseline=True)
    summary, _ = _process(tmp_path, "tx0", drive[1], form)
    assert (summary.frames, summary.failed) == (0, FRAMES)
    [(count, reason, _)] = summary.failures.rows()
    assert count == FRAMES and "--baseline" in reason and "baseline_m" in reason
    summary, out = _process(tmp_path, "tx0_given", drive[1], form,
                            CPU.replace(baseline_m=drive[1][0].calibration.baseline))
    assert (summary.frames, summary.failed) == (FRAMES, 0)
    assert abs(_labels_f(out, "/stereo", drive[1]) - reference_f) < 1e-9


def test_images_that_disagree_with_their_camera_info_fail_alone(tmp_path, drive):
    calibration = drive[1][0].calibration
    f, cx, cy, tx = calibration.f, calibration.cx, calibration.cy, -calibration.fb
    views = [CameraModel(640, 360, "plumb_bob", (), (f, 0, cx, 0, f, cy, 0, 0, 1),
                         (1, 0, 0, 0, 1, 0, 0, 0, 1), (f, 0, cx, x, 0, f, cy, 0, 0, 0, 1, 0))
             for x in (0.0, tx)]
    narrow = [replace(sample, left=sample.left[:, :320], right=sample.right[:, :320])
              if index == 0 else sample for index, sample in enumerate(drive[1])]
    summary, _ = _process(tmp_path, "mixed", narrow, RecordingForm(camera=StereoCamera(*views)))
    assert (summary.frames, summary.failed) == (FRAMES - 1, 1)
    assert "image is 320x360 but its camera_info is for 640x360" in summary.failures.rows()[0][1]


def test_corrupt_messages_are_skipped_and_counted(tmp_path, drive):
    source = tmp_path / "source"
    frames = [(START + i * 100_000_000, s) for i, s in enumerate(drive[1])]
    write_stereo_bag(source, frames, ground_truth=False,
                              form=RecordingForm(compression="jpeg"))
    first_left = []

    def corrupt(topic, index, data):
        if topic.endswith("left/image_rect/compressed") and not first_left:
            first_left.append(index)
            return data[:40]  # a CDR message cut short
        return data

    rewrite_bag(source, tmp_path / "corrupt", payload=corrupt)
    summary = bagtools.process(tmp_path / "corrupt", tmp_path / "out", CPU, keep_inputs=False)
    assert summary.counts.corrupt == 1 and "corrupt" in summary.counts.last_problem
    assert summary.frames == FRAMES - 1 and summary.unpaired == 1


def test_a_bag_cut_off_mid_chunk_keeps_the_frames_before_the_cut(tmp_path, drive, caplog):
    """An mcap recording cut off two thirds of the way, mid-chunk and before its footer: the
    frames of the chunks before the cut are processed from a repaired copy, with a warning
    that says so; a cut-off sqlite3 bag is refused with one line."""
    samples = drive[1] * 6
    frames = [(START + i * 100_000_000, s) for i, s in enumerate(samples)]
    for storage in ("mcap", "sqlite3"):
        source = tmp_path / f"source_{storage}"
        write_stereo_bag(source, frames, ground_truth=False, storage=storage,
                                  form=RecordingForm(compression="png"))
        cut = tmp_path / f"cut_{storage}"
        cut.mkdir()
        for file in source.iterdir():
            data = file.read_bytes()
            if file.suffix in (".mcap", ".db3"):
                data = data[:len(data) * 2 // 3]
            (cut / file.name).write_bytes(data)
        if storage == "sqlite3":
            with pytest.raises(InputError, match="not a bag that can be read"):
                bagtools.process(cut, tmp_path / f"out_{storage}", CPU, keep_inputs=False)
            continue
        with caplog.at_level("WARNING"):
            summary = bagtools.process(cut, tmp_path / f"out_{storage}", CPU,
                                       keep_inputs=False)
        assert 0 < summary.frames < len(samples) and summary.failed == 0
        assert "is cut off (its recording was interrupted)" in caplog.text
        again = bags.open_bag(cut)  # the repaired copy is made once
        try:
            assert bags.message_count(again, "/stereo/left/image_rect/compressed") >= \
                summary.frames
        finally:
            again.close()


def _is_open(reader):
    """Whether ``reader`` is open (a closed AnyReader holds no connections)."""
    return bool(reader.connections)


def test_readers_are_kept_for_the_next_read_of_the_same_bag(tmp_path, drive):
    """Opening a bag reads its whole index, so this process keeps the readers it gave back:
    a reader taken is its taker's alone, the read threads give theirs back, a bag written
    anew at the same path is opened anew, a reader whose read raised is closed, and only the
    most recently read bags keep readers."""
    source = tmp_path / "source"
    frames = [(START + i * 100_000_000, s) for i, s in enumerate(drive[1] * 3)]
    write_stereo_bag(source, frames, ground_truth=False)
    topics = StereoTopics("/stereo/left/image_rect", "/stereo/right/image_rect",
                          "/stereo/left/camera_info", "/stereo/right/camera_info")
    with bags.reading(source) as first, bags.reading(source) as second:
        assert first is not second
    with bags.reading(source) as again:
        assert again in (first, second)
        assert len(list(bags.read_sets_ahead(again, topics, CPU, None, 2))) == len(frames)
    assert bags.READERS.idle(source) >= 2
    with pytest.raises(RuntimeError), bags.reading(source) as failing:
        raise RuntimeError("a read that fails")
    assert not _is_open(failing)

    shutil.rmtree(source)
    write_stereo_bag(source, frames[:1], ground_truth=False)
    with bags.reading(source) as anew:
        assert anew not in (first, second) and not _is_open(first) and not _is_open(second)
        assert bags.message_count(anew, topics.left) == 1

    pool = bags.ReaderPool(per_bag=1, bags=1)
    other = tmp_path / "other"
    write_stereo_bag(other, frames[:1], ground_truth=False)
    kept, identity = pool.take(source)
    extra, _ = pool.take(source)
    pool.give(source, kept, identity)
    pool.give(source, extra, identity)
    assert pool.idle(source) == 1 and _is_open(kept) and not _is_open(extra)
    pool.give(other, *pool.take(other))
    assert pool.idle(source) == 0 and not _is_open(kept) and pool.idle(other) == 1
    pool.clear()
    assert pool.idle(other) == 0


def test_sets_in_one_pass_by_span_and_in_threads(tmp_path, drive):
    samples = drive[1] * 5
    source = tmp_path / "source"
    frames = [(START + i * 100_000_000, s) for i, s in enumerate(samples)]
    write_stereo_bag(source, frames, ground_truth=False)
    topics = StereoTopics("/stereo/left/image_rect", "/stereo/right/image_rect",
                          "/stereo/left/camera_info", "/stereo/right/camera_info")
    reader = bags.open_bag(source)
    try:
        whole = [s[0] for s in bags.stereo_sets(reader, topics, CPU, bags.SetCounts())]
        assert whole == [stamp for stamp, _ in frames]
        ahead = [s[0] for s in bags.read_sets_ahead(reader, topics, CPU, None, 3)]
        assert ahead == whole
        left, right, camera, colour = bags.convert_set(
            topics, *next(iter(bags.stereo_sets(reader, topics, CPU, bags.SetCounts())))[2:],
            CPU, colour=True)
        assert left.shape == (360, 640) and not camera.needs_rectification()
        np.testing.assert_array_equal(colour, samples[0].left)
        assert camera.calibration().baseline == pytest.approx(samples[0].calibration.baseline)
    finally:
        reader.close()
    with pytest.raises(InputError, match="does not exist"):
        bags.open_bag(tmp_path / "nope")
    np.testing.assert_array_equal(
        bags.left_view_at(source, topics, frames[1][0], CPU), samples[1].left)


def test_a_span_is_read_in_blocks_that_start_short(tmp_path, drive, monkeypatch):
    """The first blocks of a reading are short and each twice the one before, up to
    READ_BLOCK_FRAMES, so that the first set comes after a few sets' reading; the blocks
    cover the span edge to edge and the sets read ahead in them are the bag's."""
    monkeypatch.setattr(bags, "FIRST_READ_BLOCK_FRAMES", 1)
    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 4)
    source = tmp_path / "source"
    frames = [(START + i * 100_000_000, s) for i, s in enumerate(drive[1] * 8)]
    write_stereo_bag(source, frames, ground_truth=False)
    topics = StereoTopics("/stereo/left/image_rect", "/stereo/right/image_rect",
                          "/stereo/left/camera_info", "/stereo/right/camera_info")
    with bags.reading(source) as reader:
        span = bags.LogSpan(reader.start_time + 150_000_000, reader.end_time + 1, 250_000_000)
        blocks, period_ns = bags.read_blocks(reader, topics, CPU, span)
        assert period_ns == pytest.approx(100_000_000, rel=0.01)
        lengths = [(block.stop_ns - block.start_ns) / period_ns for block in blocks]
        assert lengths[:-1] == pytest.approx([1, 2, 4, 4][:len(lengths) - 1], abs=0.01)
        assert 0 < lengths[-1] <= 4.01
        assert blocks[0].start_ns == span.start_ns and blocks[-1].stop_ns == span.stop_ns
        assert all(a.stop_ns == b.start_ns for a, b in zip(blocks, blocks[1:]))
        assert blocks[0].lead_ns >= span.lead_ns
        ahead = [s[0] for s in bags.read_sets_ahead(reader, topics, CPU, span, 3)]
        alone = [s[0] for s in bags.stereo_sets(reader, topics, CPU, bags.SetCounts(), span)]
    assert ahead == alone and ahead[0] < span.start_ns and len(ahead) >= 14
