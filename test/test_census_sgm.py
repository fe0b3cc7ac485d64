from __future__ import annotations

import math

import numpy as np
import pytest

from pothole_detector.errors import ConfigError
from pothole_detector.params import Config
from pothole_detector.stages import census_sgm, perspective
from pothole_detector.stages.census_sgm import (
    CENSUS_BITS, CENSUS_OFFSETS, CENSUS_RADIUS_X, CENSUS_RADIUS_Y, DIRECTION_PAIRS, INVALID_COST,
    MAX_P2, census_transform,
    cpu_disparity, textureless)
from pothole_detector.stages.perspective import no_shifts, row_shifts
from pothole_detector.stages.road_model import RoadModel

from census_reference import (
    _path_step, aggregate, aggregate_path, matching_cost, reference_disparity, select_disparities)


def textured_pair(height: int, width: int, shift: np.ndarray, seed: int = 0):
    """Random texture and its right view: right(v, x) = left(v, x + shift(v))."""
    rng = np.random.default_rng(seed)
    wide = rng.integers(0, 256, (height, width + int(shift.max())), dtype=np.uint8)
    left = np.ascontiguousarray(wide[:, :width])
    right = np.stack([wide[v, shift[v]:shift[v] + width] for v in range(height)])
    return left, np.ascontiguousarray(right)


def _textureless_array_form(words):
    """textureless as array code: the 3 x 3 neighbourhood's blank words ANDed."""
    height, width = words.shape
    flat = np.pad(words == 0, 1, mode="edge")
    return np.logical_and.reduce([flat[a:a + height, b:b + width]
                                  for a in range(3) for b in range(3)])


