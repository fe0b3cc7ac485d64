"""Connected components over the selected superpixels, with the paper's filters."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..backend import Backend, to_host
from .superpixels import upsample_labels

EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)


def corner_mask(xp: Any, valid: Any, fraction: float) -> Any:
    """HxW bool: the corner regions of the area that has disparities.

    Side = ``fraction`` x the short image side. In the top and bottom ``side`` rows, the first
    and last ``side`` columns of each row's valid span are corner (a disparity map's left
    border is never valid, so the image corner itself is not where the data ends).
    """
    height, width = valid.shape
    side = int(round(fraction * min(height, width)))
    mask = xp.zeros((height, width), dtype=bool)
    if side <= 0:
        return mask
    has_valid = valid.any(axis=1)
    first = xp.where(has_valid, xp.argmax(valid, axis=1), 0)
    last = xp.where(has_valid, width - 1 - xp.argmax(valid[:, ::-1], axis=1), width - 1)
    cols = xp.arange(width)[None, :]
    band = xp.zeros(height, dtype=bool)
    band[:side] = True
    band[height - side:] = True
    near_end = (cols < first[:, None] + side) | (cols > last[:, None] - side)
    return band[:, None] & near_end


def pothole_components(backend: Backend, candidate: Any, valid: Any, superpixel_labels: Any,
                       n_superpixels: int, corner_fraction: float, min_superpixels: int,
                       factor: int = 1) -> tuple[Any, int]:
    """Label the 8-connected components of the bool ``candidate`` mask; drop components that
    touch a corner region of the HxW bool ``valid`` area (see corner_mask) or hold fewer than
    ``min_superpixels`` superpixels (HxW ``superpixel_labels``).

    ``candidate`` is HxW, or the mask on the SLIC grid reduced by ``factor`` whose
    nearest-neighbour enlargement (superpixels.upsample_labels) is the HxW mask: enlarging by
    whole pixels keeps 8-connectivity and the raster order of components, so labelling the
    small mask and enlarging the labels gives the same labels with factor^2 fewer pixels.

    Returns (int32 HxW labels numbered 1..k, 0 elsewhere; k).
    """
    xp = backend.xp
    if backend.is_gpu:
        return _components_gpu(backend, candidate, valid, superpixel_labels, n_superpixels,
                               corner_fraction, min_superpixels, factor)
    components, count = label_components(backend, candidate)
    components = upsample_labels(xp, components, factor, valid.shape)
    if count == 0:
        return components.astype(xp.int32), 0
    keep = xp.ones(count + 1, dtype=bool)
    keep[components[corner_mask(xp, valid, corner_fraction)]] = False
    keep[0] = False
    pairs = components.ravel().astype(xp.int64) * n_superpixels + superpixel_labels.ravel()
    present = xp.bincount(pairs[components.ravel() > 0], minlength=(count + 1) * n_superpixels)
    superpixel_count = (present.reshape(count + 1, n_superpixels) > 0).sum(axis=1)
    keep &= superpixel_count >= min_superpixels
    return relabel(xp, components, keep)


def relabel(xp: Any, labels: Any, keep: Any) -> tuple[Any, int]:
    """Keep the labels where the bool (k+1,) ``keep`` is true, renumbered 1..m in order."""
    new_ids = xp.cumsum(keep).astype(xp.int32) * keep
    kept = int(to_host(keep.sum()))
    return new_ids[labels].astype(xp.int32), kept


def label_components(backend: Backend, mask: Any) -> tuple[Any, int]:
    """8-connected components of an HxW bool mask: (int32 HxW labels 1..k in raster order of
    each component's first pixel, 0 off the mask; k). scipy.ndimage.label on the CPU; on the
    GPU union-find kernels (kernels/components.cu), one readback of k and no uploads."""
    if not backend.is_gpu:
        labels, count = backend.ndimage.label(mask, structure=EIGHT_CONNECTED)
        return labels.astype(np.int32), int(count)
    xp = backend.xp
    height, width = mask.shape
    size = height * width
    if size == 0:
        return xp.zeros((height, width), dtype=xp.int32), 0
    parent = xp.empty(size, dtype=xp.int32)
    is_root = xp.empty(size, dtype=xp.int32)
    labels = xp.empty((height, width), dtype=xp.int32)
    grid, block = ((size + 255) // 256,), (256,)
    kernel = backend.kernel
    kernel("components.cu", "label_init", {})(
        grid, block, (xp.ascontiguousarray(mask, dtype=xp.bool_), parent, np.int32(size)))
    kernel("components.cu", "label_merge", {})(
        grid, block, (parent, np.int32(height), np.int32(width)))
    kernel("components.cu", "label_flatten", {})(grid, block, (parent, is_root, np.int32(size)))
    root_count = xp.cumsum(is_root, dtype=xp.int32)
    kernel("components.cu", "label_number", {})(
        grid, block, (parent, root_count, labels, np.int32(size)))
    return labels, int(to_host(root_count[-1]))


def _components_gpu(backend: Backend, candidate: Any, valid: Any, superpixel_labels: Any,
                    n_superpixels: int, corner_fraction: float, min_superpixels: int,
                    factor: int) -> tuple[Any, int]:
    """pothole_components on the GPU: union-find labels of the (reduced) candidate mask, then
    kernels/components.cu reads them at full resolution by index arithmetic: per-row valid
    spans, corner and superpixel marks, the keep/renumber table (one block) and the final
    labels. Readbacks: the component count and the kept count."""
    xp = backend.xp
    height, width = valid.shape
    small, count = label_components(backend, candidate)
    if count == 0:
        return xp.zeros((height, width), dtype=xp.int32), 0
    small_height, small_width = small.shape
    i32 = np.int32
    kernel = backend.kernel
    first = xp.empty(height, dtype=xp.int32)
    last = xp.empty(height, dtype=xp.int32)
    kernel("components.cu", "row_extents", {})(
        ((height + 7) // 8,), (256,),
        (xp.ascontiguousarray(valid, dtype=xp.bool_), i32(height), i32(width), first, last))
    marks = xp.zeros((count + 1) * (1 + n_superpixels), dtype=xp.uint8)
    touched, present = marks[:count + 1], marks[count + 1:]
    side = int(round(corner_fraction * min(height, width)))
    size = height * width
    grid = ((size + 255) // 256,)
    kernel("components.cu", "component_marks", {})(
        grid, (256,),
        (small, xp.ascontiguousarray(superpixel_labels, dtype=xp.int32), first, last,
         i32(height), i32(width), i32(factor), i32(small_height), i32(small_width), i32(side),
         i32(n_superpixels), touched, present))
    numbers = xp.empty(count + 2, dtype=xp.int32)
    new_id, kept = numbers[:count + 1], numbers[count + 1:]
    kernel("components.cu", "component_keep", {})(
        (1,), (1024,), (touched, present, i32(count), i32(n_superpixels), i32(min_superpixels),
                        new_id, kept))
    labels = xp.empty((height, width), dtype=xp.int32)
    kernel("components.cu", "component_relabel", {})(
        grid, (256,), (small, new_id, labels, i32(height), i32(width), i32(factor),
                       i32(small_height), i32(small_width)))
    return labels, int(to_host(kept)[0])
