"""Pixel-level refinement (stages/refine.py): rims next to a pothole's superpixels join it."""

from __future__ import annotations

import numpy as np
import pytest

from pothole_detector.backend import CPU
from pothole_detector.stages.refine import radius, refine_labels, smooth


def _scene():
    """Two superpixels (left half 0, right half 1) of a 20x40 map; pothole 1 covers columns
    8-11 of rows 5-14; the road (D2 32) dips 1 px at columns 12-17 beside it and at 28-33."""
    transformed = np.full((20, 40), 32.0, np.float32)
    transformed[:, 12:18] = 31.0
    transformed[:, 28:34] = 31.0
    labels = np.zeros((20, 40), np.int32)
    labels[5:15, 8:12] = 1
    superpixel_labels = np.zeros((20, 40), np.int32)
    superpixel_labels[:, 20:] = 1
    return transformed, labels, superpixel_labels


def test_pixels_below_the_road_within_the_radius_join_the_pothole():
    transformed, labels, superpixel_labels = _scene()
    drops = np.array([2.0, 2.0])
    observed = np.array([True, True])
    refined = refine_labels(CPU, labels, smooth(CPU, transformed), superpixel_labels, drops,
                            observed, 32.0, 4, 0.25)
    assert refined.dtype == np.int32
    assert np.array_equal(refined[labels > 0], labels[labels > 0])
    grown = (refined == 1) & (labels == 0)
    # within 4 px of the pothole, where the 5x5 mean lies 0.5 px (a quarter of 2) below
    rows, cols = np.nonzero(grown)
    assert grown.any() and cols.min() >= 12 and cols.max() <= 15
    assert rows.min() >= 1 and rows.max() <= 18
    assert not refined[:, 28:34].any()  # the dip far from the pothole stays road


def test_refinement_keeps_to_observed_road_and_deep_enough_pixels():
    transformed, labels, superpixel_labels = _scene()
    observed = np.array([False, True])
    transformed = smooth(CPU, transformed)
    unobserved = refine_labels(CPU, labels, transformed, superpixel_labels,
                               np.array([2.0, 2.0]), observed, 32.0, 4, 0.25)
    assert np.array_equal(unobserved, labels)
    shallow = refine_labels(CPU, labels, transformed, superpixel_labels,
                            np.array([8.0, 8.0]), np.array([True, True]), 32.0, 4, 0.25)
    assert np.array_equal(shallow, labels)  # 1 px is less than a quarter of 8
    off = refine_labels(CPU, labels, transformed, superpixel_labels, np.array([2.0, 2.0]),
                        np.array([True, True]), 32.0, 4, 0.0)
    assert off is labels
    assert radius(32) == 16 and radius(10) == 5


def test_smooth_averages_the_valid_neighbours_and_keeps_invalid_pixels_invalid():
    values = np.arange(49, dtype=np.float32).reshape(7, 7)
    values[0, 0] = np.nan
    smoothed = smooth(CPU, values)
    assert np.isnan(smoothed[0, 0]) and smoothed.dtype == np.float32
    assert smoothed[3, 3] == np.float32(24.0)  # a linear ramp keeps its centre value
    corner = values[:4, :4][np.isfinite(values[:4, :4])].mean()  # the 5x5 square, clipped
    assert smoothed[1, 1] == pytest.approx(corner, rel=1e-6)
    filled = smooth(CPU, values, fill=True)
    assert filled[0, 0] == pytest.approx(values[:3, :3][np.isfinite(values[:3, :3])].mean())
    assert np.array_equal(filled[1:], smoothed[1:]) and np.isfinite(filled).all()
