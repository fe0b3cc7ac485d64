"""The one switch between NumPy (CPU) and CuPy (GPU).

This is the only module that imports CuPy. Stages receive an array module ``xp`` and return
arrays of the same kind as their inputs.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import math
import re
import time
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from types import ModuleType
from typing import Any, Callable, Generic, Iterator, Sequence, TypeVar
from weakref import WeakSet

import numpy as np
import scipy.ndimage

from .errors import BackendError

try:
    import cupy as _cupy
    import cupyx.scipy.ndimage as _cupy_ndimage
except Exception:  # noqa: BLE001 - any import failure means "no GPU backend"
    _cupy = None
    _cupy_ndimage = None

_log = logging.getLogger(__name__)
_T = TypeVar("_T")
BACKEND_CHOICES = ("auto", "cpu", "gpu")
KERNEL_DIR = Path(__file__).resolve().parent / "kernels"
_INCLUDE = re.compile(r'^#include "([A-Za-z0-9_]+\.cuh)"$', re.MULTILINE)


@dataclass(frozen=True)
class Backend:
    """An array backend: ``xp`` is numpy or cupy, ``ndimage`` the matching scipy.ndimage."""

    name: str
    xp: ModuleType
    ndimage: ModuleType

    @property
    def is_gpu(self) -> bool:
        return self.name == "gpu"

    def upload(self, array: np.ndarray) -> Any:
        """Copy a host array to the backend (no copy on the CPU backend)."""
        return self.xp.asarray(array)

    def to_host(self, array: Any) -> np.ndarray:
        """Copy a backend array to a NumPy array (no copy on the CPU backend)."""
        return to_host(array)

    def upload_many(self, *arrays: np.ndarray) -> tuple[Any, ...]:
        """Copy several host arrays into one device buffer; returns one array each (views into
        that buffer on the GPU). Each array is copied straight from its host memory, through
        the driver's pipelined staging."""
        if not self.is_gpu:
            return arrays
        sizes = [a.nbytes for a in arrays]
        offsets = _packed_offsets(sizes)
        device = self.xp.empty(offsets[-1], dtype=np.uint8)
        stream = self.xp.cuda.get_current_stream()
        for array, start, size in zip(arrays, offsets, sizes):
            device[start:start + size].set(
                np.ascontiguousarray(array).reshape(-1).view(np.uint8), stream=stream)
        return tuple(device[start:start + size].view(a.dtype).reshape(a.shape)
                     for a, start, size in zip(arrays, offsets, sizes))

    def kernel(self, source: str, name: str, defines: dict[str, int],
               cooperative: bool = False) -> Any:
        """The CUDA kernel ``name`` of kernels/``source`` built with ``defines`` (memoized on
        the source text, the defines and ``cooperative``: launched so that every block is
        resident at once, for kernels with grid-wide barriers). GPU backend only."""
        if not self.is_gpu:
            raise BackendError(f"kernel {name} needs the gpu backend")
        return _kernel(source, _source_digest(source), tuple(sorted(defines.items())), name,
                       cooperative)

    def multiprocessors(self) -> int:
        """Streaming multiprocessors of the current device (GPU backend only)."""
        assert _cupy is not None
        return _multiprocessors(_cupy.cuda.Device().id)

    def resident_threads(self) -> int:
        """Threads the current device holds at once: multiprocessors times the threads one
        multiprocessor holds (GPU backend only)."""
        assert _cupy is not None
        return _resident_threads(_cupy.cuda.Device().id)

    def memory_bytes(self) -> int:
        """Device memory held by the backend's allocator and by the live GraphMemory pools
        (bytes; 0 on the CPU backend)."""
        if not self.is_gpu:
            return 0
        return int(self.xp.get_default_memory_pool().total_bytes()) \
            + sum(memory.total_bytes() for memory in _GRAPH_MEMORIES)

    def release_memory(self) -> None:
        """Give the allocator's unused device blocks back to the driver (no-op on the CPU).
        GraphMemory pools keep theirs: their graphs replay into them."""
        if self.is_gpu:
            self.xp.get_default_memory_pool().free_all_blocks()

    def record_event(self) -> Any:
        """A device event recorded on the current stream, reached once everything queued there
        so far has run (None on the CPU backend): the ``after`` of :func:`to_host` and
        :func:`gather`."""
        if not self.is_gpu:
            return None
        assert _cupy is not None
        event = _cupy.cuda.Event(disable_timing=True)
        event.record()
        return event

    def copy_into(self, target: Any, source: Any) -> None:
        """Copy the backend array ``source`` into the contiguous backend array ``target`` of
        the same shape and dtype; on the GPU one transfer queued on the current stream."""
        if target.shape != source.shape or target.dtype != source.dtype:
            raise BackendError(f"cannot copy {source.dtype} {source.shape} into "
                               f"{target.dtype} {target.shape}")
        if not self.is_gpu:
            np.copyto(target, source)
            return
        assert _cupy is not None
        target.data.copy_from_device_async(_cupy.ascontiguousarray(source).data,
                                           source.nbytes, stream=_cupy.cuda.get_current_stream())

    def copy(self, source: Any) -> Any:
        """A new contiguous copy of the backend array ``source``; on the GPU one device-to-device
        transfer queued on the current stream."""
        target = self.xp.empty(source.shape, dtype=source.dtype)
        self.copy_into(target, source)
        return target

    def capture(self, body: Callable[[Callable[[], None]], _T],
                memory: GraphMemory) -> CapturedGraph[_T]:
        """The device work ``body`` queues, captured as CUDA graphs and not run (GPU backend
        only): ``body(cut)`` may call ``cut()`` to end one graph and start the next, and
        :meth:`CapturedGraph.launch` replays graph i on the current stream. ``body`` queues
        on the current stream (and on side streams joined back to it before a cut) and must
        not read back, upload from host memory or wait for the device; every array it
        allocates comes from ``memory``, and what it returns stays alive with the graphs (a
        replay writes into those arrays again). Kernels it launches should have been built
        before (run the work once without capture first)."""
        if not self.is_gpu:
            raise BackendError("graph capture needs the gpu backend")
        assert _cupy is not None
        stream = _stream(_cupy.cuda.Device().id, "capture")
        graphs: list[Any] = []

        def cut() -> None:
            graphs.append(stream.end_capture())
            stream.begin_capture()

        with _cupy.cuda.using_allocator(memory.allocate), stream:
            stream.begin_capture()
            try:
                outputs = body(cut)
            except BaseException:
                with suppress(Exception):  # the body's error says more than the end's
                    stream.end_capture()
                raise
            graphs.append(stream.end_capture())
        return CapturedGraph(graphs, outputs, memory)

    @contextmanager
    def side_stream(self) -> Iterator[Callable[[], None]]:
        """Work queued inside the block runs on a second device stream, after everything
        queued so far, so that it overlaps what the current stream queues next. Yields
        ``join``: called after the block, the current stream's later work waits for the
        side work. On the CPU the block simply runs and ``join`` does nothing."""
        if not self.is_gpu:
            yield lambda: None
            return
        assert _cupy is not None
        main = _cupy.cuda.get_current_stream()
        started = _cupy.cuda.Event(disable_timing=True)
        started.record(main)
        side = _stream(_cupy.cuda.Device().id, "side")
        side.wait_event(started)
        finished = _cupy.cuda.Event(disable_timing=True)
        try:
            with side:
                yield lambda: main.wait_event(finished)
        finally:
            finished.record(side)

    def synchronize(self) -> None:
        """Wait for queued device work (no-op on the CPU backend), e.g. before reading a clock."""
        if self.is_gpu:
            self.xp.cuda.get_current_stream().synchronize()


