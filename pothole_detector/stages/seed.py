"""The seed pass: a road model for a pair with no road model to go on (the first frame, after a
reset), from a coarse full-range match of the reduced pair."""

from __future__ import annotations

from typing import Any

from ..backend import Backend
from ..errors import NoRoadError, NoTextureError, PotholeError
from ..params import Config
from . import matching, perspective, road_model

# columns the seed pass works on where coarse_scale is 0 (auto)
SEED_COLUMNS = 512


def seed_road(backend: Backend, matcher: matching.Matcher, left: Any, right: Any,
              config: Config) -> road_model.RoadModel:
    """Road model from a full-range match of the (backend, uint8 HxW) pair reduced by the
    seed scale (``coarse_scale``, or from the image width where it is 0). Where that finds too
    few disparities or no road, it tries again without the left-right check (over a range near
    half the image width the check leaves few pixels whose partner was matched; the robust
    road fit rejects the outliers it would), then on the pair reduced half as much. Raises the
    last try's NoTextureError or NoRoadError."""
    scale = seed_scale(left.shape[1], config.coarse_scale)
    tries = dict.fromkeys(((scale, True), (scale, False), (max(1, scale // 2), False)))
    failure: PotholeError | None = None
    for factor, checked in tries:
        try:
            return seed_at(backend, matcher, left, right, config, factor, checked)
        except (NoTextureError, NoRoadError) as exc:
            failure = exc
    assert failure is not None
    raise failure


def seed_at(backend: Backend, matcher: matching.Matcher, left: Any, right: Any, config: Config,
            scale: int, checked: bool) -> road_model.RoadModel:
    """One try of the seed: the pair reduced by ``scale``, matched over up to half the reduced
    width, with the left-right check where ``checked``. Enough valid disparities are asked of
    the columns that the range lets match."""
    xp = backend.xp
    small_left = matching.downsample(xp, left, scale)
    small_right = matching.downsample(xp, right, scale)
    half_width = small_left.shape[1] // 2
    levels = perspective.round_up_levels(min(config.max_disparity_px / scale, half_width))
    shifts = xp.asarray(perspective.no_shifts(small_left.shape[0]))
    coarse = matcher(small_left, small_right, shifts, levels,
                     config if checked else config.replace(lr_max_diff_px=-1),
                     block_size=min(config.sgm_block_size, 5))
    matchable = coarse[:, min(levels, coarse.shape[1] - 1):]
    if float(xp.isfinite(matchable).mean()) < config.min_valid_fraction:
        raise NoTextureError(
            "the coarse seed pass found almost no disparities: the images lack texture, "
            "are not a rectified pair, or the road is beyond max_disparity_px"
        )
    return road_model.fit_model(
        backend, coarse, stride=1, rounds=config.road_fit_rounds,
        outlier_k=config.road_outlier_k, kind=config.road_model,
        quadratic_gain=config.road_quadratic_gain, coordinate_scale=float(scale),
        coordinate_offset=(scale - 1.0) / 2.0)


def seed_scale(width: int, coarse_scale: int) -> int:
    """The seed pass's reduction of an image ``width`` px wide: ``coarse_scale``, or where that
    is 0, the factor that leaves the seed about SEED_COLUMNS columns."""
    if coarse_scale > 0:
        return coarse_scale
    return max(1, round(width / SEED_COLUMNS))
