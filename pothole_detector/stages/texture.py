"""How much less precise the matcher is on a superpixel for the texture it has.

A match is as precise as the image is textured along the rows: the disparity noise of block
matching falls as the image's horizontal gradient grows (its Cramér-Rao bound goes as the
inverse of the RMS gradient over the block). The local road reference measures the noise of
the road's superpixels around each one, which are as textured as the road typically is; a
superpixel with less texture (the inside of a lane marking, a smooth or overexposed patch),
whose disparities the matcher fills in from its edges, is noisier than they are by the ratio
of the RMS gradients.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..backend import Backend
from .road_model import masked_median
from .superpixels import superpixel_means

# RMS gradient (grey levels) that a superpixel without any gradient counts as
FLAT_RMS_GREY = 1e-3
# kernels/texture.cu: threads of a block
_THREADS = 256


def gradient_energy(backend: Backend, left: Any, valid: Any) -> Any:
    """The squared horizontal gradient of the uint8 HxW ``left`` image, (I(u+1) - I(u-1))^2 / 4
    (grey levels^2), where the bool HxW ``valid`` holds and both neighbours exist: float32
    HxW, NaN elsewhere. On the GPU one kernel (kernels/texture.cu)."""
    xp = backend.xp
    if backend.is_gpu:
        height, width = left.shape
        size = height * width
        energy = xp.empty((height, width), dtype=xp.float32)
        backend.kernel("texture.cu", "gradient_energy", {})(
            (-(-size // _THREADS),), (_THREADS,),
            (xp.ascontiguousarray(left, dtype=xp.uint8),
             xp.ascontiguousarray(valid, dtype=xp.bool_), np.int64(size), np.int32(width), energy))
        return energy
    image = left.astype(xp.float32)
    energy = xp.full(image.shape, xp.nan, dtype=xp.float32)
    energy[:, 1:-1] = 0.25 * (image[:, 2:] - image[:, :-2]) ** 2
    return xp.where(valid, energy, xp.float32(xp.nan))


def deficit(backend: Backend, left: Any, valid: Any, labels: Any, count: int,
            observed: Any) -> Any:
    """Per superpixel, the factor by which its disparity noise exceeds that of the road's
    typical superpixel for lack of texture: the median RMS horizontal gradient of the
    ``observed`` superpixels (bool (count,)) over its own, at least 1; 1 where it has no valid
    pixel, and everywhere where none is observed. A superpixel without any gradient (flat,
    saturated) counts as FLAT_RMS_GREY, so that its noise is large but finite. ``left``:
    uint8 HxW; ``valid``: bool HxW (the pixels with a disparity); ``labels``: int32 HxW
    superpixel labels 0..count-1. Returns float64 (count,); nothing read back. On the GPU
    two kernels about a sort (kernels/texture.cu)."""
    xp = backend.xp
    energy, _ = superpixel_means(backend, gradient_energy(backend, left, valid), labels, count)
    if backend.is_gpu:
        rms = xp.empty(count, dtype=xp.float64)
        keys = xp.empty(count, dtype=xp.float64)
        blocks = (-(-count // _THREADS),)
        backend.kernel("texture.cu", "texture_keys", {})(
            blocks, (_THREADS,), (energy, xp.ascontiguousarray(observed, dtype=xp.bool_),
                                  np.int32(count), rms, keys))
        out = xp.empty(count, dtype=xp.float64)
        backend.kernel("texture.cu", "texture_deficit", {})(
            blocks, (_THREADS,), (rms, xp.sort(keys), np.int32(count),
                                  np.float64(FLAT_RMS_GREY), out))
        return out
    rms = xp.sqrt(energy.astype(xp.float64))
    typical, used = masked_median(xp, rms, observed & xp.isfinite(rms))
    known = xp.isfinite(rms) & (used > 0)
    ratio = typical / xp.maximum(xp.where(known, rms, 1.0), FLAT_RMS_GREY)
    return xp.where(known, xp.maximum(ratio, 1.0), 1.0)