class GraphMemory:
    """Device memory for captured graphs (GPU backend): a memory pool of its own that only
    :meth:`Backend.capture` allocates from, so nothing outside a graph is ever handed memory a
    graph replays into. Graphs captured into one GraphMemory may share the memory each freed
    during its capture, so they must never run at the same time (replay them on one stream)."""

    def __init__(self) -> None:
        assert _cupy is not None
        self._pool = _cupy.cuda.MemoryPool()
        _GRAPH_MEMORIES.add(self)

    def allocate(self, nbytes: int) -> Any:
        return self._pool.malloc(nbytes)

    def total_bytes(self) -> int:
        """Device memory the pool holds (bytes)."""
        return int(self._pool.total_bytes())


_GRAPH_MEMORIES: WeakSet[GraphMemory] = WeakSet()


@dataclass
class CapturedGraph(Generic[_T]):
    """The CUDA graphs from :meth:`Backend.capture` (one more than the body's cuts) and what
    its body returned (``outputs``: the arrays every replay writes into), kept alive together
    with the memory they came from."""

    graphs: list[Any]
    outputs: _T
    memory: GraphMemory

    def launch(self, index: int = 0) -> None:
        """Queue one replay of graph ``index`` on the current stream."""
        assert _cupy is not None
        self.graphs[index].launch(stream=_cupy.cuda.get_current_stream())


