"""How frames are executed: the method's stages (method.py) run on either backend through
one path. On the CPU every step completes when it is called; on the GPU:

- each pair is converted straight into page-locked upload buffers and sent up in one transfer
  (two buffers per image size, used in turn, so the next pair goes up while the device works);
- the stages write their small results into one device buffer, the frame report, that is read
  back asynchronously: its header (road fit, valid count) as soon as the road fit is done, for
  the checks that can refuse a frame, and the whole of it at the end;
- with ``cuda_graph``, SGM and the stages after it are captured as two CUDA graphs (cut after
  the road fit) per image size, level count and SLIC grid step and replayed: two launches
  instead of about fifty, the same results;
- in a stream, pair N + 1 is queued as soon as pair N's road fit is read back and checked
  (N + 1's band needs N's road model), behind N's later stages.
"""

from __future__ import annotations

import logging
import time
import weakref
from dataclasses import dataclass, replace
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from .backend import Backend, CapturedGraph, GraphMemory, Readback, StageClock, UploadBuffer, \
    to_host
from .errors import PotholeError
from .method import FrameArrays, Method, PipelineResult
from .stages import components, matching, measure, perspective, road_model, superpixels
from .stages import threshold as thresholding

_log = logging.getLogger(__name__)


@dataclass
class HostReport:
    """A frame report read back: its header (float64), threshold search result, observed range
    (near, far: m along the road), components
    found and kept by the component filters, whether they overflowed the report's tables, and
    the measure sums and extremes."""

    header: np.ndarray
    threshold: np.ndarray
    observed_range: np.ndarray
    components_found: int
    components_kept: int
    overflow: bool
    sums: np.ndarray
    extremes: np.ndarray


