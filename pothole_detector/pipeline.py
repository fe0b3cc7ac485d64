"""The detection pipeline: runs the stages in order on one backend. Knows nothing of ROS."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from .backend import (CPU, Backend, CapturedGraph, GraphMemory, Readback, StageClock,
                      UploadBuffer, to_host)
from .calibration import StereoCalibration
from .errors import InputError, NoRoadError, NoTextureError, PotholeError
from .params import Config
from .stages import components, matching, measure, perspective, road_model, superpixels
from .stages import threshold as thresholding
from .stages.transform import transform_disparity

_log = logging.getLogger(__name__)


@dataclass
class PipelineResult:
    """Everything one stereo pair produced. Arrays live on the pipeline's backend.

    ``disparity`` (D1) and ``transformed`` (D2) are float32 HxW px, NaN where invalid;
    ``labels`` int32 HxW (0 = road, k = pothole k); ``superpixels`` int32 HxW;
    ``band`` (lowest row shift, levels) and ``disparity_range`` (lowest, highest disparity the
    matcher could report, px). ``timings_ms``: per stage (CUDA events on the GPU; there the
    threshold search runs beside SLIC on a second stream, and ``threshold`` times what is left
    of it after SLIC plus the selection, and ``readback`` the copy of the frame's report to the
    host; a frame replayed as CUDA graphs has ``gpt``, ``graph`` (SGM to measure, and the
    copies of the published arrays) and ``readback`` instead of the stages between),
    ``total`` (their sum), ``host`` (wall time of the call; in a stream, from the frame's
    start to its result less the time spent queueing the next frame) and ``host_wait`` (of
    it, the waits for the GPU frame's two readbacks; 0 on the CPU).
    """

    disparity: Any
    transformed: Any
    labels: Any
    superpixels: Any
    road: road_model.RoadModel
    threshold_px: float
    band: tuple[int, int]
    disparity_range: tuple[float, float]
    potholes: list[measure.Pothole]
    backend: str
    seeded: bool
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class _Detection:
    transformed: Any
    labels: Any
    superpixels: Any
    road: road_model.RoadModel
    threshold_px: float
    potholes: list[measure.Pothole]
    wait_ms: float = 0.0


@dataclass
class _HostReport:
    header: np.ndarray
    threshold: np.ndarray
    components_kept: int
    overflow: bool
    sums: np.ndarray
    extremes: np.ndarray


class _DeviceReport:
    """One device buffer that a frame's stages write their small results into, read back at
    the end (its header, what the checks need, also as soon as the road fit is done): float64
    road report (ROAD) and kernel parameters, threshold search result, valid pixel
    count; int32 counts (components, kept, overflow, kept after the area filter); the
    measure sums and extremes of ``capacity`` labels."""

    ROAD = (0, road_model.ROAD_REPORT)
    _PARAMS = (ROAD[1], ROAD[1] + road_model.ROAD_PARAMS)
    _THRESHOLD = (_PARAMS[1], _PARAMS[1] + 3)
    _VALID = _THRESHOLD[1]
    HEADER_BYTES = 8 * (_VALID + 1)

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
        self.counts = self.buffer[self._counts_at:self._sums_at].view(xp.int32)
        self.sums = self.buffer[self._sums_at:self._extremes_at].view(xp.float64).reshape(
            capacity + 1, measure.MEASURE_SUMS)
        self.extremes = self.buffer[self._extremes_at:].view(xp.int32).reshape(
            capacity + 1, measure.MEASURE_EXTREMES)

    @property
    def header_bytes(self) -> Any:
        """The header (road report and parameters, threshold, valid count) as device bytes."""
        return self.buffer[:self.HEADER_BYTES]

    def read_header(self) -> np.ndarray:
        """Host float64 copy of the header (a synchronous readback)."""
        return to_host(self.header_bytes).view(np.float64)

    @classmethod
    def road_of(cls, header: np.ndarray) -> np.ndarray:
        return header[slice(*cls.ROAD)]

    @classmethod
    def valid_count_of(cls, header: np.ndarray) -> float:
        return float(header[cls._VALID])

    def parse(self, host: np.ndarray) -> _HostReport:
        """The report from a host copy of the whole buffer (uint8)."""
        header = host[:self.HEADER_BYTES].view(np.float64)
        counts = host[self._counts_at:self._sums_at].view(np.int32)
        return _HostReport(
            header=header,
            threshold=header[slice(*self._THRESHOLD)], components_kept=int(counts[1]),
            overflow=bool(counts[2]),
            sums=host[self._sums_at:self._extremes_at].view(np.float64).reshape(
                self.capacity + 1, measure.MEASURE_SUMS),
            extremes=host[self._extremes_at:].view(np.int32).reshape(
                self.capacity + 1, measure.MEASURE_EXTREMES))


@dataclass
class _DeviceWork:
    """The stages of a frame queued on the device: what its readbacks and result need
    (``transformed`` to ``labels`` once the stages after the road fit are queued;
    ``readbacks``: of the report's header and of the whole report; ``road`` and ``host`` once
    read back and checked, ``road`` early in the metric mode; ``exact``: labels and potholes
    measured again where the report overflowed; ``replayed``: the arrays are still a CUDA
    graph's, which its next replay writes again)."""

    report: _DeviceReport
    valid: Any
    n_sp: int
    transformed: Any = None
    sp_labels: Any = None
    candidate: Any = None
    labels: Any = None
    readbacks: tuple[Readback, Readback] | None = None
    road: road_model.RoadModel | None = None
    host: _HostReport | None = None
    wait_ms: float = 0.0
    exact: tuple[Any, list[measure.Pothole]] | None = None
    replayed: bool = False


@dataclass
class _Queued:
    """A matched frame: its detection done (CPU, ``found``) or queued on the device
    (``device``)."""

    disparity: Any
    shifts: np.ndarray
    levels: int
    seeded: bool
    started: float
    clock: StageClock
    found: _Detection | None = None
    device: _DeviceWork | None = None
    lent_ms: float = 0.0  # of its host time, ms spent queueing the next frame


_GraphKey = tuple[int, int, int]


class _FrameGraphs:
    """CUDA graphs of the GPU frame after its upload (SGM and every stage after it), one set
    per (height, width, levels). A key's first frame runs without graphs (kernels built,
    caches filled, the matcher's buffers sized); its next frame captures them, and later
    frames replay them. The graphs hold the matcher's buffers by address: when
    the matcher replaces them (its ``generation``) or the image size changes, every graph is
    dropped and each key starts again. Where a capture fails, the pipeline logs why and runs
    without graphs from then on."""

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


class Pipeline:
    """Stereo pair in, potholes out.

    The road model of one frame seeds the perspective transformation of the next (the rig is
    fixed to the vehicle); the first frame, frames after :meth:`reset` and frames after a poor
    road fit are seeded by a coarse full-range pass.

    On the GPU with ``cuda_graph`` (and the census matcher, the pixel threshold mode), a frame
    that needs no seed replays its SGM and later stages as two CUDA graphs (cut after the road
    fit) per image size and level count (see _FrameGraphs): two launches instead of about
    fifty, the same results.
    """

    def __init__(self, config: Config, calibration: StereoCalibration,
                 backend: Backend = CPU) -> None:
        self.config = config
        self.calibration = calibration
        self.backend = backend
        self.matcher = matching.Matcher(backend)
        # the seed pass's matcher: buffers of its own size, path costs in the frame matcher's
        self._seed_matcher = matching.Matcher(backend, lender=self.matcher)
        self._road: road_model.RoadModel | None = None
        self._uploads: dict[tuple[int, int], list[UploadBuffer]] = {}
        self._graphs = _FrameGraphs()
        self._graph_memory: GraphMemory | None = None  # shared by the graphs (one stream)
        self._readbacks: list[tuple[Readback, Readback]] = []  # used in turn, frame by frame
        self._unpublished: _Queued | None = None  # the last replayed frame, if not yet copied
        # the last band worked out: (road model, config, image shape, (shifts, levels))
        self._band_memo: tuple[Any, Config, tuple[int, ...], tuple[np.ndarray, int]] | None \
            = None

    def reset(self) -> None:
        """Forget the previous frame's road model; the next frame runs the seed pass."""
        self._road = None

    def run(self, left: np.ndarray, right: np.ndarray) -> PipelineResult:
        """Detect potholes in a rectified pair of host images (HxW mono or HxWx3 RGB, uint8 or
        uint16). Raises InputError, NoTextureError or NoRoadError with a message saying why.

        On the GPU nothing is read back but a report the stages write (valid count, road fit,
        threshold, component counts, pothole sums): its header once the road fit is done
        (what the checks that raise need) and the whole of it at the end, both copied
        asynchronously into page-locked memory; the checks run after every stage has been
        queued."""
        started = time.perf_counter()
        staged = self._stage((left, right), send_ahead=False)
        if isinstance(staged, PotholeError):
            raise staged
        queued = self._queue(staged, started)
        self._read_road(queued)
        self._band(staged.shape(0))  # the next frame's, while the device finishes this one
        self._read_report(queued)
        return self._finish(queued)

    def run_stream(self, pairs: Iterable[tuple[np.ndarray, np.ndarray]]
                   ) -> Iterator[PipelineResult | PotholeError]:
        """:meth:`run` over a sequence of pairs: yields, in order, each pair's result or the
        error it raised (the stream goes on after an error), the same results as :meth:`run`
        pair after pair. On the GPU two frames are in flight: while the device works on pair
        N the host checks and converts pair N + 1 into page-locked memory and sends its images
        up on a copy stream (two buffers for the current image size, used in turn); as soon as
        pair N's road fit is read back and checked (an early copy of the report's header),
        pair N + 1 (whose band needs N's road model) is queued behind N's later stages, so the
        device does not wait for the host between frames; then N's report is read and its
        result built. The CPU backend runs the same sequence, each frame whole when it is
        queued."""
        iterator = iter(pairs)
        pair = next(iterator, None)
        queued = self._queue_staged(self._stage(pair)) if pair is not None else None
        while queued is not None:
            pair = next(iterator, None)
            staged = self._stage(pair) if pair is not None else None
            outcome: _Queued | PipelineResult | PotholeError = queued
            if isinstance(queued, _Queued):
                try:
                    self._read_road(queued)
                except PotholeError as exc:
                    outcome = exc
            queueing = time.perf_counter()
            following = self._queue_staged(staged) if staged is not None else None
            if isinstance(outcome, _Queued):
                outcome.lent_ms = (time.perf_counter() - queueing) * 1e3
                try:
                    self._read_report(outcome)
                    outcome = self._finish(outcome)
                except PotholeError as exc:
                    outcome = exc
            yield outcome
            queued = following

    def _stage(self, pair: tuple[np.ndarray, np.ndarray],
               send_ahead: bool = True) -> UploadBuffer | PotholeError:
        """Pair checked and converted to grey straight into the next upload buffer of its size
        (page-locked memory on the GPU; a new size replaces the buffers of the old one), its
        images sent ahead where ``send_ahead`` (else they go up at the frame's start, ahead of
        the GPT shifts). On the GPU the images then cost the device one transfer at bus speed,
        not a copy from pageable memory (0.57-0.87 ms for a 2079x1040 pair on the lent H200s)."""
        try:
            _check_pair(*pair)
        except PotholeError as exc:
            return exc
        height, width = pair[0].shape[:2]
        buffers = self._uploads.get((height, width))
        if buffers is None:
            layout = [((height, width), np.uint8), ((height, width), np.uint8),
                      ((3, height), np.int32)]
            buffers = [UploadBuffer(self.backend, layout) for _ in range(2)]
            self._uploads = {(height, width): buffers}
        buffer = buffers.pop(0)
        buffers.append(buffer)
        left_host, right_host, _ = buffer.writable()
        matching.to_gray8(pair[0], out=left_host)
        matching.to_gray8(pair[1], out=right_host)
        if send_ahead:
            buffer.send_ahead(2)  # the images now; the shifts wait for this frame's road model
        return buffer

    def _queue_staged(self, staged: UploadBuffer | PotholeError) -> _Queued | PotholeError:
        """The pair in upload buffer ``staged`` queued (see :meth:`_queue`), or the error it
        raised."""
        if isinstance(staged, PotholeError):
            return staged
        started = time.perf_counter()
        try:
            return self._queue(staged, started)
        except PotholeError as exc:
            return exc

    def _finish(self, queued: _Queued) -> PipelineResult:
        """The result of a frame whose road and report have been read back and checked."""
        found = queued.found if queued.found is not None else self._device_detection(queued)
        timings = queued.clock.timings()
        timings["total"] = sum(timings.values())
        timings["host"] = (time.perf_counter() - queued.started) * 1e3 - queued.lent_ms
        timings["host_wait"] = found.wait_ms
        levels = queued.levels
        lowest, highest = perspective.shift_range(queued.shifts, queued.disparity.shape[1])
        return PipelineResult(
            disparity=queued.disparity, transformed=found.transformed, labels=found.labels,
            superpixels=found.superpixels, road=found.road, threshold_px=found.threshold_px,
            band=(lowest, int(levels)),
            disparity_range=(float(lowest), float(highest + levels - 1)),
            potholes=found.potholes, backend=self.backend.name, seeded=queued.seeded,
            timings_ms=timings,
        )

    def _detect_on_host(self, disparity: Any, clock: StageClock) -> _Detection:
        """The stages after matching, each read back where the next needs it (CPU backend)."""
        config, backend = self.config, self.backend
        valid = backend.xp.isfinite(disparity)
        self._check_valid(float(valid.mean()))
        with clock.stage("road"):
            road = self._accept_road(lambda: self._fit(disparity, stride=config.road_fit_stride))
        with clock.stage("dt"):
            transformed = transform_disparity(backend, disparity, road, config.delta_dt_px)
        with clock.stage("slic"):
            sp_grid, n_sp, sp_labels, sp_means, sp_valid = self._superpixels(transformed)
        with clock.stage("threshold"):
            t_r, road_mean = thresholding.histogram_threshold(
                backend, transformed, config.histogram_bin_px, config.delta_dt_px)
            reference = road_mean if config.threshold_reference == "road_mean" else t_r
            selected = self._select(sp_labels, n_sp, sp_means, sp_valid, reference, road)
        with clock.stage("components"):
            labels, count = components.pothole_components(
                backend, selected[sp_grid], valid, sp_labels, n_sp,
                config.corner_fraction, config.min_pothole_superpixels,
                factor=config.slic_downsample)
        with clock.stage("measure"):
            labels, potholes = self._measure_exact(labels, count, disparity, road)
        return _Detection(transformed, labels, sp_labels, road, reference, potholes)

    def _queue(self, staged: UploadBuffer, started: float) -> _Queued:
        """Match the pair in upload buffer ``staged``, then detect on the host (CPU) or queue
        the stages after matching on the device (GPU)."""
        config, backend = self.config, self.backend
        height, width = staged.shape(0)
        clock = StageClock(backend)
        seeded = self._road is None or not config.gpt_enabled
        seeding = config.gpt_enabled and self._road is None
        pair, shifts, levels = self._upload(staged, clock)
        if not backend.is_gpu:
            disparity = self._sgm(*pair, levels, clock)
            return _Queued(disparity, shifts, levels, seeded, started, clock,
                           found=self._detect_on_host(disparity, clock))
        key = (height, width, levels)
        graphed = config.cuda_graph and not seeding and config.threshold_mode == "pixels" \
            and self.matcher.kind(config) == "census"
        graph = self._graphs.get(key, self.matcher.generation, self._capture_frame) \
            if graphed else None
        if graph is None:
            disparity, work = self._device_frame(*pair, levels, clock, self._send_header)
            if graphed:
                self._graphs.ran(key, self.matcher.generation)
        else:
            disparity, work = self._replay(graph, pair, clock)
        with clock.stage("readback"):
            work.readbacks[1].send(work.report.buffer)
        queued = _Queued(disparity, shifts, levels, seeded, started, clock, device=work)
        if work.replayed:
            self._unpublished = queued
        return queued

    def _device_frame(self, left: Any, right: Any, shifts: Any, levels: int, clock: StageClock,
                      after_fit: Callable[[_DeviceWork], None]) -> tuple[Any, _DeviceWork]:
        """SGM and the stages after it queued on the device: (D1, the queued work);
        ``after_fit(work)`` is called once the road fit is queued."""
        disparity = self._sgm(left, right, shifts, levels, clock)
        work = self._fit_on_device(disparity, clock)
        after_fit(work)
        self._after_fit_on_device(disparity, work, clock)
        return disparity, work

    def _send_header(self, work: _DeviceWork) -> None:
        """Queue the readback of the report's header (the road fit's result, what the checks
        need) into the next of the pipeline's readbacks."""
        ring = self._readbacks
        if not ring or ring[0][1].nbytes != work.report.buffer.nbytes:
            ring[:] = [(Readback(self.backend, _DeviceReport.HEADER_BYTES),
                        Readback(self.backend, work.report.buffer.nbytes)) for _ in range(3)]
        work.readbacks = ring.pop(0)
        ring.append(work.readbacks)
        work.readbacks[0].send(work.report.header_bytes)

    def _capture_frame(self, key: _GraphKey) -> CapturedGraph:
        """:meth:`_device_frame` of a (height, width, levels) captured as two CUDA graphs, cut
        after the road fit; the outputs: the input arrays (left, right, shifts) they read, D1
        and the queued work."""
        height, width, levels = key
        xp = self.backend.xp

        def body(cut: Callable[[], None]) -> tuple[tuple[Any, Any, Any], Any, _DeviceWork]:
            pair = (xp.empty((height, width), dtype=xp.uint8),
                    xp.empty((height, width), dtype=xp.uint8),
                    xp.empty((3, height), dtype=xp.int32))
            return (pair, *self._device_frame(*pair, levels, StageClock(self.backend, timed=False),
                                              lambda work: cut()))

        if self._graph_memory is None:
            self._graph_memory = GraphMemory()
        return self.backend.capture(body, self._graph_memory)

    def _replay(self, graph: CapturedGraph, pair: tuple[Any, Any, Any],
                clock: StageClock) -> tuple[Any, _DeviceWork]:
        """One replay of a frame's graphs on the uploaded ``pair`` (left, right, shifts), the
        header's readback between them: D1 and the work, in the graph's arrays (see
        :meth:`_publish`; the frame replayed before is published first)."""
        self._publish(self._unpublished)
        inputs, disparity, captured = graph.outputs
        with clock.stage("gpt"):
            for target, source in zip(inputs, pair):
                self.backend.copy_into(target, source)
        with clock.stage("graph"):
            graph.launch(0)
            work = replace(captured, replayed=True)
            self._send_header(work)
            graph.launch(1)
        return disparity, work

    def _publish(self, queued: _Queued | None) -> None:
        """Copy a replayed frame's published arrays (and the overflow fallback's candidate) out
        of its graph's, which the next replay writes again: when the next frame is replayed or
        once the frame's report is read, whichever comes first (so no more frames' arrays are
        alive at once than without graphs). A frame whose road was refused is skipped."""
        work = queued.device if queued is not None else None
        if work is None or not work.replayed:
            return
        work.replayed = False
        if self._unpublished is queued:
            self._unpublished = None
        if work.road is None:
            return
        with queued.clock.stage("graph"):
            queued.disparity = queued.disparity.copy()
            work.transformed = work.transformed.copy()
            work.sp_labels = work.sp_labels.copy()
            work.labels = work.labels.copy()
            work.candidate = work.candidate.copy()

    def _fit_on_device(self, disparity: Any, clock: StageClock) -> _DeviceWork:
        """The valid count and the road fit queued on the device, into a new report."""
        config, backend = self.config, self.backend
        xp = backend.xp
        n_sp = superpixels.grid_count(disparity.shape, config.slic_region_size_px,
                                      config.slic_downsample)
        report = _DeviceReport(xp, components.device_capacity(n_sp))
        valid = xp.isfinite(disparity)
        with clock.stage("road"):
            report.valid_count[...] = xp.count_nonzero(valid)
            road_model.fit_on_device(
                backend, disparity, stride=config.road_fit_stride,
                rounds=config.road_fit_rounds, outlier_k=config.road_outlier_k,
                kind=config.road_model, quadratic_gain=config.road_quadratic_gain,
                report=report.road, params=report.road_params)
        return _DeviceWork(report, valid, n_sp)

    def _after_fit_on_device(self, disparity: Any, work: _DeviceWork,
                             clock: StageClock) -> None:
        """The stages after the road fit queued on the device with nothing read back (see
        :class:`_DeviceReport`; the metric threshold mode reads the road model early), their
        arrays into ``work``."""
        config, backend = self.config, self.backend
        xp, report = backend.xp, work.report
        with clock.stage("dt"):
            transformed = transform_disparity(backend, disparity, report.road_params,
                                              config.delta_dt_px)
        # the threshold search needs D2 only: it runs beside SLIC on a second stream
        with backend.side_stream() as join_threshold:
            thresholding.threshold_on_device(backend, transformed, config.histogram_bin_px,
                                             config.delta_dt_px, result=report.threshold)
        with clock.stage("slic"):
            sp_grid, n_sp, sp_labels, sp_means, sp_valid = self._superpixels(transformed)
        with clock.stage("threshold"):
            join_threshold()
            drop: float | Any = config.delta_pd_px
            if config.threshold_mode != "pixels":
                # the metric tolerance needs the road model on the host: one early readback
                work.road = self._checked_road(report.read_header(), disparity.size)
                drop = self._metric_drop(sp_labels, n_sp, work.road)
            selected = thresholding.select_on_device(
                backend, report.threshold, config.histogram_bin_px, config.delta_dt_px,
                config.threshold_reference == "road_mean", sp_means, sp_valid, drop,
                config.superpixel_min_valid_fraction)
        with clock.stage("components"):
            candidate = xp.take(selected, sp_grid)
            labels = components.components_on_device(
                backend, candidate, work.valid, sp_labels, n_sp, config.corner_fraction,
                config.min_pothole_superpixels, config.slic_downsample, report.capacity,
                report.counts[:3])
        with clock.stage("measure"):
            measure.measure_on_device(backend, labels, report.capacity, disparity,
                                      report.road_params, self.calibration,
                                      sums=report.sums, extremes=report.extremes)
            labels = measure.area_filter_on_device(
                backend, labels, report.sums, report.counts[1:2], report.capacity,
                config.min_pothole_area_m2, report.counts[3:4])
        work.transformed, work.sp_labels = transformed, sp_labels
        work.candidate, work.labels = candidate, labels

    def _read_road(self, queued: _Queued) -> None:
        """A GPU frame's header readback and the checks on it, which raise; the road model
        they accept gives the next frame its band (the CPU checked its frames when
        detecting; the metric mode checked it when queueing)."""
        work = queued.device
        if work is None or work.road is not None:
            return
        assert work.readbacks is not None
        waiting = time.perf_counter()
        header = work.readbacks[0].receive().view(np.float64)
        work.wait_ms += (time.perf_counter() - waiting) * 1e3
        work.road = self._checked_road(header, queued.disparity.size)

    def _read_report(self, queued: _Queued) -> None:
        """A GPU frame's report, read back after :meth:`_read_road`; where its components
        overflowed, they are filtered and measured again with exact sizes."""
        work = queued.device
        if work is None:
            return
        assert work.readbacks is not None and work.road is not None
        waiting = time.perf_counter()
        work.host = work.report.parse(work.readbacks[1].receive())
        work.wait_ms += (time.perf_counter() - waiting) * 1e3
        if work.host.overflow:
            config = self.config
            labels, count = components.pothole_components(
                self.backend, work.candidate, self.backend.xp.isfinite(queued.disparity),
                work.sp_labels, work.n_sp, config.corner_fraction,
                config.min_pothole_superpixels, factor=config.slic_downsample)
            work.exact = self._measure_exact(labels, count, queued.disparity, work.road)
        self._publish(queued)

    def _device_detection(self, queued: _Queued) -> _Detection:
        """The detection of a GPU frame from its report, read back and checked."""
        config, work = self.config, queued.device
        assert work is not None and work.host is not None and work.road is not None
        host, road = work.host, work.road
        t_r, road_mean = thresholding.split_from_result(host.threshold, config.histogram_bin_px,
                                                        config.delta_dt_px)
        reference = road_mean if config.threshold_reference == "road_mean" else t_r
        labels = work.labels
        if work.exact is not None:
            labels, potholes = work.exact
        else:
            potholes, _ = measure.keep_large(
                measure.potholes_from_sums(host.sums[1:host.components_kept + 1],
                                           host.extremes[1:host.components_kept + 1]),
                config.min_pothole_area_m2)
        return _Detection(work.transformed, labels, work.sp_labels, road, reference, potholes,
                          work.wait_ms)

    def _check_valid(self, valid_fraction: float) -> None:
        if valid_fraction < self.config.min_valid_fraction:
            self.reset()
            raise NoTextureError(
                f"only {valid_fraction:.1%} of pixels got a disparity (need "
                f"{self.config.min_valid_fraction:.0%}): the images lack texture, are not a "
                "rectified pair, or the road is outside max_disparity_px"
            )

    def _accept_road(self, fit: Any) -> road_model.RoadModel:
        """The road model ``fit()`` returns, kept for the next frame's band when it holds
        enough inliers; else the pipeline resets and NoRoadError is raised."""
        try:
            road = fit()
        except NoRoadError:
            self.reset()
            raise
        if road.inlier_fraction < self.config.min_road_inlier_fraction:
            self.reset()
            raise NoRoadError(
                f"no road plane: only {road.inlier_fraction:.0%} of the valid disparities "
                f"fit one (need {self.config.min_road_inlier_fraction:.0%}); is the camera "
                "looking at the road?"
            )
        self._road = road
        return road

    def _checked_road(self, header: np.ndarray, pixels: int) -> road_model.RoadModel:
        """The valid-fraction and road checks of a frame on a host copy of its
        _DeviceReport header; the accepted road model."""
        config = self.config
        self._check_valid(_DeviceReport.valid_count_of(header) / pixels)
        return self._accept_road(lambda: road_model.model_from_report(
            _DeviceReport.road_of(header), config.road_model, config.road_quadratic_gain))

    def _superpixels(self, transformed: Any) -> tuple[Any, int, Any, Any, Any]:
        """SLIC of D2: (labels on the reduced grid, count, full-resolution labels, per-label
        mean D2, per-label valid fraction)."""
        config, backend = self.config, self.backend
        sp_grid, n_sp = superpixels.superpixel_grid(
            backend, transformed, config.slic_region_size_px, config.slic_compactness,
            config.slic_iterations, config.slic_downsample)
        sp_labels = superpixels.upsample_labels(backend, sp_grid, config.slic_downsample,
                                                transformed.shape)
        sp_means, sp_valid = superpixels.superpixel_means(backend, transformed, sp_labels, n_sp)
        return sp_grid, n_sp, sp_labels, sp_means, sp_valid

    def _measure_exact(self, labels: Any, count: int, disparity: Any,
                       road: road_model.RoadModel) -> tuple[Any, list[measure.Pothole]]:
        """Measure ``count`` labelled potholes and drop those below min_pothole_area_m2
        (labels renumbered)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            potholes = measure.measure_potholes(self.backend, labels, count, disparity, road,
                                                self.calibration)
        kept, keep = measure.keep_large(potholes, self.config.min_pothole_area_m2)
        if len(kept) < len(potholes):
            labels, _ = components.relabel(self.backend.xp, labels, self.backend.xp.asarray(keep))
        return labels, kept

    def match_pair(self, left: np.ndarray, right: np.ndarray) -> tuple[Any, int]:
        """D1 of a host pair (float32 HxW px, NaN invalid, on the backend) and the number of
        disparity levels searched; seeds and updates the road model like :meth:`run`."""
        staged = self._stage((left, right), send_ahead=False)
        if isinstance(staged, PotholeError):
            raise staged
        clock = StageClock(self.backend)
        pair, _, levels = self._upload(staged, clock)
        disparity = self._sgm(*pair, levels, clock)
        if self.config.gpt_enabled:
            try:
                self._road = self._fit(disparity, stride=self.config.road_fit_stride)
            except NoRoadError:
                self.reset()
        return disparity, levels

    def _upload(self, staged: UploadBuffer, clock: StageClock
                ) -> tuple[tuple[Any, Any, Any], np.ndarray, int]:
        """One upload of the pair in upload buffer ``staged`` and the GPT shift table, then the
        seed pass where one is needed (shifts sent again): ((left, right, shifts) on the
        backend, shifts (3, H) on the host, levels). The images go up first (unless sent ahead
        already), so that the shifts, where not worked out yet (see :meth:`_band`), are worked
        out while they are on their way."""
        shape = staged.shape(0)
        seeding = self.config.gpt_enabled and self._road is None
        with clock.stage("gpt"):
            staged.send_ahead(2)
            shifts, levels = self._band(shape)
            staged.writable(2)[0][...] = shifts
            left, right, shifts_dev = staged.upload()
        if seeding:
            with clock.stage("seed"):
                self._road = self._seed(left, right)
                shifts, levels = self._band(shape)
                shifts_dev = self.backend.upload(shifts)
        return (left, right, shifts_dev), shifts, levels

    def _sgm(self, left: Any, right: Any, shifts: Any, levels: int, clock: StageClock) -> Any:
        """D1 of a pair on the backend (the ``sgm`` stage)."""
        with clock.stage("sgm"):
            return self.matcher(left, right, shifts, levels, self.config)

    def _band(self, shape: tuple[int, int]) -> tuple[np.ndarray, int]:
        """GPT shift table (int32 (3, H), host; stages/perspective.py) and level count from the
        current road model (no shifts and the full range without one or with GPT off); worked
        out once per road model and image size (:meth:`run` does it for the next frame while
        the device finishes the frame that fitted the model)."""
        config = self.config
        road = self._road if config.gpt_enabled else None
        memo = self._band_memo
        if memo is not None and memo[0] is road and memo[1] is config and memo[2] == shape:
            return memo[3]
        height, width = shape
        if road is None:
            band = (perspective.no_shifts(height),
                    perspective.round_up_levels(config.max_disparity_px))
        else:
            band = perspective.band(np, road, height, width, config.gpt_margin_below_px,
                                    config.gpt_margin_above_px, config.max_disparity_px,
                                    self.shift_mode())
        self._band_memo = (road, config, shape, band)
        return band

    def shift_mode(self) -> str:
        """pixel or row: the GPT shifts ``gpt_shift`` asks for on this backend (auto: pixel
        with the census matcher, row with OpenCV SGBM)."""
        mode = self.config.gpt_shift
        if mode != "auto":
            return mode
        return "pixel" if self.matcher.kind(self.config) == "census" else "row"

    def _fit(self, disparity: Any, stride: int, scale: float = 1.0) -> road_model.RoadModel:
        config = self.config
        return road_model.fit(
            self.backend, disparity, stride=stride, rounds=config.road_fit_rounds,
            outlier_k=config.road_outlier_k, kind=config.road_model,
            quadratic_gain=config.road_quadratic_gain, coordinate_scale=scale,
            coordinate_offset=(scale - 1.0) / 2.0)

    def _seed(self, left: Any, right: Any) -> road_model.RoadModel:
        """Road model from a full-range match of the (backend) pair reduced by coarse_scale."""
        config, xp = self.config, self.backend.xp
        scale = config.coarse_scale
        small_left = matching.downsample(xp, left, scale)
        small_right = matching.downsample(xp, right, scale)
        half_width = small_left.shape[1] // 2
        levels = perspective.round_up_levels(min(config.max_disparity_px / scale, half_width))
        shifts = xp.asarray(perspective.no_shifts(small_left.shape[0]))
        coarse = self._seed_matcher(small_left, small_right, shifts, levels, config,
                                    block_size=min(config.sgm_block_size, 5))
        if float(xp.isfinite(coarse).mean()) < config.min_valid_fraction:
            raise NoTextureError(
                "the coarse seed pass found almost no disparities: the images lack texture, "
                "are not a rectified pair, or the road is beyond max_disparity_px"
            )
        return self._fit(coarse, stride=1, scale=float(scale))

    def _select(self, sp_labels: Any, n_sp: int, means: Any, valid_fraction: Any,
                t_r: float, road: road_model.RoadModel) -> Any:
        """Bool (n,) of pothole superpixels: D3 < t_s with t_s = t_r - delta_PD (px, or a
        metric depth converted per superpixel with the road model and calibration); ``t_r`` is
        the threshold reference (road mean or split)."""
        xp, config = self.backend.xp, self.config
        if not math.isfinite(t_r):
            return xp.zeros(n_sp, dtype=bool)
        if config.threshold_mode == "pixels":
            t_s = t_r - config.delta_pd_px
        else:
            t_s = t_r - self._metric_drop(sp_labels, n_sp, road)
        return thresholding.select_superpixels(xp, means, valid_fraction, t_s,
                                               config.superpixel_min_valid_fraction)

    def _metric_drop(self, sp_labels: Any, n_sp: int, road: road_model.RoadModel) -> Any:
        """Per-superpixel disparity drop (px, float64 (n,)) of a point delta_PD_m below the road
        at the superpixel's centroid."""
        xp = self.backend.xp
        height, width = sp_labels.shape
        flat = sp_labels.ravel()
        count = xp.maximum(xp.bincount(flat, minlength=n_sp), 1)
        rows = xp.broadcast_to(xp.arange(height, dtype=xp.float64)[:, None], sp_labels.shape)
        cols = xp.broadcast_to(xp.arange(width, dtype=xp.float64)[None, :], sp_labels.shape)
        v = xp.bincount(flat, weights=rows.ravel(), minlength=n_sp) / count
        u = xp.bincount(flat, weights=cols.ravel(), minlength=n_sp) / count
        return metric_tolerance_px(xp, u, v, road, self.calibration, self.config.delta_pd_m)


def metric_tolerance_px(xp: Any, u: Any, v: Any, road: road_model.RoadModel,
                        calibration: StereoCalibration, depth_m: float) -> Any:
    """Disparity drop (px) of a point ``depth_m`` below the road at pixels (u, v)."""
    normal = measure.road_normal(road, calibration)
    f = calibration.f
    incidence = normal[0] * (u - calibration.cx) / f + normal[1] * (v - calibration.cy) / f \
        + normal[2]
    road_d = road.at(xp, u, v)
    return road_d - calibration.fb / (calibration.fb / road_d + depth_m / incidence)


def _check_pair(left: np.ndarray, right: np.ndarray) -> None:
    """Raise InputError unless ``left`` and ``right`` are a pair the pipeline can take."""
    for name, image in (("left", left), ("right", right)):
        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
            raise InputError(f"{name} image must be a non-empty HxW or HxWxC array")
        if image.ndim == 3 and image.shape[2] not in (3, 4):
            raise InputError(f"{name} image has {image.shape[2]} channels; use mono, RGB or RGBA")
        if image.dtype not in (np.uint8, np.uint16):
            raise InputError(f"{name} image is {image.dtype}; use 8- or 16-bit images")
    if left.shape[:2] != right.shape[:2]:
        raise InputError(
            f"left image is {left.shape[1]}x{left.shape[0]} but right is "
            f"{right.shape[1]}x{right.shape[0]}: a rectified pair has equal sizes"
        )
    if min(left.shape[:2]) < 16:
        raise InputError(f"images of {left.shape[1]}x{left.shape[0]} are too small (min 16x16)")
