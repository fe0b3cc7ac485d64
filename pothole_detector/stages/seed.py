"""The seed pass: a road model for a pair with no road model to go on (the first frame, after a
reset), from a coarse full-range match of the reduced pair."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..backend import Backend, to_host
from ..errors import NoRoadError, NoTextureError, PotholeError
from ..calibration import StereoCalibration
from ..params import Config
from . import matching, perspective, road_model

# columns the seed pass works on where coarse_scale is 0 (auto)
SEED_COLUMNS = 512
# the road region search: plane hypotheses, points scored, inlier distance (coarse px)
REGION_HYPOTHESES = 256
REGION_POINTS = 16384
REGION_TOLERANCE_PX = 1.0
# the share of the valid coarse pixels the region must hold, as a fraction of
# min_road_inlier_fraction (the coarse pass is sparse and noisier than the frame's)
REGION_MIN_SHARE = 0.4
# the largest roll (deg) of the camera about its optical axis against the road
MAX_ROLL_DEG = 45.0


def seed_road(backend: Backend, matcher: matching.Matcher, left: Any, right: Any,
              config: Config, calibration: StereoCalibration) -> road_model.RoadModel:
    """Road model from a full-range match of the (backend, uint8 HxW) pair reduced by the
    seed scale (``coarse_scale``, or from the image width where it is 0), matched up to
    ``max_disparity_px``. Where that finds too few disparities or no road, it tries again
    without the left-right check (over a range near half the image width the check leaves few
    pixels whose partner was matched; the robust road fit rejects the outliers it would), then
    over the widest range, half the reduced width (a rig whose near road lies beyond
    ``max_disparity_px`` matches it at random there, which can hide the road's plane), then on
    the pair reduced half as much. Raises the last try's NoTextureError or NoRoadError."""
    scale = seed_scale(left.shape[1], config.coarse_scale)
    capped = config.max_disparity_px / scale < (left.shape[1] // scale) // 2
    tries = dict.fromkeys(((scale, True, False), (scale, False, False), (scale, False, capped),
                           (max(1, scale // 2), False, False)))
    failure: PotholeError | None = None
    for factor, checked, widest in tries:
        try:
            return seed_at(backend, matcher, left, right, config, factor, checked,
                           calibration, widest)
        except (NoTextureError, NoRoadError) as exc:
            failure = exc
    assert failure is not None
    raise failure


def seed_at(backend: Backend, matcher: matching.Matcher, left: Any, right: Any, config: Config,
            scale: int, checked: bool, calibration: StereoCalibration, widest: bool = False
            ) -> road_model.RoadModel:
    """One try of the seed: the pair reduced by ``scale``, matched up to ``max_disparity_px``
    but over half the reduced width at most (over all of that where ``widest``), with the
    left-right check where ``checked``. Enough valid disparities are asked of the columns
    that the range lets match, and a road plane that holds enough of them and, as a share of
    those columns' pixels, at least ``min_valid_fraction`` (an unrelated pair's scattered
    matches meet some plane too)."""
    xp = backend.xp
    small_left = matching.downsample(xp, left, scale)
    small_right = matching.downsample(xp, right, scale)
    half_width = small_left.shape[1] // 2
    reach = half_width if widest else min(config.max_disparity_px / scale, half_width)
    levels = perspective.round_up_levels(reach)
    shifts = xp.asarray(perspective.no_shifts(small_left.shape[0]))
    coarse = matcher(small_left, small_right, shifts, levels,
                     config if checked else config.replace(lr_max_diff_px=-1),
                     block_size=min(config.sgm_block_size, 5))
    matchable = coarse[:, min(levels, coarse.shape[1] - 1):]
    valid_fraction = float(xp.isfinite(matchable).mean())
    if valid_fraction < config.min_valid_fraction:
        raise NoTextureError(
            "the coarse seed pass found almost no disparities: the images lack texture, "
            "are not a rectified pair, or the road is beyond max_disparity_px"
        )
    offset = (scale - 1.0) / 2.0
    region = road_region(to_host(coarse), float(scale), offset, calibration,
                         config.max_camera_height_m)
    need = config.min_road_inlier_fraction * REGION_MIN_SHARE
    share = 0.0 if region is None else region.inlier_fraction
    if share < need or share * valid_fraction < config.min_valid_fraction:
        raise NoRoadError(
            f"no road plane in the coarse seed pass: {share:.0%} of the disparities lie on one "
            f"(need {need:.0%}), {share * valid_fraction:.1%} of the matchable pixels (need "
            f"{config.min_valid_fraction:.0%}); is the camera looking at the road?")
    prior = road_model.prior_params(region, 2.0 * REGION_TOLERANCE_PX * scale)
    return road_model.fit_model(
        backend, coarse, stride=1, rounds=config.road_fit_rounds,
        outlier_k=config.road_outlier_k, kind=config.road_model,
        quadratic_gain=config.road_quadratic_gain, coordinate_scale=float(scale),
        coordinate_offset=offset, prior=backend.upload(prior))


def road_region(coarse: np.ndarray, scale: float, offset: float,
                calibration: StereoCalibration, max_height_m: float
                ) -> road_model.RoadModel | None:
    """The road's plane in a coarse disparity map (host float32 h x w px, NaN invalid; pixel
    (i, j) at full-resolution (u, v) = scale (j, i) + offset, disparity x scale), found before
    any fit so that cars, walls, trees and sky do not pull it: of REGION_HYPOTHESES planes
    through three valid pixels each, those that can be a road under the camera (disparity
    growing down the image, roll within MAX_ROLL_DEG, the camera at most ``max_height_m``
    above the plane: road_model.params_height), the one with the most pixels within
    REGION_TOLERANCE_PX of it, less the pixels lying well behind it (the camera cannot see
    through the road; potholes are small), each pixel weighted by its row (the road is the
    lower part of the view). A planar RoadModel in full-resolution px whose inlier fraction is
    the share of the valid pixels within REGION_TOLERANCE_PX of it, or None where no plane can
    be the road."""
    rows, cols = np.nonzero(np.isfinite(coarse))
    if rows.size < 3:
        return None
    rng = np.random.default_rng(0)
    if rows.size > REGION_POINTS:
        keep = rng.choice(rows.size, REGION_POINTS, replace=False)
        rows, cols = rows[keep], cols[keep]
    points = np.stack([np.ones(rows.size), cols * scale + offset, rows * scale + offset], 1)
    values = coarse[rows, cols].astype(np.float64) * scale
    picks = rng.integers(0, rows.size, (REGION_HYPOTHESES, 3))
    systems = points[picks]
    solvable = np.abs(np.linalg.det(systems)) > 1e-6
    planes = np.zeros((REGION_HYPOTHESES, 3))
    planes[solvable] = np.linalg.solve(systems[solvable],
                                       values[picks][solvable][..., None])[..., 0]
    alpha, beta, gamma = planes.T
    slope = np.hypot(beta, gamma)
    layout = road_model.PARAM_LAYOUT
    params = np.zeros((road_model.ROAD_PARAMS, planes.shape[0]))
    with np.errstate(divide="ignore", invalid="ignore"):
        params[[layout["ROAD_A0"], layout["ROAD_A1"], layout["ROAD_COS"], layout["ROAD_SIN"]]] \
            = alpha, slope, gamma / slope, -beta / slope
        height_m = road_model.params_height(np, params, calibration)
    roll_deg = np.degrees(np.arctan2(-beta, gamma))
    plausible = solvable & (gamma > 0) & (np.abs(roll_deg) <= MAX_ROLL_DEG) \
        & (height_m <= max_height_m)
    if not plausible.any():
        return None
    planes = planes[plausible]
    expected = planes @ points.T
    residual = values[None, :] - expected
    tolerance = REGION_TOLERANCE_PX * scale
    behind = (residual < -3.0 * tolerance) & (expected > 0)
    lower = points[:, 2] + 1.0
    score = ((np.abs(residual) <= tolerance).astype(np.float64) - behind) @ lower
    best = int(np.argmax(score))
    alpha, beta, gamma = planes[best]
    share = float(np.mean(np.abs(residual[best]) <= tolerance))
    return road_model.RoadModel(np.float64(alpha), np.float64(math.hypot(beta, gamma)),
                                math.atan2(-beta, gamma), inlier_fraction=share)


def seed_scale(width: int, coarse_scale: int) -> int:
    """The seed pass's reduction of an image ``width`` px wide: ``coarse_scale``, or where that
    is 0, the factor that leaves the seed about SEED_COLUMNS columns."""
    if coarse_scale > 0:
        return coarse_scale
    return max(1, round(width / SEED_COLUMNS))
