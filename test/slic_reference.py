"""SLIC's array form, the reference of stages/slic_cpu.py (the labels of kernels/slic.cu's
reference): each round, an array pass per neighbouring cell, then the centres by bincount."""

from __future__ import annotations

import numpy as np

from pothole_detector.stages.superpixels import _start


def slic_reference(image: np.ndarray, valid: np.ndarray, region_size: int, compactness: float,
                   iterations: int) -> tuple[np.ndarray, int]:
    """(int32 HxW labels, label count) of superpixels.slic on the CPU."""
    xp = np
    height, width = image.shape
    step, cells_y, cells_x, filled, centre_v, centre_u, centre_d = _start(
        xp, image, valid, region_size)
    n_labels = cells_y * cells_x
    pad_h, pad_w = cells_y * step - height, cells_x * step - width
    padded = xp.pad(filled, ((0, pad_h), (0, pad_w)), mode="edge")
    padded_valid = xp.pad(valid, ((0, pad_h), (0, pad_w)))
    blocks = padded.reshape(cells_y, step, cells_x, step)
    weight = padded_valid.reshape(blocks.shape).astype(xp.float32)
    rows = xp.arange(cells_y * step, dtype=xp.float32).reshape(cells_y, step, 1, 1)
    cols = xp.arange(cells_x * step, dtype=xp.float32).reshape(1, 1, cells_x, step)
    spatial_weight = xp.float32((compactness / step) ** 2)

    inside = xp.zeros((cells_y * step, cells_x * step), dtype=bool)
    inside[:height, :width] = True
    inside_flat = inside.ravel()
    v_flat = xp.broadcast_to(rows.reshape(-1, 1), inside.shape).ravel()
    u_flat = xp.broadcast_to(cols.reshape(1, -1), inside.shape).ravel()
    d_flat = padded.ravel()
    w_flat = (padded_valid & inside).ravel().astype(xp.float32)
    in_flat = inside_flat.astype(xp.float32)
    cell_i = xp.arange(cells_y, dtype=xp.int32).reshape(cells_y, 1, 1, 1)
    cell_j = xp.arange(cells_x, dtype=xp.int32).reshape(1, 1, cells_x, 1)
    far = xp.float32(1e9)

    labels = None
    for _ in range(iterations):
        grid_v = xp.pad(centre_v.reshape(cells_y, cells_x), 1, constant_values=far)
        grid_u = xp.pad(centre_u.reshape(cells_y, cells_x), 1, constant_values=far)
        grid_d = xp.pad(centre_d.reshape(cells_y, cells_x), 1)
        best = xp.full(blocks.shape, xp.inf, dtype=xp.float32)
        choice = xp.zeros(blocks.shape, dtype=xp.int8)
        for k, (di, dj) in enumerate((a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)):
            window = (slice(1 + di, 1 + di + cells_y), slice(1 + dj, 1 + dj + cells_x))
            cv = grid_v[window][:, None, :, None]
            cu = grid_u[window][:, None, :, None]
            cd = grid_d[window][:, None, :, None]
            distance = blocks - cd
            distance *= distance
            distance *= weight
            distance += spatial_weight * ((rows - cv) ** 2 + (cols - cu) ** 2)
            closer = distance < best
            xp.copyto(best, distance, where=closer)
            xp.copyto(choice, xp.int8(k), where=closer)
        label_i = cell_i + (choice // 3 - 1)
        label_j = cell_j + (choice % 3 - 1)
        labels = (label_i * cells_x + label_j).reshape(-1)
        count = xp.bincount(labels, weights=in_flat, minlength=n_labels)
        count_valid = xp.bincount(labels, weights=w_flat, minlength=n_labels)
        sum_v = xp.bincount(labels, weights=v_flat * in_flat, minlength=n_labels)
        sum_u = xp.bincount(labels, weights=u_flat * in_flat, minlength=n_labels)
        sum_d = xp.bincount(labels, weights=d_flat * w_flat, minlength=n_labels)
        occupied = count > 0
        centre_v = xp.where(occupied, sum_v / xp.maximum(count, 1), centre_v).astype(xp.float32)
        centre_u = xp.where(occupied, sum_u / xp.maximum(count, 1), centre_u).astype(xp.float32)
        centre_d = xp.where(count_valid > 0, sum_d / xp.maximum(count_valid, 1),
                            centre_d).astype(xp.float32)
    assert labels is not None
    return labels.reshape(inside.shape)[:height, :width].astype(xp.int32), n_labels
