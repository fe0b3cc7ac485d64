"""execution.py: the frame report and the CUDA graph bookkeeping (the executor running frames:
test_pipeline.py; on a GPU: test_gpu.py)."""

from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU, Readback
from pothole_detector.execution import FrameGraphs, FrameReport
from pothole_detector.stages.measure import MEASURE_SUMS


def test_frame_report_views_share_one_buffer_and_read_back_whole():
    report = FrameReport(np, capacity=5)
    report.road[:] = np.arange(15)
    report.road_params[:] = -1.0
    report.threshold[:] = (1.0, 7.0, 32.5)
    report.valid_count[...] = 1234
    report.components[:] = (9, 3, 1)
    report.kept_after_area[...] = 2
    assert int(report.components_kept[0]) == 3
    report.sums[:] = np.arange(6 * MEASURE_SUMS).reshape(6, MEASURE_SUMS)
    report.extremes[:] = np.arange(30).reshape(6, 5)
    readback = Readback(CPU, report.buffer.nbytes + 64)
    readback.send(report.buffer)
    report.buffer[:] = 0  # the readback holds the bytes sent
    host = report.parse(readback.receive())
    assert list(FrameReport.road_of(host.header)) == list(range(15))
    assert FrameReport.valid_count_of(host.header) == 1234
    assert list(host.header[15:26]) == [-1.0] * 11
    report.road_params[:] = 2.0
    assert list(report.read_header()[15:26]) == [2.0] * 11
    assert list(host.threshold) == [1.0, 7.0, 32.5]
    assert (host.components_kept, host.overflow) == (3, True)
    np.testing.assert_array_equal(host.sums, np.arange(6 * MEASURE_SUMS).reshape(6, MEASURE_SUMS))
    np.testing.assert_array_equal(host.extremes, np.arange(30).reshape(6, 5))


def test_frame_graphs_capture_a_key_on_its_second_frame_and_drop_stale_ones():
    """FrameGraphs' bookkeeping (the capture itself needs a GPU: test_gpu.py)."""
    captured: list[tuple[int, int, int, int]] = []

    def capture(key):
        captured.append(key)
        return f"graph {key}"

    graphs = FrameGraphs()

    def two_frames(key, generation):
        assert graphs.get(key, generation, capture) is None  # the key's first frame
        graphs.ran(key, generation)
        assert graphs.get(key, generation, capture) == f"graph {key}"
        return graphs.keys()

    small, other_levels, large = (192, 320, 48, 8), (192, 320, 64, 8), (160, 288, 48, 8)
    assert two_frames(small, 1) == {small}
    assert graphs.get(small, 1, capture) == "graph (192, 320, 48, 8)" and captured == [small]
    assert two_frames(other_levels, 1) == {small, other_levels}
    # the matcher replaced its buffers (more levels): every graph is stale
    assert two_frames(other_levels, 2) == {other_levels}
    assert two_frames(small, 2) == {small, other_levels}
    # another image size: the graphs of the old one go
    assert two_frames(large, 2) == {large}
    assert captured == [small, other_levels, other_levels, small, large]


def test_frame_graphs_run_without_graphs_after_a_failed_capture(caplog):
    calls = []

    def failing(key):
        calls.append(key)
        raise RuntimeError("operation not permitted when stream is capturing")

    graphs = FrameGraphs()
    key = (192, 320, 48, 8)
    graphs.ran(key, 1)
    with caplog.at_level("WARNING"):
        assert graphs.get(key, 1, failing) is None
    assert "running without graphs" in caplog.text and "not permitted" in caplog.text
    assert graphs.get(key, 1, failing) is None and calls == [key] and graphs.failed