class Readback:
    """Device bytes copied into page-locked host memory by an asynchronous transfer (on the CPU
    backend a plain copy): :meth:`send` queues the copy on the current stream, :meth:`receive`
    waits for it. The host memory is reused: receive a send's bytes before the next send."""

    def __init__(self, backend: Backend, nbytes: int) -> None:
        self._gpu = backend.is_gpu
        if self._gpu:
            assert _cupy is not None
            self._host = _cupy_pinned(nbytes)
            self._event = _cupy.cuda.Event(disable_timing=True)
        else:
            self._host = np.empty(nbytes, np.uint8)
        self._count = 0

    @property
    def nbytes(self) -> int:
        return int(self._host.size)

    def send(self, source: Any) -> None:
        """Queue the copy of ``source``, a contiguous uint8 backend array of at most
        ``nbytes``."""
        count = int(source.size)
        if count > self._host.size:
            raise BackendError(f"{count} bytes do not fit a readback of {self._host.size}")
        if self._gpu:
            assert _cupy is not None
            stream = _cupy.cuda.get_current_stream()
            source.data.copy_to_host_async(ctypes.c_void_p(self._host.ctypes.data), count,
                                           stream=stream)
            self._event.record(stream)
        else:
            self._host[:count] = source
        self._count = count

    def receive(self) -> np.ndarray:
        """A host copy of the last send's bytes (uint8), once its transfer is done (waits)."""
        if self._gpu:
            self._event.synchronize()
        return self._host[:self._count].copy()


