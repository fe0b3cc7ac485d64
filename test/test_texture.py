from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.stages import texture


def _ramps() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 16x64 image: grey rising 4 levels a column on the left half and 2 on the right, the
    pixels about the seam without a disparity; superpixels: the left half's top and bottom
    rows (0, 1), the right half (2), and one whose pixels all lack a disparity (3)."""
    columns = np.arange(64)
    row = np.where(columns < 32, 4 * columns, 2 * (columns - 32) + 60)
    image = np.tile(row, (16, 1)).astype(np.uint8)
    valid = np.ones(image.shape, dtype=bool)
    valid[:, 30:34] = False
    labels = np.full(image.shape, 2, dtype=np.int32)
    labels[:8, :32] = 0
    labels[8:, :32] = 1
    labels[:2, 30:34] = 3
    return image, valid, labels


def test_the_gradient_energy_is_the_squared_central_difference_where_there_is_disparity():
    image, valid, _ = _ramps()
    energy = texture.gradient_energy(CPU, image, valid)
    assert np.all(energy[:, 1:30] == 16) and np.all(energy[:, 34:63] == 4)
    assert np.isnan(energy[:, [0, 30, 33, 63]]).all()


def test_a_superpixel_with_half_the_road_s_gradient_is_twice_as_noisy():
    image, valid, labels = _ramps()
    observed = np.ones(4, dtype=bool)
    ratio = texture.deficit(CPU, image, valid, labels, 4, observed)
    np.testing.assert_allclose(ratio, [1.0, 1.0, 2.0, 1.0])
    # the typical texture is that of the observed superpixels alone
    ratio = texture.deficit(CPU, image, valid, labels, 4, np.array([False, False, True, True]))
    np.testing.assert_allclose(ratio, [1.0, 1.0, 1.0, 1.0])


def test_a_flat_superpixel_is_as_noisy_as_the_floor_allows_and_nothing_observed_is_neutral():
    image, valid, labels = _ramps()
    image[8:, :32] = 255
    observed = np.ones(4, dtype=bool)
    ratio = texture.deficit(CPU, image, valid, labels, 4, observed)
    np.testing.assert_allclose(ratio[1], 2.0 / texture.FLAT_RMS_GREY)  # median of 0, 2, 4
    assert ratio[0] == 1.0
    np.testing.assert_allclose(
        texture.deficit(CPU, image, valid, labels, 4, np.zeros(4, dtype=bool)), 1.0)
