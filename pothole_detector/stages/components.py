"""Connected components over the selected superpixels, with the paper's filters."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..backend import Backend, to_host

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
                       n_superpixels: int, corner_fraction: float,
                       min_superpixels: int) -> tuple[Any, int]:
    """Label the 8-connected components of the HxW bool ``candidate`` mask; drop components
    that touch a corner region of the HxW bool ``valid`` area (see corner_mask) or hold fewer
    than ``min_superpixels`` superpixels.

    Returns (int32 HxW labels numbered 1..k, 0 elsewhere; k).
    """
    xp = backend.xp
    components, count = backend.ndimage.label(candidate, structure=xp.asarray(EIGHT_CONNECTED))
    count = int(count)
    if count == 0:
        return components.astype(xp.int32), 0
    keep = xp.ones(count + 1, dtype=bool)
    keep[0] = False
    touched = components[corner_mask(xp, valid, corner_fraction)]
    keep[touched] = False
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
