"""Every CPU kernel of the stages (Numba's) compiled, or loaded from Numba's cache, now, on
small inputs: set-up runs it (``python -m pothole_detector.stages``), and the node before its
first frame, so that no frame waits for the compiler."""

from __future__ import annotations

import numpy as np

from ..backend import CPU
from . import census_sgm, components, photometric, rectify, refine, superpixels, threshold
from .road_model import RoadModel


def compile_cpu_kernels(census: bool = True) -> None:
    """The census matcher's kernels (``census``: the matcher in use is ours), rectification's,
    SLIC's and the host passes of the threshold, photometric, refinement and component
    stages."""
    if census:
        census_sgm.compile_cpu_kernels()
    rectify.compile_cpu_kernel()
    superpixels.compile_cpu_kernels()
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (24, 40), dtype=np.uint8)
    disparity = rng.normal(20.0, 1.0, image.shape).astype(np.float32)
    disparity[::5, ::7] = np.nan
    photometric.disagreement(CPU, image, image, disparity)
    threshold.threshold_search(CPU, disparity, 0.25, 20.0)
    filled, smoothed = refine.smooth(CPU, disparity)
    labels = np.zeros(image.shape, np.int32)
    labels[8:16, 10:20] = 1
    refine.extend_occluded(CPU, labels, filled, smoothed, RoadModel(np.float64(20.0),
                                                                    np.float64(0.0), 0.0),
                           np.zeros(image.shape, np.int32), np.ones(1, bool))
    components.join_pieces(CPU, labels, 2, np.zeros(1, np.int32), 2)
