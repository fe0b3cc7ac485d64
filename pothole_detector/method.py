"""The detection method: its stages in order, on either backend. Knows nothing of ROS, nor of
how frames are executed.

:meth:`Method.prepare` (seed, GPT) and :meth:`Method.stages` (SGM, road, DT, SLIC,
threshold, selection, components, measure) are the method, written once for NumPy and CuPy
arrays. How frames are executed (upload buffers, the frame report and its readbacks, CUDA
graphs, two frames in flight) is execution.py's, which calls these; pipeline.py puts the two
together.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, Protocol

import numpy as np

from .backend import CPU, Backend, StageClock, gather, lookup, to_host
from .calibration import StereoCalibration
from .errors import InputError, NoRoadError, NoTextureError, PotholeError
from .params import Config
from .stages import components, local_road, matching, measure, perspective, photometric
from .stages import refine, road_model, seed
from .stages import superpixels, texture
from .stages.rectify import Rectification, invalidate_unseen, remap
from .stages import threshold as thresholding
from .stages.transform import transform_disparity

_log = logging.getLogger(__name__)
ARRAY_FIELDS = ("disparity", "transformed", "labels", "superpixels", "observed", "searched")
SUPERPIXEL_FIELDS = ("observed", "searched")


@dataclass
class PipelineResult:
    """Everything one stereo pair produced. Arrays live on the pipeline's backend; :meth:`host`
    hands NumPy copies.

    ``disparity`` (D1) and ``transformed`` (D2) are float32 HxW px, NaN where invalid;
    ``labels`` int32 HxW (0 = road, k = pothole k); ``superpixels`` int32 HxW; ``observed``
    bool (superpixel count,): where the road is observed, i.e. a pothole ``delta_pd_m`` deep
    would stand out of the disparity noise of one pixel (``host("observed")`` gives it as a
    bool HxW mask); ``searched`` bool (superpixel count,): where potholes were looked for,
    where such a pothole would stand out of the noise of the superpixel means about the local
    road (stages/local_road.py), which reaches farther than the observed road and leaves out
    superpixels too poorly textured to match (stages/texture.py); the observed road itself
    without the local road reference or in pixels mode;
    ``observed_range_m`` (near, far): the distance ahead along the road (m, from the point below
    the camera, along the optical axis's direction on the road plane) that the observed
    superpixels span, NaN where none is;
    ``band`` (lowest GPT shift, levels) and ``disparity_range`` (lowest, highest disparity the
    matcher could report, px). ``timings_ms``: per stage (CUDA events on the GPU, where the
    threshold search runs beside SLIC on a second stream and ``threshold`` times what is left
    of it after SLIC plus the selection, and ``readback`` the copy of the frame's report to the
    host; a frame replayed as CUDA graphs has ``gpt``, ``graph`` and ``readback`` instead of
    the stages from SGM on), ``total`` (their sum), ``host`` (wall time of the call; in a
    stream, from the frame's start to its result less the time spent queueing the next frame)
    and ``host_wait`` (of it, the waits for the GPU frame's readbacks; 0 on the CPU).
    ``ready``: on the GPU, the device event after which the arrays hold their values (None: the
    current stream's order); :meth:`host` and :meth:`at` read after it on a stream of their
    own, so the next frame's work, queued before a stream hands this result out, does not hold
    them up.
    """

    disparity: Any
    transformed: Any
    labels: Any
    superpixels: Any
    observed: Any
    searched: Any
    observed_range_m: tuple[float, float]
    road: road_model.RoadModel
    threshold_px: float
    band: tuple[int, int]
    disparity_range: tuple[float, float]
    potholes: list[measure.Pothole]
    backend: str
    seeded: bool
    timings_ms: dict[str, float] = field(default_factory=dict)
    ready: Any = None

    def host(self, name: str, window: tuple[slice, slice] | None = None) -> np.ndarray:
        """Array ``name`` (one of ARRAY_FIELDS) as a NumPy array, or its (rows, columns)
        ``window`` alone: a device-to-host copy of that on the GPU (a per-superpixel field
        looked up through the superpixels on the device first), the array itself (or a view)
        on the CPU."""
        if name not in ARRAY_FIELDS:
            raise KeyError(f"{name!r} is not one of {', '.join(ARRAY_FIELDS)}")
        if name in SUPERPIXEL_FIELDS:
            superpixels = self.superpixels if window is None else self.superpixels[window]
            return lookup(getattr(self, name), superpixels, self.ready)
        array = getattr(self, name)
        return to_host(array if window is None else array[window], self.ready)

    def at(self, name: str, pixels: np.ndarray) -> np.ndarray:
        """Array ``name`` (one of ARRAY_FIELDS) at pixels ``pixels`` (int (K,), flat indices
        row * width + column) as a NumPy (K,) array: gathered on the backend, only those
        values copied to the host."""
        if name not in ARRAY_FIELDS:
            raise KeyError(f"{name!r} is not one of {', '.join(ARRAY_FIELDS)}")
        if name in SUPERPIXEL_FIELDS:
            return gather(getattr(self, name), pixels, through=self.superpixels,
                          after=self.ready)
        return gather(getattr(self, name), pixels, after=self.ready)


@dataclass
class FrameArrays:
    """What :meth:`Method.stages` leaves on the backend: D1, D2, the valid mask, the
    superpixels (of grid step ``region_px``), the candidate mask on the SLIC grid, the pothole
    labels, the bool per-superpixel mask of where the road is observed and the float64
    per-superpixel threshold drops (px) of the road fit's noise (the refinement's; with the
    local road reference, the selection's come from the road's noise around each superpixel,
    local_road.offsets); ``local``: with the local road reference, float64 per
    superpixel, how far (px) the road around it lies below the road model
    (stages/local_road.py); ``inconsistent``: bool per superpixel, where the two views
    disagree on its brightness (stages/photometric.py); ``bumps``: bool per superpixel, where
    the road stands significantly above the local road (local_road.LocalTests); ``searched``:
    bool per superpixel, where potholes are looked for (PipelineResult); ``depressed``: with the
    local road reference, bool per superpixel, the searched ones that lie below the local road
    by more than refine_depth_fraction of their threshold (components.join_pieces);
    ``significant``: bool per superpixel, the searched ones deeper below the road around them
    than corner_significance times their threshold (measure.reportable)."""

    disparity: Any
    transformed: Any
    valid: Any
    superpixels: superpixels.Superpixels
    candidate: Any
    labels: Any
    observed: Any = None
    drops: Any = None
    region_px: int = 0
    local: Any = None
    inconsistent: Any = None
    bumps: Any = None
    searched: Any = None
    depressed: Any = None
    significant: Any = None


class FrameReport(Protocol):
    """Where a frame's stages write their small results, each a backend array of its own
    (execution.FrameReport lays them out in one buffer): ``road`` the road fit report
    (road_model.FIT_LAYOUT) and ``road_params`` its kernel parameters, ``threshold`` the
    threshold search result (3,), ``valid_count`` (1,), ``observed_range`` (near, far m),
    ``components`` int32 (found, kept, overflow) and ``components_kept`` its kept count (1,),
    ``kept_after_area`` int32 (1,), ``sums`` and ``extremes`` the measure's of up to
    ``capacity`` labels."""

    capacity: int
    road: Any
    road_params: Any
    threshold: Any
    valid_count: Any
    observed_range: Any
    components: Any
    components_kept: Any
    kept_after_area: Any
    sums: Any
    extremes: Any


class Checkpoint(Protocol):
    """The executor's hold points in :meth:`Method.stages`."""

    def road_fitted(self, report: FrameReport) -> road_model.RoadModel | Any:
        """The road fit is queued: the road the later stages use (the checked RoadModel, or on
        the device its kernel parameters, checked once read back)."""

    def host_road(self, report: FrameReport) -> road_model.RoadModel:
        """The checked road model on the host (a synchronous readback on the GPU)."""


class Method:
    """The method on one stereo rig: the road model carried from frame to frame, the matchers,
    the GPT band and the stages; executed frame by frame by execution.FrameExecutor
    (pipeline.Pipeline).

    The road model of one frame seeds the perspective transformation of the next (the rig is
    fixed to the vehicle); the first frame, frames after :meth:`reset` and frames after a poor
    road fit are seeded by a coarse full-range pass.
    """

    def __init__(self, config: Config, calibration: StereoCalibration,
                 backend: Backend = CPU, rectification: Rectification | None = None) -> None:
        """``calibration``: the rectified pair's; ``rectification``: where the images come
        raw, the tables that rectify them into that pair's frame (stages/rectify.py)."""
        self.config = config
        self.calibration = calibration
        self.backend = backend
        self.rectification = rectification
        # the tables on the backend, uploaded once
        self.device_rectification = None if rectification is None else rectification.on(backend)
        self.matcher = matching.Matcher(backend)
        # the seed pass's matcher: buffers of its own size, path costs in the frame matcher's
        self._seed_matcher = matching.Matcher(backend, lender=self.matcher)
        self.road: road_model.RoadModel | None = None
        self._axis_sine = 1.0  # of the last seeded road: see region_size
        self._accepted: road_model.RoadModel | None = None  # the last road a frame passed
        self._refused = 0  # frames refused in a row
        self._band_memo: tuple[Any, Config, tuple[int, ...], tuple[np.ndarray, int]] | None \
            = None

    def reset(self) -> None:
        """Forget the previous frame's road model; the next frame runs the seed pass."""
        self.road = None
        self._accepted = None
        self._refused = 0

    def match_pair(self, left: np.ndarray, right: np.ndarray) -> tuple[Any, int]:
        """D1 of a host pair (float32 HxW px, NaN invalid, on the backend) and the number of
        disparity levels searched; seeds and updates the road model as a frame does."""
        matching.check_pair(left, right)
        xp = self.backend.xp
        images = self.rectified(*(self.backend.upload(matching.to_gray8(image))
                                  for image in (left, right)))
        clock = StageClock(self.backend)
        seeded = self.road is None
        (*pair, prior), _, levels = self.prepare(
            lambda shifts, prior: (*images, xp.asarray(shifts), xp.asarray(prior)),
            images[0].shape, clock)
        disparity = self.match(*pair, levels)
        if self.config.gpt_enabled:
            report, _ = self.fit_road(disparity, prior, seeded)
            try:
                self.road = road_model.model_from_report(to_host(report),
                                                         self.config.road_model,
                                                         self.config.road_quadratic_gain)
            except NoRoadError:
                self.reset()
        return disparity, levels

    # --- the method, in order -------------------------------------------------------------

    def rectified(self, left: Any, right: Any, out: tuple[Any, Any] | None = None
                  ) -> tuple[Any, Any]:
        """The uint8 HxW pair (on the backend) in the rectified frame: remapped where the
        pipeline has a rectification (into ``out`` where given), else as it is. Raises
        InputError where the images are not of the calibration's raw size."""
        tables = self.device_rectification
        if tables is None:
            return left, right
        if tuple(left.shape) != tables.source_shape:
            raise InputError(
                f"images are {left.shape[1]}x{left.shape[0]} but camera_info describes "
                f"{tables.source_shape[1]}x{tables.source_shape[0]} raw images; publish the "
                "camera_info of these images")
        targets = out or (None, None)
        return (remap(self.backend, left, tables.left, targets[0]),
                remap(self.backend, right, tables.right, targets[1]))

    def match(self, left: Any, right: Any, shifts: Any, levels: int) -> Any:
        """D1 of a prepared pair on the backend (float32 HxW px, NaN invalid): the matcher's,
        less what the raw cameras did not see where the pipeline rectifies
        (stages/rectify.invalidate_unseen)."""
        disparity = self.matcher(left, right, shifts, levels, self.config)
        if self.device_rectification is None:
            return disparity
        return invalidate_unseen(self.backend, disparity, self.device_rectification)

    def view(self, left: np.ndarray) -> np.ndarray:
        """The left host image as the results see it (for pictures and coloured clouds):
        rectified for display where the pipeline rectifies, else itself."""
        if self.rectification is None:
            return left
        return self.rectification.left_view(left)

    def output_shape(self, shape: tuple[int, ...]) -> tuple[int, int]:
        """The (height, width) of the results for input images of ``shape``."""
        if self.rectification is None:
            return int(shape[0]), int(shape[1])
        return self.rectification.shape

    def prepare(self, send: Callable[[np.ndarray, np.ndarray], tuple[Any, Any, Any, Any]],
                shape: tuple[int, int], clock: StageClock
                ) -> tuple[tuple[Any, Any, Any, Any], np.ndarray, int]:
        """Seed and GPT: ``send(shifts, prior)`` puts the pair, the host GPT shift table and
        the road fit's prior (road_model.prior_params) on the backend and returns (left,
        right, shifts, prior); where no road model carries over, the coarse seed pass fits one
        on the pair and the shifts and prior go again. Returns the backend (left, right,
        shifts, prior), the host shifts (int32 (3, H)) and the level count of the band."""
        seeding = self.config.gpt_enabled and self.road is None
        with clock.stage("gpt"):
            shifts, levels = self.band(shape)
            left, right, shifts_dev, prior_dev = send(shifts, self.prior())
        if seeding:
            with clock.stage("seed"):
                self.road = self._seed(left, right)
                self._axis_sine = float(measure.road_normal(self.road, self.calibration)[2])
                shifts, levels = self.band(shape)
                shifts_dev = self.backend.upload(shifts)
                prior_dev = self.backend.upload(self.prior())
        return (left, right, shifts_dev, prior_dev), shifts, levels

    def prior(self) -> np.ndarray:
        """The road fit's prior (host float64 (PRIOR_PARAMS,), road_model.prior_params): the
        current road model and the distance from it that a turn of the camera by
        ``road_prior_change_deg`` allows, used where at least ``min_road_inlier_fraction`` of
        the valid pixels lie that close; none without a road model or with the change 0."""
        road, change = self.road, self.config.road_prior_change_deg
        if road is None or change <= 0:
            return road_model.prior_params(None, 0.0)
        return road_model.prior_params(
            road, road_model.prior_tolerance_px(road, self.calibration, change),
            self.config.min_road_inlier_fraction)

    def stages(self, left: Any, right: Any, shifts: Any, prior: Any, levels: int,
               report: FrameReport, clock: StageClock, checkpoint: Checkpoint,
               seeded: bool = False) -> FrameArrays:
        """SGM to measure on a prepared pair (``prior``: the road fit's, see :meth:`prior`).
        Small results go into ``report`` (valid count,
        road fit, threshold search, component counts, pothole sums); nothing is read back but
        what ``checkpoint`` reads. Where the seed pass ran on the pair (``seeded``), the road is
        fitted twice (:meth:`fit_road`)."""
        config, backend = self.config, self.backend
        xp = backend.xp
        with clock.stage("sgm"):
            disparity = self.match(left, right, shifts, levels)
        valid = xp.isfinite(disparity)
        with clock.stage("road"):
            report.valid_count[...] = xp.count_nonzero(valid)
            self.fit_road(disparity, prior, seeded, report.road, report.road_params)
        road = checkpoint.road_fitted(report)
        with clock.stage("dt"):
            transformed = transform_disparity(backend, disparity, road, config.delta_dt_px)
        # the threshold search needs D2 only: on the GPU it runs beside SLIC
        with clock.stage("threshold"), backend.side_stream() as join_threshold:
            thresholding.threshold_search(backend, transformed, config.histogram_bin_px,
                                          config.delta_dt_px, result=report.threshold)
        with clock.stage("slic"):
            region_px = self.region_size(transformed.shape[1])
            found = superpixels.superpixels(backend, transformed, region_px,
                                            config.slic_compactness, config.slic_iterations,
                                            config.slic_downsample)
        with clock.stage("threshold"):
            join_threshold()
            pixels = config.threshold_mode == "pixels"
            observe = partial(
                thresholding.observation, backend, transformed.shape, region_px,
                config.slic_downsample, report.road_params, report.road, self.calibration,
                config.delta_pd_m, config.delta_pd_px if pixels else 0.0,
                config.threshold_noise_sigmas, max_depth_m=config.max_threshold_m)
            observed, drops = observe(observed_range=report.observed_range)
            drop = config.delta_pd_px if pixels else drops
            searched, local, bumps, depressed = observed, None, None, None
            significant = None
            if config.road_reference != "local" and config.corner_significance > 0:
                significant = local_road.deeper(observed, found.means, config.delta_dt_px,
                                                0.0, drop, config.corner_significance)
            if config.road_reference == "local":
                ahead, ahead_drops = observe(max_depth_m=math.inf)
                usable = ahead & (found.valid_fraction > config.superpixel_min_valid_fraction)
                local, noise = local_road.offsets(
                    backend, found.means, usable, ahead_drops, transformed.shape, region_px,
                    config.slic_downsample, report.road_params, self.calibration,
                    config.delta_dt_px, config.local_road_radius_m, report.road)
                superpixel_noise = noise
                if not pixels:
                    if config.texture_noise:
                        superpixel_noise = noise * texture.deficit(
                            backend, left, valid, found.labels, found.count, ahead)
                    searched, drop = observe(noise_px=superpixel_noise)
                tests = local_road.local_tests(
                    backend, found.means, local, noise, drop, searched, config.delta_dt_px,
                    config.refine_depth_fraction, config.corner_significance,
                    config.bump_noise_sigmas)
                drop, depressed = tests.drop, tests.depressed
                significant, bumps = tests.significant, tests.bumps
            selected = thresholding.select(
                backend, report.threshold, config.histogram_bin_px, config.delta_dt_px,
                thresholding.reference_for(config.threshold_reference, config.threshold_mode),
                found.means,
                xp.where(searched, found.valid_fraction, xp.float32(-1)), drop,
                config.superpixel_min_valid_fraction)
            candidate = xp.take(selected, found.grid)
            flagged = None
            if config.photometric_factor > 0:
                disagreement, _ = superpixels.superpixel_means(
                    backend, photometric.disagreement(backend, left, right, disparity),
                    found.labels, found.count)
                flagged = photometric.inconsistent(backend, disagreement, searched & ~selected,
                                                   config.photometric_factor)
        frame = FrameArrays(disparity, transformed, valid, found, candidate, None, observed,
                            drops, region_px, local, flagged, bumps, searched, depressed,
                            significant)
        frame.labels = self.label_and_measure(frame, road, report, clock)
        return frame

    def label_and_measure(self, frame: FrameArrays, road: road_model.RoadModel | Any,
                          report: FrameReport, clock: StageClock) -> Any:
        """Components, refinement and measure of ``frame``'s candidate mask into ``report``
        (labels of up to ``report.capacity`` components; more set its overflow count): the
        labels after the area filter."""
        config, backend, found = self.config, self.backend, frame.superpixels
        with clock.stage("components"):
            labels = components.pothole_components(
                backend, frame.candidate, frame.valid, found.labels, found.count,
                config.min_pothole_superpixels, config.slic_downsample,
                report.capacity, report.components, frame.inconsistent, frame.bumps)
        with clock.stage("refine"):
            shift = None if frame.local is None else local_road.pixel_offsets(
                backend, frame.local, frame.disparity.shape, frame.region_px,
                config.slic_downsample)
            filled, smoothed = refine.smooth(backend, frame.disparity, shift)
            labels = refine.refine_labels(
                backend, labels, filled, road, config.delta_dt_px, found.labels, frame.drops,
                frame.searched, refine.radius(frame.region_px),
                config.refine_depth_fraction)
            labels = refine.extend_occluded(backend, labels, filled, smoothed, road,
                                            found.labels, frame.searched)
            labels = components.join_pieces(backend, labels, refine.radius(frame.region_px) // 2,
                                            report.components_kept, config.slic_downsample,
                                            found.grid, frame.depressed, frame.region_px)
        with clock.stage("measure"):
            corners = components.far_corners(backend, frame.valid, config.corner_fraction)
            measure.measure(backend, labels, report.capacity, smoothed, road,
                            self.calibration, report.sums, report.extremes, corners,
                            found.labels, frame.significant)
            return measure.area_filter(backend, labels, report.sums, report.components_kept,
                                       report.capacity, config.min_pothole_area_m2,
                                       report.kept_after_area, config.min_pothole_depth_m,
                                       config.max_pothole_depth_m)

    def checked_road(self, road_report: np.ndarray, valid_count: float,
                     pixels: int) -> road_model.RoadModel:
        """The road model of a host copy of a frame's road fit report once the frame passes the
        checks (enough valid disparities, a fit, enough inliers); kept for the next frame's
        band. A frame that fails them raises NoTextureError or NoRoadError; the last accepted
        road model carries on to the next frame, unless the frame before was refused too or no
        frame was accepted since the last seed, when the pipeline resets (the next frame is
        seeded)."""
        config = self.config
        try:
            if valid_count / pixels < config.min_valid_fraction:
                raise NoTextureError(
                    f"only {valid_count / pixels:.1%} of pixels got a disparity (need "
                    f"{config.min_valid_fraction:.0%}): the images lack texture, are not a "
                    "rectified pair, or the road is outside max_disparity_px")
            road = road_model.model_from_report(road_report, config.road_model,
                                                config.road_quadratic_gain)
            if road.inlier_fraction < config.min_road_inlier_fraction:
                raise NoRoadError(
                    f"no road plane: only {road.inlier_fraction:.0%} of the valid disparities "
                    f"fit one (need {config.min_road_inlier_fraction:.0%}); is the camera "
                    "looking at the road?")
        except PotholeError:
            accepted, refused = self._accepted, self._refused + 1
            self.reset()
            if refused == 1 and accepted is not None:
                self.road, self._accepted, self._refused = accepted, accepted, refused
            raise
        self._refused = 0
        self.road = self._accepted = road
        return road

    def band(self, shape: tuple[int, int]) -> tuple[np.ndarray, int]:
        """GPT shift table (int32 (3, H), host; stages/perspective.py) and level count from the
        current road model (no shifts and the full range without one or with GPT off); worked
        out once per road model and image size."""
        config = self.config
        road = self.road if config.gpt_enabled else None
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

    def region_size(self, width: int) -> int:
        """The SLIC grid step (full-resolution px) on images ``width`` px wide
        (superpixels.region_size of ``slic_region_size_px``), shrunk for the angle between the
        optical axis and the road that the last seed pass fitted (the rig's; a full step
        without one, as with ``gpt_enabled`` off): fixed from one seed to the next."""
        return superpixels.region_size(self.config.slic_region_size_px, width,
                                       self._axis_sine)

    def shift_mode(self) -> str:
        """pixel or row: the GPT shifts ``gpt_shift`` asks for (auto: pixel with the census
        matcher, row with OpenCV SGBM)."""
        mode = self.config.gpt_shift
        if mode != "auto":
            return mode
        return "pixel" if self.config.matcher == "census" else "row"

    def fit_road(self, disparity: Any, prior: Any, seeded: bool, report: Any = None,
                 params: Any = None) -> tuple[Any, Any]:
        """The road fit stage on a frame's backend D1 with the backend ``prior``: the fit report
        and parameters (road_model.fit), in ``report`` and ``params`` where given. Where the
        seed pass ran on the frame (``seeded``) the fit runs again with its own road as the
        prior: the coarse seed only finds the road, and where the frame's road lies off it
        (curvature the coarse pass made up, a plane tilted by its noise) the pixels near the
        seed hold part of the road only; the second fit takes those near the first fit's
        road."""
        config = self.config
        options = dict(stride=config.road_fit_stride, rounds=config.road_fit_rounds,
                       outlier_k=config.road_outlier_k, kind=config.road_model,
                       quadratic_gain=config.road_quadratic_gain, report=report, params=params)
        report, params = road_model.fit(self.backend, disparity, prior=prior, **options)
        if seeded:
            report, params = road_model.fit(
                self.backend, disparity, prior=road_model.refit_prior(self.backend.xp, params,
                                                                      prior), **options)
        return report, params

    def _seed(self, left: Any, right: Any) -> road_model.RoadModel:
        """The seed pass (stages/seed.py) on the (backend) pair."""
        return seed.seed_road(self.backend, self._seed_matcher, left, right, self.config,
                              self.calibration)