class FrameReport:
    """One backend buffer that a frame's stages write their small results into: float64 road
    fit report (ROAD) and kernel parameters, threshold search result, valid pixel count, the
    observed range (near, far, m); int32
    component counts (found, kept, overflow) and the count kept after the area filter; the
    measure sums and extremes of ``capacity`` labels. Read back in two parts: the header (what
    the checks need) and the whole buffer."""

    ROAD = (0, road_model.ROAD_REPORT)
    _PARAMS = (ROAD[1], ROAD[1] + road_model.ROAD_PARAMS)
    _THRESHOLD = (_PARAMS[1], _PARAMS[1] + 3)
    _VALID = _THRESHOLD[1]
    _OBSERVED = (_VALID + 1, _VALID + 3)
    HEADER_BYTES = 8 * _OBSERVED[1]

    def __init__(self, xp: Any, capacity: int) -> None:
        self.capacity = capacity
        self._counts_at = -(-self.HEADER_BYTES // 16) * 16
        self._sums_at = self._counts_at + 16
        self._extremes_at = self._sums_at + (capacity + 1) * measure.MEASURE_SUMS * 8
        end = self._extremes_at + (capacity + 1) * measure.MEASURE_EXTREMES * 4
        self.buffer = xp.empty(end, dtype=xp.uint8)
        header = self.buffer[:self.HEADER_BYTES].view(xp.float64)
        self.road = header[slice(*self.ROAD)]
        self.road_params = header[slice(*self._PARAMS)]
        self.threshold = header[slice(*self._THRESHOLD)]
        self.valid_count = header[self._VALID:self._VALID + 1]
        self.observed_range = header[slice(*self._OBSERVED)]
        counts = self.buffer[self._counts_at:self._sums_at].view(xp.int32)
        self.components = counts[0:3]
        self.components_kept = counts[1:2]
        self.kept_after_area = counts[3:4]
        self.sums = self.buffer[self._sums_at:self._extremes_at].view(xp.float64).reshape(
            capacity + 1, measure.MEASURE_SUMS)
        self.extremes = self.buffer[self._extremes_at:].view(xp.int32).reshape(
            capacity + 1, measure.MEASURE_EXTREMES)

    @property
    def header_bytes(self) -> Any:
        """The header (road report and parameters, threshold, valid count) as backend bytes."""
        return self.buffer[:self.HEADER_BYTES]

    def read_header(self) -> np.ndarray:
        """Host float64 copy of the header (a synchronous readback on the GPU)."""
        return to_host(self.header_bytes).view(np.float64)

    @classmethod
    def road_of(cls, header: np.ndarray) -> np.ndarray:
        return header[slice(*cls.ROAD)]

    @classmethod
    def valid_count_of(cls, header: np.ndarray) -> float:
        return float(header[cls._VALID])

    def parse(self, host: np.ndarray) -> HostReport:
        """The report from a host copy of the whole buffer (uint8)."""
        header = host[:self.HEADER_BYTES].view(np.float64)
        counts = host[self._counts_at:self._sums_at].view(np.int32)
        return HostReport(
            header=header, threshold=header[slice(*self._THRESHOLD)],
            observed_range=header[slice(*self._OBSERVED)],
            components_found=int(counts[0]), components_kept=int(counts[1]),
            overflow=bool(counts[2]),
            sums=host[self._sums_at:self._extremes_at].view(np.float64).reshape(
                self.capacity + 1, measure.MEASURE_SUMS),
            extremes=host[self._extremes_at:].view(np.int32).reshape(
                self.capacity + 1, measure.MEASURE_EXTREMES))


@dataclass
class _Frame:
    """A frame in flight: its report and arrays, its pixel count, the checked host road model
    once read back (``road``), its two
    readbacks (header, whole report), the report read back (``host``); ``replayed``: the arrays
    are still a CUDA graph's, which its next replay writes again; ``lent_ms``: of its host time,
    ms spent queueing the next frame."""

    report: FrameReport
    pixels: int
    arrays: FrameArrays | None = None
    road: road_model.RoadModel | None = None
    readbacks: tuple[Readback, Readback] | None = None
    host: HostReport | None = None
    shifts: np.ndarray | None = None
    levels: int = 0
    seeded: bool = False
    started: float = 0.0
    clock: StageClock | None = None
    wait_ms: float = 0.0
    replayed: bool = False
    lent_ms: float = 0.0
    ready: Any = None


class _Checkpoint:
    """method.Checkpoint of one frame: after the road fit queue ``after_fit(frame)`` (the
    header's readback, or the cut between two graphs); the stages then take the checked model
    (CPU) or the device parameters (GPU, checked when the header is read back)."""

    def __init__(self, executor: FrameExecutor, frame: _Frame,
                 after_fit: Callable[[_Frame], None]) -> None:
        self._executor, self._frame, self._after_fit = executor, frame, after_fit

    def road_fitted(self, report: FrameReport) -> road_model.RoadModel | Any:
        self._after_fit(self._frame)
        if self._executor.backend.is_gpu:
            return report.road_params
        return self.host_road(report)

    def host_road(self, report: FrameReport) -> road_model.RoadModel:
        frame = self._frame
        if frame.road is None:
            frame.road = self._executor.checked_road(report.read_header(), frame)
        return frame.road


_GraphKey = tuple[int, int, int, int]


class FrameGraphs:
    """CUDA graphs of the GPU frame after its upload (SGM and every stage after it), one set
    per (height, width, levels, SLIC grid step). A key's first frame runs without graphs
    (kernels built, caches filled, the matcher's buffers sized); its next frame captures them,
    and later frames replay them. The graphs hold the matcher's buffers by address: when the
    matcher replaces them (its ``generation``) or the image size changes, every graph is
    dropped and each key starts again. Where a capture fails, frames run without graphs from
    then on."""

    def __init__(self) -> None:
        self._graphs: dict[_GraphKey, CapturedGraph] = {}
        self._ran: set[_GraphKey] = set()
        self._generation = -1
        self.failed = False

    def keys(self) -> set[_GraphKey]:
        """The keys that have a graph now."""
        return set(self._graphs)

    def get(self, key: _GraphKey, generation: int,
            capture: Callable[[_GraphKey], CapturedGraph]) -> CapturedGraph | None:
        """The graph of ``key``, captured now by ``capture`` if the key ran without one before
        on the same matcher buffers; None: run this frame without a graph, then call
        :meth:`ran`."""
        self._forget_stale(key, generation)
        graph = self._graphs.get(key)
        if graph is None and key in self._ran and not self.failed:
            try:
                graph = self._graphs[key] = capture(key)
            except Exception as exc:  # noqa: BLE001 - any capture failure: run without graphs
                self.failed = True
                _log.warning("capturing the frame as CUDA graphs failed (%s: %s); running "
                             "without graphs (cuda_graph: false avoids the attempt)",
                             type(exc).__name__, exc)
        return graph

    def ran(self, key: _GraphKey, generation: int) -> None:
        """``key`` ran without a graph; the matcher's buffers are now of ``generation``."""
        self._forget_stale(key, generation)
        self._ran.add(key)

    def _forget_stale(self, key: _GraphKey, generation: int) -> None:
        if generation != self._generation or any(k[:2] != key[:2] for k in self._ran):
            self._graphs.clear()
            self._ran.clear()
            self._generation = generation


class FrameExecutor:
    """Runs a Method's stages frame by frame (:meth:`run`) or over a stream of pairs
    (:meth:`run_stream`) on its backend."""

    def __init__(self, method: Method) -> None:
        # the method's owner (pipeline.Pipeline) owns the executor too: a weak reference lets a
        # dropped pipeline, and the device memory of its buffers and graphs, go at once rather
        # than at the next collection
        self.method = weakref.proxy(method)
        self.backend: Backend = method.backend
        self.graphs = FrameGraphs()
        self._uploads: dict[tuple[int, int], list[UploadBuffer]] = {}
        self._graph_memory: GraphMemory | None = None  # shared by the graphs (one stream)
        self._readbacks: list[tuple[Readback, Readback]] = []  # used in turn, frame by frame
        self._unpublished: _Frame | None = None  # the last replayed frame, if not yet copied
        # the rectified images of each upload buffer (GPU; the CPU makes them anew each frame)
        self._rectified_images: dict[int, tuple[Any, Any]] = {}

    def run(self, left: np.ndarray, right: np.ndarray) -> PipelineResult:
        """One pair: its stages queued, the report's header read back and checked (the next
        frame's band is worked out while the device finishes), then the whole report."""
        started = time.perf_counter()
        staged = self._stage((left, right), send_ahead=False)
        if isinstance(staged, PotholeError):
            raise staged
        frame = self._queue(staged, started)
        self._read_road(frame)
        self.method.band(self.method.output_shape(staged.shape(0)))
        self._read_report(frame)
        return self._finish(frame)

    def run_stream(self, pairs: Iterable[tuple[np.ndarray, np.ndarray]]
                   ) -> Iterator[PipelineResult | PotholeError]:
        """Pipeline.run_stream: two frames in flight on the GPU (see the module's text)."""
        iterator = iter(pairs)
        pair = next(iterator, None)
        queued = self._queue_staged(self._stage(pair)) if pair is not None else None
        while queued is not None:
            pair = next(iterator, None)
            staged = self._stage(pair) if pair is not None else None
            outcome: _Frame | PipelineResult | PotholeError = queued
            if isinstance(queued, _Frame):
                try:
                    self._read_road(queued)
                except PotholeError as exc:
                    outcome = exc
            queueing = time.perf_counter()
            following = self._queue_staged(staged) if staged is not None else None
            if isinstance(outcome, _Frame):
                outcome.lent_ms = (time.perf_counter() - queueing) * 1e3
                try:
                    self._read_report(outcome)
                    outcome = self._finish(outcome)
                except PotholeError as exc:
                    outcome = exc
            yield outcome
            queued = following

    def checked_road(self, header: np.ndarray, frame: _Frame) -> road_model.RoadModel:
        """Method.checked_road on a host copy of a frame report's header."""
        return self.method.checked_road(FrameReport.road_of(header),
                                        FrameReport.valid_count_of(header), frame.pixels)

    def _stage(self, pair: tuple[np.ndarray, np.ndarray],
               send_ahead: bool = True) -> UploadBuffer | PotholeError:
        """Pair checked and converted to grey straight into the next upload buffer of its size
        (page-locked memory on the GPU; a new size replaces the buffers of the old one), its
        images sent ahead where ``send_ahead`` (else they go up at the frame's start)."""
        try:
            matching.check_pair(*pair)
        except PotholeError as exc:
            return exc
        height, width = pair[0].shape[:2]
        buffers = self._uploads.get((height, width))
        if buffers is None:
            rows = self.method.output_shape((height, width))[0]
            layout = [((height, width), np.uint8), ((height, width), np.uint8),
                      ((3, rows), np.int32), ((road_model.PRIOR_PARAMS,), np.float64)]
            buffers = [UploadBuffer(self.backend, layout) for _ in range(2)]
            self._uploads = {(height, width): buffers}
            self._rectified_images.clear()
        buffer = buffers.pop(0)
        buffers.append(buffer)
        left_host, right_host = buffer.writable()[:2]
        matching.to_gray8(pair[0], out=left_host)
        matching.to_gray8(pair[1], out=right_host)
        if send_ahead:
            buffer.send_ahead(2)  # the images now; the shifts wait for this frame's road model
        return buffer

    def _rectified(self, staged: UploadBuffer, pair: tuple[Any, Any, Any, Any],
                   clock: StageClock) -> tuple[Any, Any, Any, Any]:
        """The uploaded (left, right, shifts, prior) with the images rectified on the device
        (Method.rectified) into arrays kept with upload buffer ``staged`` (its images are
        overwritten only by its next upload), where the method rectifies."""
        if self.method.rectification is None:
            return pair
        xp = self.backend.xp
        shape = self.method.output_shape(staged.shape(0))
        targets = self._rectified_images.get(id(staged))
        if targets is None or targets[0].shape != shape:
            targets = (xp.empty(shape, dtype=xp.uint8), xp.empty(shape, dtype=xp.uint8))
            if self.backend.is_gpu:
                self._rectified_images[id(staged)] = targets
        with clock.stage("rectify"):
            left, right = self.method.rectified(pair[0], pair[1], targets)
        return left, right, pair[2], pair[3]

    def _queue_staged(self, staged: UploadBuffer | PotholeError) -> _Frame | PotholeError:
        """The pair in upload buffer ``staged`` queued, or the error it raised."""
        if isinstance(staged, PotholeError):
            return staged
        try:
            return self._queue(staged, time.perf_counter())
        except PotholeError as exc:
            return exc

    def _queue(self, staged: UploadBuffer, started: float) -> _Frame:
        """Prepare the pair in upload buffer ``staged`` (seed, GPT) and queue its stages (on
        the CPU: run them), replayed as CUDA graphs where they can be."""
        method, config, backend = self.method, self.method.config, self.backend
        height, width = method.output_shape(staged.shape(0))
        clock = StageClock(backend)
        seeded = method.road is None or not config.gpt_enabled
        seeding = config.gpt_enabled and method.road is None
        staged.send_ahead(2)
        pair, shifts, levels = method.prepare(
            lambda table, prior: self._rectified(staged, _send(staged, table, prior), clock),
            (height, width), clock)
        key = (height, width, levels, method.region_size(width))
        graphed = backend.is_gpu and config.cuda_graph and not seeding \
            and config.matcher == "census"
        graph = self.graphs.get(key, method.matcher.generation, self._capture) \
            if graphed else None
        if graph is None:
            frame = self._frame(pair, levels, clock, self._send_header, seeding)
            if graphed:
                self.graphs.ran(key, method.matcher.generation)
        else:
            frame = self._replay(graph, pair, clock)
        frame.shifts, frame.levels, frame.seeded, frame.started, frame.clock = \
            shifts, levels, seeded, started, clock
        assert frame.readbacks is not None
        with clock.stage("readback"):
            frame.readbacks[1].send(frame.report.buffer)
        if frame.replayed:
            self._unpublished = frame
        else:
            frame.ready = backend.record_event()
        return frame

    def _frame(self, pair: tuple[Any, Any, Any, Any], levels: int, clock: StageClock,
               after_fit: Callable[[_Frame], None], seeded: bool = False) -> _Frame:
        """The method's stages from SGM on, into a new report (``seeded``: the seed pass ran
        on the pair)."""
        config = self.method.config
        n_sp = superpixels.grid_count(pair[0].shape,
                                      self.method.region_size(pair[0].shape[1]),
                                      config.slic_downsample)
        frame = _Frame(FrameReport(self.backend.xp, components.device_capacity(n_sp)),
                       pixels=int(pair[0].size))
        frame.arrays = self.method.stages(*pair, levels, frame.report, clock,
                                          _Checkpoint(self, frame, after_fit), seeded)
        return frame

    def _send_header(self, frame: _Frame) -> None:
        """Queue the readback of the report's header into the next of the readback pairs."""
        ring = self._readbacks
        if not ring or ring[0][1].nbytes != frame.report.buffer.nbytes:
            ring[:] = [(Readback(self.backend, FrameReport.HEADER_BYTES),
                        Readback(self.backend, frame.report.buffer.nbytes)) for _ in range(3)]
        frame.readbacks = ring.pop(0)
        ring.append(frame.readbacks)
        frame.readbacks[0].send(frame.report.header_bytes)

    def _capture(self, key: _GraphKey) -> CapturedGraph:
        """:meth:`_frame` of a (height, width, levels, SLIC grid step) captured as two CUDA
        graphs, cut after the road fit; the outputs: the input arrays (left, right, shifts,
        prior) they read and the frame."""
        height, width, levels, _ = key
        xp = self.backend.xp

        def body(cut: Callable[[], None]) -> tuple[tuple[Any, Any, Any, Any], _Frame]:
            pair = (xp.empty((height, width), dtype=xp.uint8),
                    xp.empty((height, width), dtype=xp.uint8),
                    xp.empty((3, height), dtype=xp.int32),
                    xp.empty(road_model.PRIOR_PARAMS, dtype=xp.float64))
            return pair, self._frame(pair, levels, StageClock(self.backend, timed=False),
                                     lambda frame: cut())

        if self._graph_memory is None:
            self._graph_memory = GraphMemory()
        return self.backend.capture(body, self._graph_memory)

    def _replay(self, graph: CapturedGraph, pair: tuple[Any, Any, Any, Any],
                clock: StageClock) -> _Frame:
        """One replay of a frame's graphs on the uploaded ``pair``, the header's readback
        between them; the frame's arrays are the graph's (see :meth:`_publish`; the frame
        replayed before is published first)."""
        self._publish(self._unpublished)
        inputs, captured = graph.outputs
        with clock.stage("gpt"):
            for target, source in zip(inputs, pair):
                self.backend.copy_into(target, source)
        with clock.stage("graph"):
            graph.launch(0)
            frame = replace(captured, replayed=True)
            self._send_header(frame)
            graph.launch(1)
        return frame

    def _publish(self, frame: _Frame | None) -> None:
        """Copy a replayed frame's published arrays (and what the overflow fallback needs) out
        of its graph's, which the next replay writes again: when the next frame is replayed or
        once the frame's report is read, whichever comes first. A frame whose road was refused
        is skipped."""
        if frame is None or not frame.replayed:
            return
        frame.replayed = False
        if self._unpublished is frame:
            self._unpublished = None
        if frame.road is None or frame.arrays is None or frame.clock is None:
            return
        with frame.clock.stage("graph"):
            arrays = frame.arrays
            found = arrays.superpixels
            copy = self.backend.copy
            frame.arrays = FrameArrays(
                copy(arrays.disparity), copy(arrays.transformed), None,
                superpixels.Superpixels(None, found.count, copy(found.labels), None, None),
                copy(arrays.candidate), copy(arrays.labels), copy(arrays.observed),
                copy(arrays.drops), arrays.region_px, searched=copy(arrays.searched))
            frame.ready = self.backend.record_event()

    def _wait(self, frame: _Frame, readback: Readback) -> np.ndarray:
        """A readback's bytes; the wait counts into the frame's host_wait on the GPU."""
        waiting = time.perf_counter()
        received = readback.receive()
        if self.backend.is_gpu:
            frame.wait_ms += (time.perf_counter() - waiting) * 1e3
        return received

    def _read_road(self, frame: _Frame) -> None:
        """The header readback of a frame and the checks on it, which raise (a frame whose
        road the stages checked already is skipped)."""
        if frame.road is None:
            assert frame.readbacks is not None
            header = self._wait(frame, frame.readbacks[0]).view(np.float64)
            frame.road = self.checked_road(header, frame)

    def _read_report(self, frame: _Frame) -> None:
        """A frame's whole report, read back after :meth:`_read_road`; where its components
        overflowed the report's tables, components and measure run again with room for all
        (with the host road model: a replayed frame's report may hold the next frame's)."""
        assert frame.readbacks is not None and frame.arrays is not None
        frame.host = frame.report.parse(self._wait(frame, frame.readbacks[1]))
        if frame.host.overflow:
            xp = self.backend.xp
            exact = FrameReport(xp, max(frame.host.components_found, 1))
            arrays = replace(frame.arrays, valid=xp.isfinite(frame.arrays.disparity))
            frame.arrays = replace(frame.arrays, labels=self.method.label_and_measure(
                arrays, frame.road, exact, StageClock(self.backend, timed=False)))
            frame.ready = self.backend.record_event()
            remeasured = exact.parse(to_host(exact.buffer))
            frame.host = replace(frame.host, components_kept=remeasured.components_kept,
                                 overflow=False, sums=remeasured.sums,
                                 extremes=remeasured.extremes)
        self._publish(frame)

    def _finish(self, frame: _Frame) -> PipelineResult:
        """The result of a frame whose road and report have been read back and checked."""
        config = self.method.config
        host, arrays, clock = frame.host, frame.arrays, frame.clock
        assert host is not None and arrays is not None and clock is not None
        assert frame.road is not None and frame.shifts is not None
        kept = host.components_kept
        potholes, _ = measure.keep_large(
            host.sums[1:kept + 1], host.extremes[1:kept + 1], config.min_pothole_area_m2,
            config.min_pothole_depth_m, config.max_pothole_depth_m)
        timings = clock.timings()
        timings["total"] = sum(timings.values())
        timings["host"] = (time.perf_counter() - frame.started) * 1e3 - frame.lent_ms
        timings["host_wait"] = frame.wait_ms
        lowest, highest = perspective.shift_range(frame.shifts, arrays.disparity.shape[1])
        return PipelineResult(
            disparity=arrays.disparity, transformed=arrays.transformed, labels=arrays.labels,
            superpixels=arrays.superpixels.labels, observed=arrays.observed,
            searched=arrays.searched,
            observed_range_m=(float(host.observed_range[0]), float(host.observed_range[1])),
            road=frame.road,
            threshold_px=thresholding.reference_level(
                host.threshold, config.histogram_bin_px, config.delta_dt_px,
                thresholding.reference_for(config.threshold_reference, config.threshold_mode)),
            band=(lowest, int(frame.levels)),
            disparity_range=(float(lowest), float(highest + frame.levels - 1)),
            potholes=potholes, backend=self.backend.name, seeded=frame.seeded,
            timings_ms=timings, ready=frame.ready)


def _send(staged: UploadBuffer, shifts: np.ndarray, prior: np.ndarray
          ) -> tuple[Any, Any, Any, Any]:
    """The GPT shift table and the road fit's prior written behind the pair in ``staged`` and
    the whole buffer queued for upload: the backend (left, right, shifts, prior)."""
    shifts_host, prior_host = staged.writable(2)
    shifts_host[...] = shifts
    prior_host[...] = prior
    return staged.upload()