@pytest.mark.parametrize("shape", [(1, 1), (5, 3), (47, 131)])
def test_blank_patches_are_those_of_the_array_form(shape):
    rng = np.random.default_rng(shape[1])
    image = rng.integers(0, 256, shape, dtype=np.uint8)
    image[: shape[0] // 2, : shape[1] // 2] = 255
    words = census_transform(image)
    np.testing.assert_array_equal(textureless(words), _textureless_array_form(words))
    assert shape[0] < 20 or textureless(words).any()


def _census_array_form(image):
    """The array form census_transform's kernel replaced: a bit plane at a time."""
    height, width = image.shape
    ry, rx = CENSUS_RADIUS_Y, CENSUS_RADIUS_X
    padded = np.pad(image, ((ry, ry), (rx, rx)), mode="edge")
    words = np.zeros((height, width), dtype=np.uint32)
    for bit, (dy, dx) in enumerate(CENSUS_OFFSETS):
        ahead = padded[ry + dy:ry + dy + height, rx + dx:rx + dx + width]
        behind = padded[ry - dy:ry - dy + height, rx - dx:rx - dx + width]
        words |= (ahead > behind).astype(np.uint32) << np.uint32(bit)
    return words


@pytest.mark.parametrize("shape", [(1, 1), (2, 9), (5, 3), (47, 131)])
def test_census_words_are_those_of_the_array_form(shape):
    image = np.random.default_rng(shape[0]).integers(0, 256, shape, dtype=np.uint8)
    np.testing.assert_array_equal(census_transform(image), _census_array_form(image))


def test_census_of_a_ramp_sets_exactly_the_rightward_bits():
    image = np.tile(np.arange(40, dtype=np.uint8) * 3, (12, 1))
    words = census_transform(image)
    expected = sum(1 << i for i, (dy, dx) in enumerate(CENSUS_OFFSETS) if dx > 0)
    assert CENSUS_BITS == 31
    assert (words[:, 4:-4] == expected).all()


def test_cost_is_zero_at_the_true_shift_and_invalid_left_of_the_image():
    left, right = textured_pair(10, 50, np.full(10, 6))
    cost = matching_cost(census_transform(left), census_transform(right), no_shifts(10), 16)
    assert (cost[4:-4, 20:-5, 6] == 0).all()
    assert (cost[4:-4, 20:-5, 5] > 3).mean() > 0.9
    assert (cost[:, 3, 4:] == INVALID_COST).all()


def test_path_step_known_answer():
    previous = np.array([[0, 10, 10]], np.int32)
    cost = np.full((1, 3), 5, np.int32)
    np.testing.assert_array_equal(_path_step(cost, previous, 1, 3), [[5, 6, 8]])


def test_path_starts_where_the_predecessor_is_outside():
    cost = np.random.default_rng(1).integers(0, 31, (5, 7, 16)).astype(np.int32)
    for dx, dy in census_sgm.DIRECTIONS:
        paths = aggregate_path(cost, dx, dy, 3, 20)
        start_u = 0 if dx > 0 else 6
        start_v = 0 if dy > 0 else 4
        if dx:
            np.testing.assert_array_equal(paths[:, start_u], cost[:, start_u])
        if dy:
            np.testing.assert_array_equal(paths[start_v], cost[start_v])
        assert (paths >= cost).all() and (paths <= cost + 20).all()


@pytest.mark.parametrize("with_gpt", [False, True])
def test_cpu_matcher_recovers_a_road_like_shift_with_gpt_row_shifts(with_gpt):
    """Disparity grows by one every 6 rows, like a road; GPT's kappa follows it."""
    height, width = 24, 64
    true_shift = 9 + np.arange(height) // 6
    left, right = textured_pair(height, width, true_shift, seed=2)
    shifts = row_shifts(np.arange(height) // 6) if with_gpt else no_shifts(height)
    disparity = cpu_disparity(left, right, shifts, 16, 7, 86, 5, 1, True)
    error = np.abs(disparity - true_shift[:, None])[6:-6, 24:-8]
    assert np.isfinite(error).mean() > 0.9
    assert np.nanmedian(error) < 0.2 and np.nanmean(error > 1.0) < 0.02
    assert np.isnan(disparity[:, :9]).all()


@pytest.mark.parametrize("slope", [0.07, -0.07])
def test_cpu_matcher_recovers_a_rolled_road_with_gpt_pixel_shifts(slope):
    """Disparity changes along the rows too (a rolled rig): 6.6 px over the row, which the
    pixel shifts follow, so 16 levels hold it with a 4 px margin on either side."""
    height, width = 24, 96
    rng = np.random.default_rng(5)
    right = rng.integers(0, 256, (height, width), dtype=np.uint8)
    columns, rows = np.arange(width)[None, :], np.arange(height)[:, None]
    true_d = np.floor(15.5 + slope * (columns - 48) + rows / 6)
    left = np.take_along_axis(right, np.maximum(columns - true_d.astype(int), 0), axis=1)
    model = RoadModel(15.5 - 48 * slope, math.hypot(1 / 6, slope), math.atan2(-slope, 1 / 6))
    shifts, levels = perspective.band(np, model, height, width, 4.0, 4.0, 64, "pixel")
    assert levels == 16
    disparity = cpu_disparity(left, right, shifts, levels, 7, 86, 5, 1, True)
    error = np.abs(disparity - true_d)[6:-6, 30:-6]
    assert np.isfinite(error).mean() > 0.9
    assert np.nanmedian(error) < 0.2 and np.nanmean(error > 1.0) < 0.03
    assert np.isnan(disparity[:, :9]).all()


def test_uniqueness_and_left_right_check_invalidate():
    total = np.full((1, 4, 16), 100, np.uint8)
    total[0, :, 5] = 10
    paths = np.zeros((8, 1, 4, 16), np.uint8)
    paths[0] = total
    # every pixel picks 5; pixels 0..4 point left of the image
    raw = select_disparities(paths, 5, 1)
    assert (raw[0, :] == -1).all()
    wide = np.full((8, 1, 20, 16), 12, np.uint8)
    wide[:, :, :, 5] = 10
    ambiguous = select_disparities(wide, 25, -1)
    assert (ambiguous[0, 6:] == -1).all()
    clear = select_disparities(wide, 5, -1)
    assert (clear[0, 6:] == 5).all()


def test_settings_the_matcher_cannot_run_are_refused():
    image = np.zeros((8, 8), np.uint8)
    with pytest.raises(ConfigError, match="multiple of 16"):
        cpu_disparity(image, image, no_shifts(8), 24, 5, 50, 5, 1, True)
    with pytest.raises(ConfigError, match="P1 < P2"):
        cpu_disparity(image, image, no_shifts(8), 16, 50, 250, 5, 1, True)


def test_path_costs_stay_within_the_byte_pair_bound():
    """Each path cost is at most INVALID_COST + P2, so two opposite paths fit one byte at
    P2 = MAX_P2 (what the GPU matcher's four volumes rely on)."""
    rng = np.random.default_rng(11)
    left = rng.integers(0, 256, (16, 40), dtype=np.uint8)
    right = rng.integers(0, 256, (16, 40), dtype=np.uint8)
    cost = matching_cost(census_transform(left), census_transform(right), no_shifts(16), 16)
    paths = aggregate(cost, 0, MAX_P2).astype(np.int32)
    assert paths.max() <= INVALID_COST + MAX_P2 == 127
    assert paths.max() > INVALID_COST + MAX_P2 // 2
    for a, b in DIRECTION_PAIRS:
        assert (paths[a] + paths[b]).max() <= 255


def test_textureless_patches_are_invalid_and_textured_ones_are_not():
    left, right = textured_pair(40, 90, np.full(40, 6), seed=4)
    left[10:30, 40:70] = 120
    right[10:30, 34:64] = 120
    disparity = cpu_disparity(left, right, no_shifts(40), 16, 3, 20, 5, 1, True)
    # windows (9x7) that lie inside the flat patch, and their 3x3 neighbourhoods
    assert not np.isfinite(disparity[15:25, 46:64]).any()
    textured = disparity[5:35, 16:36]
    assert np.isfinite(textured).mean() > 0.9
    assert np.nanmedian(textured) == 6


def test_lanes_leave_at_most_8_levels_each_in_whole_words_where_possible():
    for levels in range(16, 513, 16):
        lanes = census_sgm.lanes_for(levels)
        assert lanes in (4, 8, 16, 32) and levels % lanes == 0
        assert levels // lanes <= (8 if levels <= 128 else 16 if levels <= 256 else 32)
    assert [census_sgm.lanes_for(n) for n in (16, 48, 64, 96, 128, 384)] == [4, 8, 16, 16, 32, 32]


def test_path_lanes_hold_16_padding_levels_where_only_then_each_gets_an_even_count():
    assert [census_sgm.path_levels(n) for n in (16, 48, 64, 80, 96, 112, 144, 208, 240)] \
        == [16, 48, 64, 96, 96, 128, 144, 208, 256]
    for levels in range(16, 513, 16):
        held = census_sgm.path_levels(levels)
        assert held in (levels, levels + 16)
        lanes = census_sgm.lanes_for(held)
        even = held % lanes == 0 and (held // lanes) % 2 == 0
        assert held == levels or even


def test_winner_search_lanes_hold_whole_words_of_at_most_12_levels():
    assert [census_sgm.select_lanes_for(n) for n in (16, 48, 64, 96, 128, 208, 384)] \
        == [4, 4, 8, 8, 16, 16, 32]
    for levels in range(16, 513, 16):
        lanes = census_sgm.select_lanes_for(levels)
        assert lanes in (4, 8, 16, 32) and levels % lanes == 0


def test_slot_pairs_add_as_bytes_only_where_two_slots_stay_below_256():
    for p2 in range(1, census_sgm.MAX_P2 + 1):
        two_slots = 4 * (census_sgm.INVALID_COST + p2)  # four directions at their bound
        assert census_sgm.slot_pair_bytes(p2) == (two_slots <= 255)
    assert census_sgm.slot_pair_bytes(Config().census_p2)


def test_winner_search_blocks_fit_the_shared_memory_of_a_block():
    # the real frames' band (96 held levels, 8 lanes, blocks of 512) within the 48 KB a block
    # has without asking; a full range at 1920 columns within a multiprocessor's 227 KB
    assert census_sgm.select_shared_bytes(96, 2079, 512, 8) <= 48 * 1024
    assert census_sgm.select_shared_bytes(384, 1920, 256, 32) <= 227 * 1024
    # records (8 bytes a pixel), right view (4 bytes a column and level), totals (odd pitch)
    assert census_sgm.select_shared_bytes(96, 100, 64, 8) == 4 * (300 + 96 + 8 * 49)


def test_horizontal_walks_go_second_where_lanes_hold_at_most_4_levels():
    assert census_sgm.horizontals_second(64, 16) and census_sgm.horizontals_second(64, 32)
    assert not census_sgm.horizontals_second(96, 16)
    assert not census_sgm.horizontals_second(256, 32)


def test_gpt_bands_get_small_path_blocks_and_wide_winner_search_blocks():
    # lanes of an even count up to 8 levels (the GPT bands, 1280x720's 32 lanes of 2 too)
    for levels, lanes in ((96, 16), (64, 16), (64, 32), (128, 32), (256, 32)):
        assert census_sgm.path_threads(levels, lanes) == 128
        assert census_sgm.select_threads(levels, lanes) == 512
    # one level a register, or more than 8 a lane (full ranges)
    for levels, lanes in ((208, 16), (304, 16), (368, 16), (384, 32), (80, 16)):
        assert census_sgm.path_threads(levels, lanes) == 256
        assert census_sgm.select_threads(levels, lanes) == 256
    # every block holds whole path lines
    for levels in range(16, 513, 16):
        held = census_sgm.path_levels(levels)
        lanes = census_sgm.lanes_for(held)
        assert census_sgm.path_threads(held, lanes) % lanes == 0


def test_lanes_double_while_the_lines_leave_the_device_underfilled():
    resident = 132 * 2048
    lines_720p = census_sgm.path_lines(720, 1280)
    assert census_sgm.lanes_for(64, census_sgm.path_lines(240, 320), resident) == 32
    assert census_sgm.lanes_for(64, census_sgm.path_lines(480, 640), resident) == 16
    assert census_sgm.lanes_for(64, lines_720p, resident) == 16
    assert census_sgm.lanes_for(64, census_sgm.path_lines(1080, 1920), resident) == 16
    assert census_sgm.lanes_for(96, 10, resident) == 16      # 3 levels a lane would be odd
    assert census_sgm.lanes_for(16, 10, resident) == 8       # 2 levels a lane, not 1
    assert census_sgm.lanes_for(128, 10, resident) == 32     # at most 32
    assert census_sgm.lanes_for(64, lines_720p, 0) == 16


def test_pixels_whose_band_reaches_left_of_the_image_are_invalid():
    """Left of column levels - 1 a pixel's true match may lie off the image while the levels
    left to it are the shallow ones: such pixels are invalid, the rest match the truth."""
    left, right = textured_pair(40, 90, np.full(40, 12), seed=5)
    disparity = cpu_disparity(left, right, no_shifts(40), 32, 3, 20, 5, 1, True)
    assert not np.isfinite(disparity[:, :31]).any()
    valid = np.isfinite(disparity)
    assert valid[5:35, 31:85].mean() > 0.9
    assert np.all(np.abs(disparity[valid] - 12) <= 1)


PARITY_CASES = [
    # height, width, levels, p1, p2, uniqueness, left-right tolerance, median, shift pattern
    (24, 64, 16, 3, 20, 5, 1, True, "none"),
    (31, 77, 32, 7, 86, 5, 1, True, "rows"),
    (40, 90, 48, 0, 1, 0, -1, False, "rows"),
    (17, 120, 32, 1, 4, 10, 0, True, "pixels"),
    (50, 140, 64, 3, MAX_P2, 25, 2, False, "pixels"),
]


@pytest.mark.parametrize("height,width,levels,p1,p2,uniqueness,lr,median,pattern", PARITY_CASES)
def test_cpu_matcher_gives_the_reference_disparities_exactly(height, width, levels, p1, p2,
                                                             uniqueness, lr, median, pattern):
    """The compiled CPU kernels (stages/census_cpu.py) against the plain NumPy statement of
    the algorithm (census_reference.py): costs, penalties small and large, uniqueness and
    left-right settings, the GPT row and pixel shifts with rows whose first columns differ."""
    rng = np.random.default_rng(height * width + levels)
    left, right = textured_pair(height, width, rng.integers(4, 12, height), seed=levels)
    if pattern == "rows":
        shifts = row_shifts(rng.integers(0, 6, height))
    elif pattern == "pixels":
        model = RoadModel(6.0, 0.15, 0.1)
        shifts, _ = perspective.band(np, model, height, width, 4.0, 4.0, levels, "pixel")
    else:
        shifts = no_shifts(height)
    expected = reference_disparity(left, right, shifts, levels, p1, p2, uniqueness, lr, median)
    actual = cpu_disparity(left, right, shifts, levels, p1, p2, uniqueness, lr, median)
    np.testing.assert_array_equal(actual, expected)
    assert np.isfinite(actual).mean() > 0.2


def test_volumes_kept_between_frames_give_each_frame_its_own_disparities():
    """Frames of other sizes and level counts in turn through one HostVolumes (grown, then
    reused with the values the frame before left): each as a matcher with new volumes."""
    volumes = census_sgm.HostVolumes()
    rng = np.random.default_rng(8)
    for height, width, levels in ((30, 70, 32), (12, 40, 16), (30, 70, 48), (30, 70, 32)):
        left, right = textured_pair(height, width, rng.integers(4, 12, height), seed=levels)
        shifts = row_shifts(rng.integers(0, 6, height))
        kept = cpu_disparity(left, right, shifts, levels, 7, 86, 5, 1, True, volumes)
        np.testing.assert_array_equal(
            kept, cpu_disparity(left, right, shifts, levels, 7, 86, 5, 1, True))
        assert np.isfinite(kept).mean() > 0.1


def test_compiling_the_cpu_kernels_ahead_covers_what_a_frame_needs(demo_sample):
    """The node compiles the CPU kernels before it subscribes: a frame afterwards finds every
    kernel compiled for its argument types and compiles nothing more."""
    from pothole_detector.pipeline import Pipeline
    from pothole_detector.stages import census_cpu

    census_sgm.compile_cpu_kernels()
    kernels = (census_cpu._cost_volume, census_cpu._write_row_paths,
               census_cpu._add_crossing_paths, census_cpu._select)
    compiled = [list(kernel.signatures) for kernel in kernels]
    assert all(compiled)
    Pipeline(Config(), demo_sample.calibration).run(demo_sample.left, demo_sample.right)
    assert [list(kernel.signatures) for kernel in kernels] == compiled
