"""The overlay: potholes tinted, the road shaded by where potholes were looked for."""

import numpy as np

from pothole_detector.imageio import UNOBSERVED_SHADE, UNSEARCHED_SHADE, overlay


def test_the_overlay_shades_the_road_beyond_the_observed_and_the_searched_road():
    """Three bands of a grey image: observed (as it is), searched only (a lighter shade) and
    neither (the darker shade); without the searched mask, all road not observed takes the
    darker shade."""
    image = np.full((6, 8), 200, np.uint8)
    observed = np.zeros((6, 8), bool)
    observed[4:] = True
    searched = observed.copy()
    searched[2:] = True
    labels = np.zeros((6, 8), np.int32)
    shaded = overlay(image, labels, [], observed, searched)
    assert shaded.shape == (6, 8, 3) and shaded.dtype == np.uint8
    assert (shaded[4:] == 200).all()
    assert (shaded[2:4] == int(200 * UNOBSERVED_SHADE)).all()
    assert (shaded[:2] == int(200 * UNSEARCHED_SHADE)).all()
    plain = overlay(image, labels, [], observed)
    assert (plain[:4] == int(200 * UNSEARCHED_SHADE)).all() and (plain[4:] == 200).all()
