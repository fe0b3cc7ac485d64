"""GNSS with odometry (motion.fuse_gnss): a 1.2 km drive, odometry with 1 % scale error and
0.3 deg of heading drift per 100 m, fixes with 0.1 m noise; with gaps and outliers."""

from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.geodesy import enu_of, latlon_of
from pothole_detector.survey.motion import fit_rigid_2d, fuse_gnss

ORIGIN = (47.3769, 8.5417)
RATE_HZ, SPEED_M_S, LENGTH_M = 10.0, 10.0, 1200.0


def drive(seed=0):
    """(stamps ns, true east/north m, odometry positions m in its own frame)."""
    steps = int(LENGTH_M / SPEED_M_S * RATE_HZ)
    distance = np.arange(steps) * SPEED_M_S / RATE_HZ
    heading = 0.6 * np.sin(distance / 150.0) + distance / 800.0  # bends and a long curve
    step = SPEED_M_S / RATE_HZ
    truth = np.cumsum(np.stack([np.cos(heading), np.sin(heading)], axis=1) * step, axis=0)
    drift = np.deg2rad(0.3) * distance / 100.0
    odometry_heading = heading + drift + 0.4  # its own frame, turned
    odometry = np.cumsum(np.stack([np.cos(odometry_heading), np.sin(odometry_heading)],
                                  axis=1) * step * 1.01, axis=0) + [5.0, -3.0]
    stamps = (np.arange(steps) * 1e9 / RATE_HZ).astype(np.int64) + 10**18
    return stamps, truth, odometry


def fixes(stamps, truth, noise=0.1, seed=1):
    rng = np.random.default_rng(seed)
    measured = truth + rng.normal(0.0, noise, truth.shape)
    return stamps.copy(), latlon_of(measured, *ORIGIN), np.full(len(stamps), noise)


def errors(fusion, odometry, truth):
    origin_shift = enu_of(np.array([fusion.origin[0]]), np.array([fusion.origin[1]]),
                          *ORIGIN)[0]
    return np.linalg.norm(fusion.to_enu(odometry) + origin_shift - truth, axis=1)


def test_drift_is_corrected_along_the_drive_not_once_for_all_of_it():
    stamps, truth, odometry = drive()
    fusion = fuse_gnss(stamps, odometry, *fixes(stamps, truth), window_m=20.0)
    error = errors(fusion, odometry, truth)
    assert np.percentile(error, 95) < 0.3 and np.median(error) < 0.1
    assert np.nanmedian(fusion.residuals_m) < 0.2 and fusion.kept.all()
    # one rigid fit over the whole drive, as before: metres off
    measured = enu_of(*fixes(stamps, truth)[1].T, *ORIGIN)
    rigid = fit_rigid_2d(odometry, measured).apply(odometry)
    assert np.median(np.linalg.norm(rigid - truth, axis=1)) > 1.0


def test_outlier_fixes_are_rejected():
    stamps, truth, odometry = drive()
    gnss_stamps, latlon, sigma = fixes(stamps, truth)
    rng = np.random.default_rng(3)
    bad = rng.random(len(stamps)) < 0.05
    enu = enu_of(latlon[:, 0], latlon[:, 1], *ORIGIN)
    enu[bad] += rng.normal(0.0, 15.0, (bad.sum(), 2))
    fusion = fuse_gnss(stamps, odometry, gnss_stamps, latlon_of(enu, *ORIGIN), sigma, 20.0)
    error = errors(fusion, odometry, truth)
    assert np.percentile(error, 95) < 0.3
    assert (fusion.kept[bad] == 0).mean() > 0.9 and (fusion.kept[~bad] > 0).all()


@pytest.mark.parametrize("gap_m", [60.0, 150.0])
def test_in_a_gap_the_odometry_carries_the_drive(gap_m):
    """No fixes over a stretch: positions there drift no more than the odometry alone would
    from the gap's edge (1 % of scale and the heading drift over half the gap)."""
    stamps, truth, odometry = drive()
    gnss_stamps, latlon, sigma = fixes(stamps, truth)
    distance = np.arange(len(stamps)) * SPEED_M_S / RATE_HZ
    gap = (distance > 600.0) & (distance < 600.0 + gap_m)
    fusion = fuse_gnss(stamps, odometry, gnss_stamps[~gap], latlon[~gap], sigma[~gap], 20.0)
    error = errors(fusion, odometry, truth)
    assert np.percentile(error[~gap], 95) < 0.3
    assert error[gap].max() < 0.3 + 0.015 * gap_m / 2


def test_without_enough_fixes_there_is_no_fusion():
    stamps, truth, odometry = drive()
    assert fuse_gnss(stamps, odometry, stamps[:1], fixes(stamps, truth)[1][:1],
                     np.ones(1), 20.0) is None
