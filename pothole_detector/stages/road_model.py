"""Road model: v-disparity with roll, fitted from nine moments with robust refit rounds.

Road disparity is ``f(u, v) = p(u, v) + q(u, v)``: the plane ``p = a0 + a1 t`` with the
rotated row ``t = v cos(phi) - u sin(phi)`` and a correction ``q``. The paper's planar model has
``q = 0``. The quadratic model is the disparity of a road whose height off the plane is any
quadratic in road coordinates (camber, a crown, a crest or sag, a twist), fitted to the planar
model's inliers: a point h below the plane has disparity p (1 - h / H) (H: the camera's
height), and road coordinates are (u, 1) / p up to an affine map, so the quadratic part of h
adds multiples of u^2 / p, u / p and 1 / p, and its linear part re-tilts the plane:
``q = c0 + c1 x + c2 y + w (c5 + x (c4 + x c3))`` with x = u / 1000, y = v / 1000 and
``w = 100 / max(p, 8)``: a camber's drop grows like u^2 / p towards the horizon. w stops growing
at 8 px of road disparity, where 0.2 px of matching noise is 1/40 of the disparity and no
pothole is resolved on any rig; beyond it the model would chase walls and trees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import numba
import numpy as np

from ..backend import Backend, to_host
from ..errors import NoRoadError

# The quadratic correction's coordinates are u and v divided by CURVATURE_SCALE_PX and its
# inverse disparity is INVERSE_SCALE_PX / max(p, MIN_ROAD_DISPARITY_PX) (px), for conditioning
# and to stay finite at the horizon. Where the correction exceeds MAX_CURVATURE_PERCENT of the
# plane's disparity the model extrapolates past the road it was fitted on, and the road there is
# not observed. The kernels take them as defines (ROAD_DEFINES).
ROAD_CONSTANTS = {"CURVATURE_SCALE_PX": 1000, "INVERSE_SCALE_PX": 100,
                  "MIN_ROAD_DISPARITY_PX": 8, "MAX_CURVATURE_PERCENT": 50}
CURVATURE_SCALE_PX = float(ROAD_CONSTANTS["CURVATURE_SCALE_PX"])
INVERSE_SCALE_PX = float(ROAD_CONSTANTS["INVERSE_SCALE_PX"])
MIN_ROAD_DISPARITY_PX = float(ROAD_CONSTANTS["MIN_ROAD_DISPARITY_PX"])
MAX_CURVATURE_SHARE = ROAD_CONSTANTS["MAX_CURVATURE_PERCENT"] / 100.0
# Columns per row at which the band and the row extremes evaluate the road.
ROW_SAMPLES = 9

# The road fit report (float64 (ROAD_REPORT,)): status (0 fitted, else a key of FIT_FAILURES),
# valid count, planar a0, a1, roll (rad), planar inliers and sigma (px), curvature c0..c5,
# quadratic inliers and sigma (px). Read and written by name here and in kernels/road.cu.
FIT_LAYOUT = {"FIT_STATUS": 0, "FIT_VALID": 1, "FIT_A0": 2, "FIT_A1": 3, "FIT_ROLL": 4,
              "FIT_PLANAR_INLIERS": 5, "FIT_PLANAR_SIGMA": 6, "FIT_CURVATURE": 7,
              "FIT_QUADRATIC_INLIERS": 13, "FIT_QUADRATIC_SIGMA": 14, "ROAD_REPORT": 15}
ROAD_REPORT = FIT_LAYOUT["ROAD_REPORT"]
# A road model as the kernels read it (RoadModel.kernel_params, float64 (ROAD_PARAMS,)): a0, a1,
# cos(roll), sin(roll), c0..c5 (zeros for a planar model), curved (1.0 for a quadratic model).
PARAM_LAYOUT = {"ROAD_A0": 0, "ROAD_A1": 1, "ROAD_COS": 2, "ROAD_SIN": 3, "ROAD_C0": 4,
                "ROAD_CURVED": 10, "ROAD_PARAMS": 11}
ROAD_PARAMS = PARAM_LAYOUT["ROAD_PARAMS"]
ROAD_DEFINES = {**PARAM_LAYOUT, **ROAD_CONSTANTS}
# A prior for the fit (float64 (PRIOR_PARAMS,)): a road model's kernel parameters, the distance
# (px) from it within which the fit looks for the road (0: no prior), and the share of the valid
# pixels that must lie that close for the prior to be used (else it is stale: every valid pixel).
PRIOR_TOLERANCE = ROAD_PARAMS
PRIOR_MIN_SHARE = ROAD_PARAMS + 1
PRIOR_PARAMS = ROAD_PARAMS + 2
# the narrowest band about the prior (px): the matcher's disparity noise on any rig
MIN_PRIOR_TOLERANCE_PX = 2.0
_F = FIT_LAYOUT


@dataclass(frozen=True)
class RoadModel:
    """Road disparity model in full-resolution pixel coordinates of the left image.

    ``curvature`` holds (c0, c1, c2, c3, c4, c5) of
    ``q = c0 + c1 x + c2 y + w (c5 + x (c4 + x c3))`` with x = u / 1000, y = v / 1000 and
    w = 100 / max(p(u, v), 8) (the module's docstring).
    """

    a0: float
    a1: float
    roll_rad: float
    curvature: tuple[float, ...] = (0.0,) * 6
    inlier_fraction: float = 1.0
    sigma_px: float = 0.0
    kind: str = "planar"

    @property
    def roll_deg(self) -> float:
        return math.degrees(self.roll_rad)

    def rotated_row(self, xp: Any, u: Any, v: Any) -> Any:
        """t = v cos(phi) - u sin(phi) (px) for coordinate arrays u, v."""
        return v * math.cos(self.roll_rad) - u * math.sin(self.roll_rad)

    def at(self, xp: Any, u: Any, v: Any) -> Any:
        """Road disparity f(u, v) (px) at coordinate arrays u, v (broadcast)."""
        planar = self.a0 + self.a1 * self.rotated_row(xp, u, v)
        if self.kind == "planar":
            return planar
        return planar + _poly(xp, self.curvature, u / CURVATURE_SCALE_PX,
                              v / CURVATURE_SCALE_PX, planar)

    def disparity(self, xp: Any, height: int, width: int, dtype: Any = np.float32) -> Any:
        """Road disparity f(u, v) over an HxW grid (px), as ``dtype``; on the host a Numba
        kernel with :meth:`at`'s float64 arithmetic (the same bits)."""
        if xp is np:
            grid = np.empty((height, width), dtype=dtype)
            _grid_on_host(float(self.a0), float(self.a1), math.cos(self.roll_rad),
                          math.sin(self.roll_rad), self.kind != "planar",
                          np.asarray(self.curvature, dtype=np.float64), grid)
            return grid
        v = xp.arange(height, dtype=xp.float64)[:, None]
        u = xp.arange(width, dtype=xp.float64)[None, :]
        return self.at(xp, u, v).astype(dtype)

    def row_extremes(self, xp: Any, height: int, width: int) -> tuple[Any, Any]:
        """Per-row minimum and maximum of f over u in [0, width-1]; two float64 arrays (H,),
        from f at ROW_SAMPLES columns (exact for a planar model: the ends)."""
        values = self.row_samples(height, width)[1]
        return xp.asarray(values.min(axis=1)), xp.asarray(values.max(axis=1))

    def row_samples(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """(columns (S,), f there per row (H, S)) on the host: both ends and, for a curved
        model, ROW_SAMPLES columns evenly spread (px)."""
        samples = ROW_SAMPLES if self.kind != "planar" else 2
        columns = np.linspace(0.0, float(max(width - 1, 0)), samples)
        rows = np.arange(height, dtype=np.float64)[:, None]
        return columns, self.at(np, columns[None, :], rows)

    def kernel_params(self) -> np.ndarray:
        """The model as the GPU kernels read it (float64 (ROAD_PARAMS,)): a0, a1, cos(roll),
        sin(roll), c0..c5 (zeros for a planar model), curved (1.0 for a quadratic model)."""
        curved = self.kind != "planar"
        layout = PARAM_LAYOUT
        params = np.zeros(ROAD_PARAMS)
        params[[layout["ROAD_A0"], layout["ROAD_A1"], layout["ROAD_COS"], layout["ROAD_SIN"],
                layout["ROAD_CURVED"]]] = (self.a0, self.a1, math.cos(self.roll_rad),
                                           math.sin(self.roll_rad), float(curved))
        if curved:
            params[layout["ROAD_C0"]:layout["ROAD_C0"] + 6] = self.curvature
        return params

    def as_dict(self) -> dict:
        return {"a0": self.a0, "a1": self.a1, "roll_deg": self.roll_deg,
                "inlier_fraction": self.inlier_fraction, "sigma_px": self.sigma_px,
                "model": self.kind, "curvature": list(self.curvature)}


@numba.njit(parallel=True, cache=True)
def _grid_on_host(a0: float, a1: float, cos_roll: float, sin_roll: float, curved: bool,
                  c: np.ndarray, out: np.ndarray) -> None:
    """RoadModel.at over every pixel of ``out`` (HxW), rows on Numba's threads: the plane
    a0 + a1 (v cos - u sin), plus for a curved model the correction of :func:`_poly`, in
    float64, written as ``out``'s dtype."""
    height, width = out.shape
    for v in numba.prange(height):
        along = np.float64(v) * cos_roll
        y = np.float64(v) / CURVATURE_SCALE_PX
        for u in range(width):
            planar = a0 + a1 * (along - np.float64(u) * sin_roll)
            if curved:
                x = np.float64(u) / CURVATURE_SCALE_PX
                floor = planar if not planar < MIN_ROAD_DISPARITY_PX else MIN_ROAD_DISPARITY_PX
                inverse = INVERSE_SCALE_PX / floor
                planar = planar + (c[0] + x * c[1] + y * c[2]
                                   + inverse * (c[5] + x * (c[4] + x * c[3])))
            out[v, u] = planar


def _inverse(xp: Any, planar: Any) -> Any:
    """w of the correction q where the plane's disparity is ``planar`` (px)."""
    return INVERSE_SCALE_PX / xp.maximum(planar, MIN_ROAD_DISPARITY_PX)


def _poly(xp: Any, c: Any, x: Any, y: Any, planar: Any) -> Any:
    """The correction q at x = u / 1000, y = v / 1000 where the plane's disparity is
    ``planar`` (px)."""
    inverse = _inverse(xp, planar)
    return c[0] + x * c[1] + y * c[2] + inverse * (c[5] + x * (c[4] + x * c[3]))


def moments(xp: Any, disparity: Any, mask: Any, u: Any, v: Any) -> np.ndarray:
    """The nine moments (n, Su, Sv, Sd, Suu, Svv, Suv, Sud, Svd) of the masked pixels.

    ``disparity`` and ``mask`` are HxW, ``u`` (1xW) and ``v`` (Hx1) the pixel coordinates.
    One matrix product; returns a float64 host array of 9 numbers (the only readback).
    """
    return _moments_of(xp, _basis(xp, disparity, u, v), mask)


def _basis(xp: Any, disparity: Any, u: Any, v: Any) -> Any:
    """(N, 4) float64 columns 1, u, v, d (d = 0 where invalid) of an HxW map."""
    shape = disparity.shape
    d = xp.where(xp.isfinite(disparity), disparity, 0)
    return xp.stack([xp.ones(shape), xp.broadcast_to(u, shape), xp.broadcast_to(v, shape), d],
                    axis=-1).reshape(-1, 4).astype(xp.float64)


def _moments_of(xp: Any, basis: Any, mask: Any) -> np.ndarray:
    second = to_host((basis * mask.reshape(-1, 1)).T @ basis)
    return np.array([second[0, 0], second[0, 1], second[0, 2], second[0, 3], second[1, 1],
                     second[2, 2], second[1, 2], second[1, 3], second[2, 3]])


def solve_roll(m: np.ndarray) -> tuple[float, float, float, float]:
    """Least-squares (a0, a1, phi, residual) of d = a0 + a1 (v cos phi - u sin phi) from the
    nine moments. dE/dphi = 0 has two roots (the maximiser of the explained variance and its
    orthogonal); the one with the smaller residual is kept. The residual leaves out the sum of
    d^2, which is the same for both."""
    n, su, sv, sd, suu, svv, suv, sud, svd = (float(x) for x in m)
    if n < 3:
        raise RoadFitFailed(1)
    mu, mv, md = su / n, sv / n, sd / n
    cuu, cvv, cuv = suu - n * mu * mu, svv - n * mv * mv, suv - n * mu * mv
    cud, cvd = sud - n * mu * md, svd - n * mv * md
    a = np.array([[cvv, cuv], [cuv, cuu]])
    b = np.array([cvd, cud])
    if abs(np.linalg.det(a)) <= 1e-9 * max(cuu * cvv, 1e-300):
        raise RoadFitFailed(2)
    w_max = np.linalg.solve(a, b)
    w_orth = np.array([-b[1], b[0]]) if np.any(b) else np.array([1.0, 0.0])
    best = None
    for w in (w_max, w_orth):
        norm = math.hypot(w[0], w[1])
        if norm == 0:
            continue
        c, s = w[0] / norm, -w[1] / norm
        if c < 0:
            c, s = -c, -s
        var_t = c * c * cvv - 2 * c * s * cuv + s * s * cuu
        cov_td = c * cvd - s * cud
        a1 = cov_td / var_t if var_t > 0 else 0.0
        residual = -a1 * cov_td
        if best is None or residual < best[3]:
            a0 = md - a1 * (c * mv - s * mu)
            best = (a0, a1, math.atan2(s, c), residual)
    assert best is not None
    return best


def _curvature_design(xp: Any, shape: tuple[int, int], u: Any, v: Any, planar: Any) -> Any:
    """(N, 6) float64 columns 1, x, y, x^2 w, x w, w of q (RoadModel) with x = u / 1000,
    y = v / 1000 and w from the HxW plane disparity ``planar`` (px)."""
    x = xp.broadcast_to(u / CURVATURE_SCALE_PX, shape).reshape(-1)
    y = xp.broadcast_to(v / CURVATURE_SCALE_PX, shape).reshape(-1)
    inverse = _inverse(xp, planar).reshape(-1)
    return xp.stack([xp.ones_like(x), x, y, x * x * inverse, x * inverse, inverse], axis=1)


def _fit_curvature(xp: Any, design: Any, residual: Any, mask: Any) -> tuple[float, ...]:
    """Least-squares quadratic q(u, v) of the planar residual over the masked pixels."""
    weighted = design * mask.reshape(-1, 1)
    target = xp.where(mask, residual, 0).reshape(-1, 1)
    system = to_host(weighted.T @ xp.concatenate([design, target], axis=1))
    return tuple(float(c) for c in np.linalg.lstsq(system[:, :6], system[:, 6], rcond=None)[0])


def masked_median(xp: Any, values: Any, mask: Any) -> tuple[Any, Any]:
    """The median of ``values`` where the bool ``mask`` holds (the mean of the two middle ones
    for an even count; meaningless for none) and that count, as 0-d backend arrays: the others
    set to infinity, the elements at the two middle places of the masked count in sorted
    order. On the device a sort and a take at the count, nothing read back; on the host a
    partition at those places (the same elements, without sorting the rest)."""
    filled = xp.where(mask, values, xp.inf).reshape(-1)
    count = xp.count_nonzero(mask)
    if xp is np:
        places = (max((int(count) - 1) // 2, 0), min(int(count) // 2, filled.size - 1))
        ordered = np.partition(filled, places)
        low, high = ordered[places[0]], ordered[places[1]]
    else:
        ordered = xp.sort(filled)
        low = xp.take(ordered, xp.maximum((count - 1) // 2, 0))
        high = xp.take(ordered, xp.minimum(count // 2, ordered.size - 1))
    return (low + high) / 2, count


def _robust_sigma(xp: Any, residual: Any, mask: Any) -> Any:
    """1.4826 x median absolute residual of the masked pixels (px), as a 0-d backend array
    (0 when nothing is masked); no host readback."""
    median, count = masked_median(xp, xp.abs(residual), mask)
    return xp.where(count > 0, 1.4826 * median, 0.0)


class RoadFitFailed(NoRoadError):
    """A fit with too few or degenerate disparities; ``status`` as in the fit report."""

    def __init__(self, status: int) -> None:
        super().__init__(FIT_FAILURES[status])
        self.status = status


# fit report status -> why the fit failed (status 0: fitted)
FIT_FAILURES = {
    1: "fewer than 3 valid disparities: no road to fit",
    2: "valid disparities lie on a line: the road plane is undetermined",
}


def fit_report(xp: Any, disparity: Any, *, stride: int = 1, rounds: int = 3,
               outlier_k: float = 2.5, kind: str = "planar", coordinate_scale: float = 1.0,
               coordinate_offset: float = 0.0, prior: Any = None) -> np.ndarray:
    """Fit the road model to an HxW disparity map (px, NaN = invalid): the fit report, host
    float64 (ROAD_REPORT,), laid out as :func:`model_from_report` reads it.

    The first fit uses every valid pixel of the ``stride`` grid; each of ``rounds`` refits drops
    pixels whose residual exceeds ``outlier_k`` robust sigmas. The quadratic correction (kind
    quadratic or auto) is fitted to the planar model's inliers by rounds of its own. With a
    ``prior`` (float64 (PRIOR_PARAMS,) of :func:`prior_params`: the road expected and how far
    from it the road may lie, px), the fit takes only the valid pixels that close to it: the
    road region, not the cars, walls and trees beside it; unless fewer than the prior's share
    of the valid pixels lie there (a stale prior), when it takes every valid pixel. Pixel
    (i, j) of the map sits at full-resolution coordinates
    ``coordinate_scale * (j, i) + coordinate_offset`` and its disparity is scaled likewise, so
    the model is always in full-resolution pixels.
    """
    sub = disparity[::stride, ::stride]
    height, width = sub.shape
    step = stride * coordinate_scale
    u = xp.arange(width, dtype=xp.float64)[None, :] * step + coordinate_offset
    v = xp.arange(height, dtype=xp.float64)[:, None] * step + coordinate_offset
    d = sub.astype(xp.float64) * coordinate_scale
    valid = xp.isfinite(d)
    basis = _basis(xp, d, u, v)
    report = np.full(ROAD_REPORT, np.nan)
    first = valid
    if prior is not None and float(prior[PRIOR_TOLERANCE]) > 0:
        expected = params_at(xp, prior, u, v)
        near = valid & (xp.abs(d - expected) <= prior[PRIOR_TOLERANCE])
        if float(near.sum()) >= float(prior[PRIOR_MIN_SHARE]) * float(valid.sum()):
            first = near

    def robust_rounds(model: RoadModel, refit: Any, mask: Any
                      ) -> tuple[RoadModel, float, float, Any]:
        for round_index in range(rounds + 1):
            model = refit(model, mask)
            residual = d - model.at(xp, u, v)
            sigma = _robust_sigma(xp, residual, mask)
            mask = first & (xp.abs(residual) <= outlier_k * xp.maximum(sigma, 1e-3))
        inliers, sigma_px, report[_F["FIT_VALID"]] = to_host(xp.stack(
            [mask.sum(), sigma, valid.sum()]).astype(xp.float64))
        return model, inliers, sigma_px, mask

    def refit_planar(model: RoadModel, mask: Any) -> RoadModel:
        a0, a1, phi, _ = solve_roll(_moments_of(xp, basis, mask))
        return RoadModel(a0, a1, phi)

    try:
        planar, report[_F["FIT_PLANAR_INLIERS"]], report[_F["FIT_PLANAR_SIGMA"]], \
            planar_inliers = robust_rounds(RoadModel(0.0, 0.0, 0.0), refit_planar, first)
    except RoadFitFailed as failure:
        report[_F["FIT_STATUS"]] = failure.status
        return report
    report[_F["FIT_STATUS"]] = 0
    report[[_F["FIT_A0"], _F["FIT_A1"], _F["FIT_ROLL"]]] = planar.a0, planar.a1, planar.roll_rad
    if kind == "planar":
        return report
    plane = planar.at(xp, u, v)
    design = _curvature_design(xp, d.shape, u, v, plane)
    planar_residual = d - plane

    def refit_quadratic(model: RoadModel, mask: Any) -> RoadModel:
        return replace(planar, curvature=_fit_curvature(xp, design, planar_residual, mask),
                       kind="quadratic")

    quadratic, report[_F["FIT_QUADRATIC_INLIERS"]], report[_F["FIT_QUADRATIC_SIGMA"]], _ = \
        robust_rounds(planar, refit_quadratic, planar_inliers)
    report[_F["FIT_CURVATURE"]:_F["FIT_CURVATURE"] + 6] = quadratic.curvature
    return report


def fit_road(xp: Any, disparity: Any, *, stride: int = 1, rounds: int = 3,
             outlier_k: float = 2.5, kind: str = "planar", quadratic_gain: float = 0.1,
             coordinate_scale: float = 1.0, coordinate_offset: float = 0.0,
             prior: Any = None) -> RoadModel:
    """The road model of :func:`fit_report` (kind auto: quadratic where it lowers the inlier
    sigma by the fraction ``quadratic_gain``). Raises NoRoadError when the fit fails."""
    return model_from_report(
        fit_report(xp, disparity, stride=stride, rounds=rounds, outlier_k=outlier_k, kind=kind,
                   coordinate_scale=coordinate_scale, coordinate_offset=coordinate_offset,
                   prior=prior),
        kind, quadratic_gain)


def fit(backend: Backend, disparity: Any, *, stride: int = 1, rounds: int = 3,
        outlier_k: float = 2.5, kind: str = "planar", quadratic_gain: float = 0.1,
        coordinate_scale: float = 1.0, coordinate_offset: float = 0.0, report: Any = None,
        params: Any = None, prior: Any = None) -> tuple[Any, Any]:
    """The road fit stage: the fit report (float64 (ROAD_REPORT,), see
    :func:`model_from_report`) and the chosen model's kernel parameters (float64
    (ROAD_PARAMS,), as RoadModel.kernel_params; NaN when the fit failed) as backend arrays,
    written into ``report`` and ``params`` where given; ``prior``: a backend (PRIOR_PARAMS,)
    array of :func:`prior_params` or None (see :func:`fit_report`). On the GPU
    :func:`fit_on_device`, nothing read back; on the CPU :func:`fit_report`."""
    options = dict(stride=stride, rounds=rounds, outlier_k=outlier_k, kind=kind,
                   coordinate_scale=coordinate_scale, coordinate_offset=coordinate_offset,
                   prior=prior)
    if backend.is_gpu:
        return fit_on_device(backend, disparity, quadratic_gain=quadratic_gain, report=report,
                             params=params, **options)
    found = fit_report(backend.xp, disparity, **options)
    report = np.empty(ROAD_REPORT) if report is None else report
    params = np.empty(ROAD_PARAMS) if params is None else params
    report[...] = found
    params[...] = np.nan if found[_F["FIT_STATUS"]] else \
        model_from_report(found, kind, quadratic_gain).kernel_params()
    return report, params


def fit_model(backend: Backend, disparity: Any, *, quadratic_gain: float = 0.1,
              kind: str = "planar", **options: Any) -> RoadModel:
    """:func:`fit` and its model on the host (one readback on the GPU). Raises NoRoadError
    when the fit fails."""
    report, _ = fit(backend, disparity, quadratic_gain=quadratic_gain, kind=kind, **options)
    return model_from_report(to_host(report), kind, quadratic_gain)


def fit_on_device(backend: Backend, disparity: Any, *, stride: int = 1, rounds: int = 3,
                  outlier_k: float = 2.5, kind: str = "planar", quadratic_gain: float = 0.1,
                  coordinate_scale: float = 1.0, coordinate_offset: float = 0.0,
                  report: Any = None, params: Any = None, prior: Any = None
                  ) -> tuple[Any, Any]:
    """:func:`fit_road` as one cooperative launch of one block per multiprocessor
    (kernels/road.cu), nothing read back: returns the device report (float64 (ROAD_REPORT,),
    see :func:`model_from_report`) and the chosen model's kernel parameters (float64
    (ROAD_PARAMS,), as RoadModel.kernel_params; NaN when the fit failed). ``report`` and
    ``params`` may be given as device arrays to write into. GPU backend only."""
    xp = backend.xp
    sub = xp.ascontiguousarray(disparity[::stride, ::stride], dtype=xp.float32)
    height, width = sub.shape
    tables = _coordinate_tables(backend, height, width, stride * coordinate_scale,
                                coordinate_offset)
    n = height * width
    residual = xp.empty(n, dtype=xp.float64)
    planar_values = xp.empty(n, dtype=xp.float64)
    blocks = backend.multiprocessors()
    # each block's median keys in shared memory where they fit (stride 4 at 2079x1040 on 132
    # multiprocessors: 6 KiB), else in global memory
    segments = height * -(-width // 32)
    key_bytes = -(-segments // (blocks * ROAD_WARPS)) * ROAD_WARPS * 32 * 4
    local_keys = key_bytes <= MAX_SHARED_KEY_BYTES
    keys = xp.empty(1 if local_keys else n, dtype=xp.uint32)
    # workspace: barrier counter (16 bytes), block totals, one histogram per radix pass
    phases = 2 if kind != "planar" else 1
    totals_bytes = 2 * blocks * ROAD_MAX_SUMS * 8
    histogram_count = phases * (rounds + 1) * ROAD_HISTOGRAMS_PER_ROUND
    workspace = xp.zeros(16 + totals_bytes + histogram_count * ROAD_BINS * 4, dtype=xp.uint8)
    report = xp.empty(ROAD_REPORT, dtype=xp.float64) if report is None else report
    params = xp.empty(ROAD_PARAMS, dtype=xp.float64) if params is None else params
    if prior is None:
        prior = _no_prior(backend)
    kernel = _kernel(backend, "road_fit", cooperative=True)
    if local_keys and key_bytes > 48 * 1024 - ROAD_STATIC_SHARED_BYTES:
        kernel.max_dynamic_shared_size_bytes = MAX_SHARED_KEY_BYTES
    kernel((blocks,), (ROAD_WARPS * 32,),
           (sub, tables, np.int32(height), np.int32(width), np.float64(coordinate_scale),
            np.int32(rounds), np.float64(outlier_k), np.int32(kind != "planar"), residual,
            planar_values, keys, np.int32(local_keys), np.int32(kind == "auto"),
            np.float64(quadratic_gain), workspace[:16].view(xp.uint32),
            workspace[16:16 + totals_bytes].view(xp.float64),
            workspace[16 + totals_bytes:].view(xp.uint32), report, params, prior),
           shared_mem=key_bytes if local_keys else 0)
    return report, params


def model_from_report(report: np.ndarray, kind: str, quadratic_gain: float) -> RoadModel:
    """The RoadModel of a host copy of a fit report (FIT_LAYOUT). The quadratic model is kept
    where it lowers the inlier sigma by the fraction ``quadratic_gain`` (kind auto). a0 and a1
    stay NumPy float64 scalars, so that the model evaluated on float32 coordinates gives
    float64 disparities. Raises NoRoadError for a failed fit."""
    status = int(report[_F["FIT_STATUS"]])
    if status != 0:
        raise NoRoadError(FIT_FAILURES.get(status, "the road fit failed"))
    n_valid = max(report[_F["FIT_VALID"]], 1.0)
    planar = RoadModel(report[_F["FIT_A0"]], report[_F["FIT_A1"]],
                       float(report[_F["FIT_ROLL"]]),
                       inlier_fraction=float(report[_F["FIT_PLANAR_INLIERS"]] / n_valid),
                       sigma_px=float(report[_F["FIT_PLANAR_SIGMA"]]))
    if kind == "planar":
        return planar
    curvature = report[_F["FIT_CURVATURE"]:_F["FIT_CURVATURE"] + 6]
    quadratic = replace(planar, curvature=tuple(float(c) for c in curvature), kind="quadratic",
                        inlier_fraction=float(report[_F["FIT_QUADRATIC_INLIERS"]] / n_valid),
                        sigma_px=float(report[_F["FIT_QUADRATIC_SIGMA"]]))
    if kind == "auto" and not quadratic.sigma_px < (1.0 - quadratic_gain) * planar.sigma_px:
        return planar
    return quadratic


def params_planar(params: Any, u: Any, v: Any) -> Any:
    """Disparity (px) at pixels (u, v) of the plane (the linear part) of the road model given by
    its kernel parameters (backend float64 (ROAD_PARAMS,), PARAM_LAYOUT)."""
    layout = PARAM_LAYOUT
    return params[layout["ROAD_A0"]] + params[layout["ROAD_A1"]] * (
        v * params[layout["ROAD_COS"]] - u * params[layout["ROAD_SIN"]])


def params_at(xp: Any, params: Any, u: Any, v: Any) -> Any:
    """Road disparity (px) at pixels (u, v) of the road model given by its kernel parameters
    (backend float64 (ROAD_PARAMS,), PARAM_LAYOUT), on the backend with nothing read back."""
    layout = PARAM_LAYOUT
    c = [params[layout["ROAD_C0"] + k] for k in range(6)]
    planar = params_planar(params, u, v)
    return planar + params[layout["ROAD_CURVED"]] * _poly(
        xp, tuple(c), u / CURVATURE_SCALE_PX, v / CURVATURE_SCALE_PX, planar)


def road_plane(xp: Any, params: Any, calibration: Any) -> tuple[tuple[Any, Any, Any], Any]:
    """The plane n . P = f B of the linear part of the road model given by its kernel
    parameters: n = (beta f, gamma f, a0 + beta cx + gamma cy) and |n| (backend scalars)."""
    layout = PARAM_LAYOUT
    a0, a1 = params[layout["ROAD_A0"]], params[layout["ROAD_A1"]]
    beta, gamma = -a1 * params[layout["ROAD_SIN"]], a1 * params[layout["ROAD_COS"]]
    normal = (beta * calibration.f, gamma * calibration.f,
              a0 + beta * calibration.cx + gamma * calibration.cy)
    return normal, xp.sqrt(normal[0] ** 2 + normal[1] ** 2 + normal[2] ** 2)


def params_normal(xp: Any, params: Any, calibration: Any) -> tuple[Any, Any, Any]:
    """Unit normal (three backend scalars) of the plane of the linear part of the road model
    given by its kernel parameters, as measure.road_normal computes it from a RoadModel."""
    normal, norm = road_plane(xp, params, calibration)
    return normal[0] / norm, normal[1] / norm, normal[2] / norm


def params_height(xp: Any, params: Any, calibration: Any) -> Any:
    """The camera's height (m, a backend scalar) above the plane of the linear part of the
    road model given by its kernel parameters: f B / |n|."""
    _, norm = road_plane(xp, params, calibration)
    return calibration.fb / norm


def fit_sigma(xp: Any, report: Any, params: Any) -> Any:
    """The robust disparity sigma (px, a backend scalar) of the chosen model of a fit report
    and its kernel parameters: the quadratic rounds' where the model is curved."""
    return xp.where(params[PARAM_LAYOUT["ROAD_CURVED"]] != 0,
                    report[FIT_LAYOUT["FIT_QUADRATIC_SIGMA"]],
                    report[FIT_LAYOUT["FIT_PLANAR_SIGMA"]])


def prior_params(model: RoadModel | None, tolerance_px: float,
                 min_share: float = 0.0) -> np.ndarray:
    """The fit's prior (host float64 (PRIOR_PARAMS,)): ``model``'s kernel parameters,
    ``tolerance_px`` and ``min_share``; no prior (all zeros) where ``model`` is None."""
    prior = np.zeros(PRIOR_PARAMS)
    if model is not None:
        prior[:ROAD_PARAMS] = model.kernel_params()
        prior[PRIOR_TOLERANCE] = tolerance_px
        prior[PRIOR_MIN_SHARE] = min_share
    return prior


def refit_prior(xp: Any, params: Any, prior: Any) -> Any:
    """The prior of a second fit (float64 (PRIOR_PARAMS,), on the backend): the first fit's
    kernel parameters ``params`` (float64 (ROAD_PARAMS,); NaN where it failed, which leaves
    no pixel near it, so the second fit takes every valid pixel) with the tolerance and share
    of the first fit's ``prior``."""
    return xp.concatenate([xp.asarray(params, dtype=xp.float64),
                           xp.asarray(prior, dtype=xp.float64)[ROAD_PARAMS:]])


def prior_tolerance_px(model: RoadModel, calibration: Any, change_deg: float) -> float:
    """How far (px) the road may lie from ``model`` in the next frame: the disparity by which a
    turn of the camera by ``change_deg`` about its x axis moves the road (a1 f tan(change)), at
    least MIN_PRIOR_TOLERANCE_PX. Not widened by the fit's sigma: measured inside the band, it
    grows with the band, and the band would grow with it frame after frame."""
    return float(max(abs(model.a1) * calibration.f * math.tan(math.radians(change_deg)),
                     MIN_PRIOR_TOLERANCE_PX))


@lru_cache(maxsize=4)
def _no_prior(backend: Backend) -> Any:
    """A device prior that asks for none."""
    return backend.upload(np.zeros(PRIOR_PARAMS))


def device_params(backend: Backend, model: RoadModel | Any) -> Any:
    """Kernel parameters (device float64 (ROAD_PARAMS,)) of a RoadModel (one small upload) or
    of a device parameter array from :func:`fit_on_device` (returned as it is)."""
    if isinstance(model, RoadModel):
        return backend.upload(model.kernel_params())
    return model


# kernels/road.cu: warps per block, sums (MAX_SUMS), histogram bins (BINS), global histograms
# one round can use (one per radix pass and median rank), the kernel's own shared memory, and
# the shared memory left for the keys beside it.
ROAD_WARPS = 16
ROAD_MAX_SUMS = 27
ROAD_BINS = 4096
ROAD_HISTOGRAMS_PER_ROUND = 5
ROAD_STATIC_SHARED_BYTES = 36 * 1024
MAX_SHARED_KEY_BYTES = 160 * 1024

_ROAD_DEFINES = {"THREADS": 32 * ROAD_WARPS, "BINS": ROAD_BINS, "MAX_SUMS": ROAD_MAX_SUMS,
                 "PRIOR_TOLERANCE": PRIOR_TOLERANCE, "PRIOR_MIN_SHARE": PRIOR_MIN_SHARE,
                 **FIT_LAYOUT, **ROAD_DEFINES}

@lru_cache(maxsize=4)
def _coordinate_tables(backend: Backend, height: int, width: int, step: float,
                       offset: float) -> Any:
    """Device float64 (2 (width + height),): column u, row v, then u / 1000 and v / 1000, as
    fit_road computes them; uploaded once per size."""
    u = np.arange(width, dtype=np.float64) * step + offset
    v = np.arange(height, dtype=np.float64) * step + offset
    return backend.upload(np.concatenate([u, v, u / CURVATURE_SCALE_PX, v / CURVATURE_SCALE_PX]))


def _kernel(backend: Backend, name: str, cooperative: bool = False) -> Any:
    """Kernel ``name`` of kernels/road.cu with the numbers it shares with this module."""
    return backend.kernel("road.cu", name, _ROAD_DEFINES, cooperative=cooperative)

