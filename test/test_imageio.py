"""The overlay: potholes tinted, the road shaded by where potholes were looked for."""

import numpy as np
import pytest

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



def _overlay_whole_image(image, labels, potholes, observed, searched):
    """The overlay as whole-image array code: each pothole's mask, tint and outline over the
    whole image, the shading by boolean indexing (the labels' text by the same helper)."""
    import cv2

    from pothole_detector.imageio import PALETTE, write_label
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else image.copy()
    if canvas.dtype != np.uint8:
        canvas = cv2.convertScaleAbs(canvas, alpha=255.0 / max(float(canvas.max()), 1.0))
    beyond = searched & ~observed
    canvas[~searched] = (canvas[~searched] * UNSEARCHED_SHADE).astype(np.uint8)
    canvas[beyond] = (canvas[beyond] * UNOBSERVED_SHADE).astype(np.uint8)
    scale = max(0.5, min(image.shape[:2]) / 700.0)
    thickness = max(1, int(round(2 * scale)))
    for pothole in potholes:
        colour = PALETTE[(pothole.label - 1) % len(PALETTE)]
        mask = labels == pothole.label
        canvas[mask] = (0.55 * canvas[mask] + 0.45 * colour).astype(np.uint8)
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(canvas, contours, -1, tuple(int(c) for c in colour), thickness)
        write_label(canvas, pothole, scale, thickness)
    return canvas


@pytest.mark.parametrize("form", ["grey", "rgb", "grey16"])
def test_each_pothole_is_drawn_in_its_box_as_over_the_whole_image(form):
    """Tint and outline worked within each pothole's bounding box, on a grey image shaded
    before it becomes RGB, give the whole-image form's pixels, for potholes of two pieces,
    with holes, at the image's edges and corners, ragged ones, over a shaded road; from a
    grey, an RGB and a 16-bit grey image."""
    from pothole_detector.stages.measure import Pothole

    rng = np.random.default_rng(4)
    height, width = 180, 400
    image = rng.integers(0, 256, (height, width), dtype=np.uint8)
    if form == "rgb":
        image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    elif form == "grey16":
        image = rng.integers(0, 4096, (height, width), dtype=np.uint16)
    labels = np.zeros((height, width), np.int32)
    labels[0:12, 0:20] = 1                      # a corner
    labels[60:100, 40:70] = 2
    labels[70:80, 50:60] = 0                    # a hole
    labels[120:124, 45:52] = 2                  # a second piece
    labels[150:180, 340:400] = 3                # the bottom right corner
    labels[20:40, 399] = 4                      # one column at the right edge
    labels[5:45, 180:260] = np.where(rng.random((40, 80)) < 0.5, 5, 0)  # ragged
    observed = rng.random((height, width)) < 0.6
    searched = observed | (rng.random((height, width)) < 0.5)
    potholes = []
    for label in range(1, 6):
        rows, cols = np.nonzero(labels == label)
        potholes.append(Pothole(label=label, pixels=rows.size, area_m2=0.1, max_depth_m=0.05,
                                mean_depth_m=0.03, volume_m3=0.003,
                                centroid_cam_m=(0.0, 0.0, 5.0),
                                bbox_px=(int(cols.min()), int(rows.min()), int(cols.max()),
                                         int(rows.max()))))
    expected = _overlay_whole_image(image, labels, potholes, observed, searched)
    np.testing.assert_array_equal(overlay(image, labels, potholes, observed, searched),
                                  expected)