class UploadBuffer:
    """Host memory for one frame's upload: several arrays back to back (each starting on a
    16-byte boundary) in one buffer, page-locked on the GPU backend and copied by asynchronous
    transfers into a device buffer of the same layout that the object keeps, so that the host
    can fill it, and part of it can go up, while the device still works on the frame before.
    Each upload overwrites the device arrays of the one before. ``layout``: (shape, dtype) of
    each array."""

    def __init__(self, backend: Backend,
                 layout: Sequence[tuple[tuple[int, ...], np.dtype | type]]) -> None:
        self._gpu = backend.is_gpu
        self._layout = [(tuple(shape), np.dtype(dtype)) for shape, dtype in layout]
        self._offsets = _packed_offsets(
            [math.prod(shape) * dtype.itemsize for shape, dtype in self._layout])
        total = self._offsets[-1]
        if self._gpu:
            assert _cupy is not None
            self._host = _cupy_pinned(total)
            self._device = _cupy.empty(total, dtype=np.uint8)
        else:
            self._host = self._device = np.empty(total, np.uint8)
        self._views = self._carve(self._host)
        self._device_views = self._carve(self._device)
        self._sent: Any = None
        self._ahead: Any = None
        self._ahead_count = 0

    def _carve(self, buffer: Any) -> tuple[Any, ...]:
        return tuple(buffer[start:start + math.prod(shape) * dtype.itemsize].view(dtype)
                     .reshape(shape)
                     for (shape, dtype), start in zip(self._layout, self._offsets))

    def shape(self, index: int) -> tuple[int, ...]:
        """The shape of array ``index`` (no wait)."""
        return self._layout[index][0]

    def writable(self, start: int = 0) -> tuple[np.ndarray, ...]:
        """The host arrays from ``start`` on, once the transfers that read them have finished
        (it waits for them): the buffer's last upload, and the transfer sent ahead if it
        covers any of them (that one then counts as not sent). Arrays behind the ones sent
        ahead can be written while those are still on their way."""
        waits = [self._sent]
        if start < self._ahead_count:
            waits.append(self._ahead)
            self._ahead_count = 0
        for event in waits:
            if event is not None:
                event.synchronize()
        return self._views[start:]

    def send_ahead(self, count: int) -> None:
        """Queue the transfer of the first ``count`` arrays now, on a copy stream of its own, so
        that it overlaps the device's work on the frame before; :meth:`upload` then sends the
        rest and orders the current stream after both. The device arrays must no longer be in
        use by queued work. No-op on the CPU backend, and where those arrays have already been
        sent ahead since they were last written."""
        if not self._gpu or self._ahead_count >= count:
            return
        assert _cupy is not None
        end = self._offsets[count]
        stream = _stream(_cupy.cuda.Device().id, "copy")
        self._device[:end].set(self._host[:end], stream=stream)
        if self._ahead is None:
            self._ahead = _cupy.cuda.Event(disable_timing=True)
        self._ahead.record(stream)
        self._ahead_count = count

    def upload(self) -> tuple[Any, ...]:
        """The device arrays, holding the host arrays' contents once the transfer queued on the
        current stream has run (on the CPU backend the host arrays themselves). Write the host
        arrays again only through :meth:`writable`."""
        if not self._gpu:
            return self._views
        assert _cupy is not None
        stream = _cupy.cuda.get_current_stream()
        start = self._offsets[self._ahead_count]
        if self._ahead_count:
            stream.wait_event(self._ahead)
            self._ahead_count = 0
        if start < self._offsets[-1]:
            self._device[start:].set(self._host[start:], stream=stream)
        if self._sent is None:
            self._sent = _cupy.cuda.Event(disable_timing=True)
        self._sent.record(stream)
        return self._device_views


