from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.backend import (CPU, StageClock, UploadBuffer, gather, get_backend,
                                      gpu_available, lookup, to_host)
from pothole_detector.errors import BackendError


def test_cpu_backend_is_numpy():
    backend = get_backend("cpu")
    assert backend is CPU and backend.xp is np and not backend.is_gpu
    array = np.arange(4)
    assert backend.upload(array) is not None and to_host(array) is array


def test_reads_on_the_cpu_take_the_arrays_as_they_are():
    """On the CPU there is no device event to wait for: to_host hands the array itself, and
    gather picks flat indices, directly or through a label image."""
    values = np.arange(12.0).reshape(3, 4)
    labels = np.array([[0, 1, 1, 2]] * 3)
    assert CPU.record_event() is None
    assert to_host(values, after=CPU.record_event()) is values
    np.testing.assert_array_equal(gather(values, np.array([5, 0, 11])), [5.0, 0.0, 11.0])
    np.testing.assert_array_equal(gather(np.array([10, 20, 30]), np.array([3, 1]),
                                         through=labels), [30, 20])


def test_lookup_gives_each_label_its_table_entry_in_the_labels_shape():
    table = np.array([True, False, True])
    labels = np.array([[0, 1, 1, 2], [2, 2, 0, 1], [1, 0, 0, 0]], dtype=np.int32)
    np.testing.assert_array_equal(lookup(table, labels),
                                  [[True, False, False, True], [True, True, True, False],
                                   [False, True, True, True]])
    window = lookup(table, labels[1:, ::2])
    assert window.dtype == np.bool_ and window.shape == (2, 2)
    np.testing.assert_array_equal(window, [[True, True], [False, True]])


def test_side_stream_on_the_cpu_runs_the_block_and_joins_as_a_no_op():
    done = []
    with CPU.side_stream() as join:
        done.append(np.arange(3).sum())
    assert join() is None and done == [3]


def test_stage_clock_keeps_its_timings_when_read_again():
    clock = StageClock(CPU)
    with clock.stage("a"):
        pass
    first = clock.timings()
    with clock.stage("b"):
        pass
    again = clock.timings()
    assert set(first) == {"a"} and again["a"] == first["a"] and set(again) == {"a", "b"}


def test_upload_buffer_lays_arrays_out_on_16_byte_boundaries_and_hands_them_over_on_cpu():
    buffer = UploadBuffer(CPU, [((3, 5), np.uint8), ((7,), np.int32), ((2, 3), np.float32)])
    views = buffer.writable()
    assert [v.shape for v in views] == [(3, 5), (7,), (2, 3)]
    assert [v.dtype for v in views] == [np.uint8, np.int32, np.float32]
    starts = [v.__array_interface__["data"][0] - views[0].__array_interface__["data"][0]
              for v in views]
    assert starts == [0, 16, 48]
    assert [buffer.shape(i) for i in range(3)] == [(3, 5), (7,), (2, 3)]
    assert all(a is b for a, b in zip(buffer.writable(1), views[1:]))
    views[1][...] = np.arange(7)
    uploaded = buffer.upload()
    assert all(a is b for a, b in zip(uploaded, views))
    np.testing.assert_array_equal(uploaded[1], np.arange(7))


def test_unknown_backend_is_refused():
    with pytest.raises(BackendError, match="unknown backend"):
        get_backend("tpu")


def test_auto_falls_back_to_cpu_without_a_gpu():
    backend = get_backend("auto")
    assert backend.is_gpu == gpu_available()


def test_copy_is_a_new_contiguous_array_of_the_same_values():
    source = np.arange(24, dtype=np.float32).reshape(4, 6)[:, ::2]
    copied = CPU.copy(source)
    assert copied.flags.c_contiguous and not np.shares_memory(copied, source)
    np.testing.assert_array_equal(copied, source)
    assert copied.dtype == source.dtype


@pytest.mark.skipif(gpu_available(), reason="a GPU is present")
def test_gpu_request_without_a_gpu_says_what_to_do():
    with pytest.raises(BackendError, match="--backend cpu"):
        get_backend("gpu")


def test_kernel_sources_carry_their_headers_and_the_digest_covers_them(tmp_path, monkeypatch):
    import pothole_detector.backend as backend_module
    for source in ("road.cu", "threshold.cu", "components.cu"):
        text = backend_module._source_text(source)
        assert '#include "' not in text and "block_inclusive_scan(T value" in text
    for source in ("road.cu", "local_road.cu", "photometric.cu"):
        assert "void grid_barrier(unsigned* arrivals" in backend_module._source_text(source)
    (tmp_path / "part.cuh").write_text("#define PART 1\n")
    (tmp_path / "main.cu").write_text('// top\n#include "part.cuh"\nint x = PART;\n')
    monkeypatch.setattr(backend_module, "KERNEL_DIR", tmp_path)
    backend_module._source_text.cache_clear()
    backend_module._source_digest.cache_clear()
    try:
        expected = "// top\n#define PART 1\n\nint x = PART;\n"
        assert backend_module._source_text("main.cu") == expected
        before = backend_module._source_digest("main.cu")
        (tmp_path / "part.cuh").write_text("#define PART 2\n")
        backend_module._source_text.cache_clear()
        backend_module._source_digest.cache_clear()
        assert backend_module._source_digest("main.cu") != before
    finally:
        backend_module._source_text.cache_clear()
        backend_module._source_digest.cache_clear()


def test_defines_are_in_the_kernel_text_so_every_module_has_the_same_options():
    import pothole_detector.backend as backend_module
    built = backend_module._built_text("threshold.cu", (("BINS", 64), ("RUN", 16)))
    assert built == "#define BINS 64\n#define RUN 16\n" + backend_module._source_text(
        "threshold.cu")
    assert backend_module._built_text("threshold.cu", ()) == backend_module._source_text(
        "threshold.cu")
    assert not any(option.startswith("-D") for option in backend_module.NVRTC_OPTIONS)
