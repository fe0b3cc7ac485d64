from __future__ import annotations

import numpy as np

from pothole_detector.backend import CPU
from pothole_detector.stages.components import (components_found, far_corners, in_far_corner,
                                                join_pieces, relabel)


def grid_superpixels(height, width, step):
    v, u = np.mgrid[0:height, 0:width]
    return (v // step) * (width // step) + u // step, (height // step) * (width // step)


def test_filters_single_superpixel_and_keeps_diagonal_neighbours():
    height, width = 100, 100
    superpixels, n = grid_superpixels(height, width, 10)
    candidate = np.zeros((height, width), bool)
    candidate[40:50, 40:50] = True        # one superpixel
    candidate[60:70, 60:70] = True        # two superpixels touching diagonally
    candidate[70:80, 70:80] = True
    labels, count = components_found(CPU, candidate, np.ones_like(candidate), superpixels, n, 2)
    assert count == 1
    assert labels[65, 65] == 1 and labels[75, 75] == 1 and labels[45, 45] == 0


def corner_mask(valid, fraction):
    return in_far_corner(far_corners(CPU, valid, fraction), *np.indices(valid.shape))


def test_corner_regions_follow_the_valid_area():
    valid = np.ones((50, 100), bool)
    valid[:, :30] = False
    mask = corner_mask(valid, 0.2)
    assert mask[0, 30:40].all() and not mask[0, 40:50].any()
    assert mask[0, 90:100].all() and not mask[20, 35]
    corners = far_corners(CPU, valid, 0.2)
    assert corners.side == 10 and corners.first[0] == 30 and corners.last[0] == 99


def test_only_the_top_corners_are_far():
    """The top corners are where the road is farthest; a pothole in a near (bottom) corner
    is seen best."""
    mask = corner_mask(np.ones((100, 100), bool), 0.1)
    assert mask[:10, :10].all() and mask[:10, 90:].all() and not mask[10:].any()
    assert mask.sum() == 200


def test_relabel_renumbers_in_order():
    labels = np.array([[0, 1, 2, 3]])
    new, count = relabel(np, labels, np.array([False, True, False, True]))
    np.testing.assert_array_equal(new, [[0, 1, 0, 2]])
    assert count == 2


def test_labelling_the_reduced_grid_gives_the_full_resolution_labels():
    """A mask enlarged by whole pixels (SLIC grid -> frame) has the same 8-connected
    components in the same order; odd frame sizes repeat the last row and column."""
    from pothole_detector.stages.superpixels import upsample_labels
    rng = np.random.default_rng(5)
    for factor, (height, width) in ((2, (61, 97)), (3, (90, 120)), (2, (40, 41))):
        small = rng.random((height // factor, width // factor)) < 0.35
        full = upsample_labels(CPU, small, factor, (height, width))
        valid = np.ones((height, width), bool)
        valid[:, :7] = False
        superpixels = (np.arange(height)[:, None] // 8) * 64 + np.arange(width)[None, :] // 8
        n = int(superpixels.max()) + 1
        expected = components_found(CPU, full, valid, superpixels, n, 1)
        found = components_found(CPU, small, valid, superpixels, n, 1, factor=factor)
        assert found[1] == expected[1] > 3
        np.testing.assert_array_equal(found[0], expected[0])


def test_a_component_mostly_of_inconsistent_superpixels_is_dropped():
    """Two components of four superpixels each: one with three flagged (dropped), one with two
    (kept: no more than half)."""
    height, width = 60, 100
    superpixels, n = grid_superpixels(height, width, 10)
    candidate = np.zeros((height, width), bool)
    candidate[20:40, 10:30] = True        # superpixels 21, 22, 31, 32
    candidate[20:40, 60:80] = True        # superpixels 26, 27, 36, 37
    flagged = np.zeros(n, bool)
    flagged[[21, 22, 31]] = True
    flagged[[26, 27]] = True
    labels, count = components_found(CPU, candidate, np.ones_like(candidate), superpixels, n,
                                     2, inconsistent=flagged)
    assert count == 1 and labels[30, 70] == 1 and labels[30, 20] == 0


def test_a_component_beside_a_bump_is_dropped():
    """A matcher that moved an edge reads a dip beside a bump: the component touching a bump
    superpixel goes, one two superpixels away from it stays, and so does the reduced-grid
    labelling's result."""
    height, width = 60, 100
    superpixels, n = grid_superpixels(height, width, 10)
    candidate = np.zeros((height, width), bool)
    candidate[20:40, 10:30] = True        # superpixels 21, 22, 31, 32; 23 lies beside it
    candidate[20:40, 60:80] = True        # superpixels 26, 27, 36, 37; 29 does not
    bumps = np.zeros(n, bool)
    bumps[[23, 29]] = True
    labels, count = components_found(CPU, candidate, np.ones_like(candidate), superpixels, n,
                                     2, bumps=bumps)
    assert count == 1 and labels[30, 70] == 1 and labels[30, 20] == 0
    small = candidate[::2, ::2]
    reduced = components_found(CPU, small, np.ones_like(candidate), superpixels, n, 2,
                               factor=2, bumps=bumps)
    np.testing.assert_array_equal(reduced[0], labels)


def test_pieces_of_one_depression_join_and_others_keep_apart():
    """Three pieces: two 3 px apart (within twice the reach of 2 px) become one component, one
    15 px away stays apart; numbered in raster order, the count written; road stays 0. On the
    grid reduced by 2 the same, and with no reach the two stay apart."""
    labels = np.zeros((41, 61), np.int32)
    labels[5:10, 5:15] = 1
    labels[5:10, 18:25] = 2       # a gap of 3 columns from piece 1
    labels[20:25, 40:50] = 3
    labels[40, 60] = 4            # a lone pixel in the odd last row and column
    for factor in (1, 2):
        count = np.zeros(1, np.int32)
        joined = join_pieces(CPU, labels, 2, count, factor)
        assert count[0] == 3 and joined.dtype == np.int32
        assert set(np.unique(joined[5:10, 5:25][labels[5:10, 5:25] > 0])) == {1}
        assert (joined[20:25, 40:50] == 2).all() and joined[40, 60] == 3
        assert (joined[labels == 0] == 0).all()
        apart = join_pieces(CPU, labels, 0, count, factor)
        assert count[0] == 4 and len(np.unique(apart)) == 5


def test_pieces_join_across_depressed_road_and_not_across_level_road():
    """Superpixels of 4 x 4 cells on a grid reduced by 2. Pieces 1 and 2 lie 9 px apart:
    beyond the reach of 2 px, they join where the road between them is depressed (within the
    bridge of 8 px of each), and stay apart where it is level. A depressed superpixel that
    no piece reaches is no component, and pieces 18 px apart (more than two bridges) stay
    apart however depressed the road between them: the count and the numbering (raster
    order) hold only pieces."""
    labels = np.zeros((32, 64), np.int32)
    labels[8:16, 0:15] = 1
    labels[8:16, 24:40] = 2
    labels[8:16, 58:64] = 3         # 18 px beyond piece 2
    grid, _ = grid_superpixels(16, 32, 4)
    level = np.zeros(grid.max() + 1, bool)
    depressed = level.copy()
    depressed[grid[4:8, 7:12]] = True   # the gap between pieces 1 and 2 (px 15-23)
    depressed[grid[12:16, 0:4]] = True  # far below piece 1, beyond its bridge
    depressed[grid[4:8, 20:29]] = True  # the gap between pieces 2 and 3 (px 40-57)
    count = np.zeros(1, np.int32)
    joined = join_pieces(CPU, labels, 2, count, 2, grid, depressed, 8)
    assert count[0] == 2
    assert (joined[labels == 1] == 1).all() and (joined[labels == 2] == 1).all()
    assert (joined[labels == 3] == 2).all() and (joined[labels == 0] == 0).all()
    apart = join_pieces(CPU, labels, 2, count, 2, grid, level, 8)
    assert count[0] == 3 and [apart[8, 0], apart[8, 24], apart[8, 58]] == [1, 2, 3]


def test_the_cells_holding_a_label_are_the_padded_block_form():
    from pothole_detector.stages.components import _cells_on
    rng = np.random.default_rng(12)
    for shape, factor in (((20, 30), 2), ((21, 31), 2), ((25, 17), 3), ((8, 8), 1)):
        labels = (rng.random(shape) < 0.05) * rng.integers(1, 4, shape).astype(np.int32)
        on = labels > 0
        padded = np.pad(on, ((0, -shape[0] % factor), (0, -shape[1] % factor)))
        want = padded.reshape(padded.shape[0] // factor, factor, padded.shape[1] // factor,
                              factor).any(axis=(1, 3)).astype(np.uint8)
        np.testing.assert_array_equal(_cells_on(labels, factor), want)