def _packed_offsets(sizes: Sequence[int]) -> list[int]:
    """Byte offsets of arrays of ``sizes`` bytes laid back to back, each starting on a 16-byte
    boundary, and the total length last."""
    offsets = [0]
    for size in sizes:
        offsets.append(offsets[-1] + -(-size // 16) * 16)
    return offsets


class StageClock:
    """Per-stage times of one frame: CUDA events on the GPU (no synchronization until
    :meth:`timings`), wall clock on the CPU; with ``timed`` False it records nothing (work
    being captured into a graph cannot be timed)."""

    def __init__(self, backend: Backend, timed: bool = True) -> None:
        self._gpu = backend.is_gpu
        self._timed = timed
        self._marks: list[tuple[str, Any, Any]] = []
        self._read: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if not self._timed:
            yield
        elif self._gpu:
            start = _timing_event()
            start.record()
            try:
                yield
            finally:
                end = _timing_event()
                end.record()
                self._marks.append((name, start, end))
        else:
            begin = time.perf_counter()
            try:
                yield
            finally:
                self._marks.append((name, begin, time.perf_counter()))

    def timings(self) -> dict[str, float]:
        """Stage name -> ms (a stage entered twice adds up, a stage entered after an earlier
        call adds to it); waits for the device."""
        result = self._read
        for name, start, end in self._marks:
            if self._gpu:
                assert _cupy is not None
                end.synchronize()
                elapsed = _cupy.cuda.get_elapsed_time(start, end)
            else:
                elapsed = (end - start) * 1e3
            result[name] = result.get(name, 0.0) + elapsed
        if self._gpu:
            # both events of every mark have completed: they serve the next frames' clocks
            _spare_events(_cupy.cuda.Device().id).extend(
                event for _, start, end in self._marks for event in (start, end))
        self._marks.clear()
        return dict(result)


@lru_cache(maxsize=None)
def _spare_events(device: int) -> list[Any]:
    return []


def _timing_event() -> Any:
    """A CUDA event for StageClock: a read one again where there is one (creating events is
    a few microseconds each, sixteen per frame)."""
    assert _cupy is not None
    spare = _spare_events(_cupy.cuda.Device().id)
    try:
        return spare.pop()
    except IndexError:
        return _cupy.cuda.Event()


CPU = Backend("cpu", np, scipy.ndimage)


# NVRTC's options for every kernel module (the defines are in the text: _built_text)
NVRTC_OPTIONS = ("--std=c++17",)


@lru_cache(maxsize=None)
def _source_text(source: str) -> str:
    """kernels/``source`` with each ``#include "name.cuh"`` line replaced by that header from
    kernels/ (one level), read once per process: NVRTC and CuPy's compile cache then see
    every line the kernel is built from."""
    return _INCLUDE.sub(lambda match: (KERNEL_DIR / match.group(1)).read_text(),
                        (KERNEL_DIR / source).read_text())


@lru_cache(maxsize=None)
def _source_digest(source: str) -> str:
    """sha1 of kernels/``source`` with its headers (see _source_text)."""
    return hashlib.sha1(_source_text(source).encode()).hexdigest()


def _built_text(source: str, defines: tuple[tuple[str, int], ...]) -> str:
    """The text NVRTC builds for kernels/``source`` with ``defines``: a ``#define`` line each,
    then the source with its headers (_source_text). The defines go into the text rather than
    into NVRTC's options, so that every module has the same options (NVRTC_OPTIONS): CuPy
    compiles an empty program once a process for each distinct set of options (part of its
    compile cache's key), which a fresh process's first frame would pay per module."""
    return "".join(f"#define {key} {value}\n" for key, value in defines) + _source_text(source)


@lru_cache(maxsize=64)
def _module(source: str, digest: str, defines: tuple[tuple[str, int], ...],
            cooperative: bool) -> Any:
    """A compiled RawModule of kernels/``source`` (digest: sha1 of its text, part of the key);
    ``cooperative``: its kernels launch cooperatively."""
    assert _cupy is not None
    return _cupy.RawModule(code=_built_text(source, defines), options=NVRTC_OPTIONS,
                           enable_cooperative_groups=cooperative)


@lru_cache(maxsize=256)
def _kernel(source: str, digest: str, defines: tuple[tuple[str, int], ...], name: str,
            cooperative: bool) -> Any:
    """Kernel ``name`` of the module built from kernels/``source`` with ``defines``."""
    return _module(source, digest, defines, cooperative).get_function(name)


def _cupy_pinned(nbytes: int) -> np.ndarray:
    """A uint8 NumPy array of ``nbytes`` in page-locked host memory."""
    assert _cupy is not None
    memory = _cupy.cuda.alloc_pinned_memory(nbytes)
    return np.frombuffer(memory, np.uint8, nbytes)


@lru_cache(maxsize=None)
def _multiprocessors(device: int) -> int:
    assert _cupy is not None
    return int(_cupy.cuda.Device(device).attributes["MultiProcessorCount"])


@lru_cache(maxsize=None)
def _stream(device: int, role: str) -> Any:
    """The device's one extra stream for ``role`` ("side": Backend.side_stream, "copy":
    UploadBuffer.send_ahead, "capture": Backend.capture, "reading": to_host and gather after
    an event). Non-blocking: it never waits for the legacy default stream's work."""
    assert _cupy is not None
    return _cupy.cuda.Stream(non_blocking=True)


@lru_cache(maxsize=None)
def _resident_threads(device: int) -> int:
    assert _cupy is not None
    return _multiprocessors(device) * int(
        _cupy.cuda.Device(device).attributes["MaxThreadsPerMultiProcessor"])


def gpu_available() -> bool:
    """True when CuPy imports and sees at least one CUDA device."""
    if _cupy is None:
        return False
    try:
        return _cupy.cuda.runtime.getDeviceCount() > 0
    except Exception:  # noqa: BLE001 - driver missing or broken: no GPU
        return False


def get_backend(name: str = "auto") -> Backend:
    """Return the backend called ``name`` (auto, cpu or gpu).

    ``auto`` picks the GPU when CuPy sees a device, else the CPU with one log line.
    """
    if name not in BACKEND_CHOICES:
        raise BackendError(f"unknown backend {name!r}: use one of {', '.join(BACKEND_CHOICES)}")
    if name == "cpu":
        return CPU
    if gpu_available():
        return Backend("gpu", _cupy, _cupy_ndimage)
    if name == "gpu":
        raise BackendError(
            "backend 'gpu' needs CuPy and a CUDA device (pip install cupy-cuda12x or "
            "cupy-cuda13x); use --backend cpu or auto on this machine"
        )
    _log.info("no CUDA device visible to CuPy: using the CPU backend")
    return CPU


def array_module(array: Any) -> Any:
    """The module of ``array``: CuPy for a CuPy array, else NumPy."""
    return _cupy if _cupy is not None and isinstance(array, _cupy.ndarray) else np


def to_host(array: Any, after: Any = None) -> np.ndarray:
    """NumPy view or copy of a NumPy or CuPy array. ``after``: an event of
    :meth:`Backend.record_event` after which ``array`` holds its values; the copy then waits for
    that event alone, on a stream of its own, not for what the current stream queued after it
    (a stream's next frame)."""
    if array_module(array) is np:
        return np.asarray(array)
    stream = _reading_stream(after)
    with stream:
        return _cupy.ascontiguousarray(array).get(stream=stream)


def gather(array: Any, flat_index: np.ndarray, through: Any = None,
           after: Any = None) -> np.ndarray:
    """``array.ravel()[flat_index]`` as a NumPy array, ``array`` NumPy or CuPy; with
    ``through`` (an int array of the same kind), ``array[through.ravel()[flat_index]]``: a
    lookup through a label image. On the GPU the index goes up once and only the gathered
    values come back; ``after`` as in :func:`to_host`."""
    if array_module(array) is np:
        index = np.asarray(flat_index)
        if through is not None:
            index = through.ravel()[index]
        return np.asarray(array.ravel()[index])
    stream = _reading_stream(after)
    flat_index = np.ascontiguousarray(flat_index)
    with stream:
        index = _cupy.empty(flat_index.shape, dtype=flat_index.dtype)
        index.set(flat_index, stream=stream)
        if through is not None:
            index = _cupy.take(through.ravel(), index)
        return _cupy.take(array.ravel(), index).get(stream=stream)


def lookup(table: Any, labels: Any, after: Any = None) -> np.ndarray:
    """``table[labels]`` as a NumPy array of ``labels``' shape: ``table`` (N,) and the int
    ``labels`` (any shape, a view will do) both NumPy or both CuPy. On the GPU the lookup runs
    on the device and only its result comes back (a bool label image: a quarter of the bytes
    of the int32 labels); ``after`` as in :func:`to_host`."""
    if array_module(labels) is np:
        return np.take(np.asarray(table), labels)
    stream = _reading_stream(after)
    with stream:
        return _cupy.take(table, labels).get(stream=stream)


def _reading_stream(event: Any) -> Any:
    """The stream a read queues on: the device's reading stream, queued to wait for ``event``
    first; the current stream where ``event`` is None."""
    assert _cupy is not None
    if event is None:
        return _cupy.cuda.get_current_stream()
    stream = _stream(_cupy.cuda.Device().id, "reading")
    stream.wait_event(event)
    return stream
