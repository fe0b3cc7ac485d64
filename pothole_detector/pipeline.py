"""The detector: the method (method.py) run by its executor (execution.py). Knows nothing of
ROS.

Stereo pairs go in through :meth:`Pipeline.run` or :meth:`Pipeline.run_stream` and come out
as PipelineResults; the method's stages and its road model are method.Method's, how frames
are executed (upload buffers, the frame report and its readbacks, CUDA graphs, two frames in
flight) execution.FrameExecutor's.
"""

from __future__ import annotations

from typing import Iterable, Iterator

import numpy as np

from .backend import CPU, Backend
from .calibration import StereoCalibration
from .errors import PotholeError
from .execution import FrameExecutor
from .method import Method, PipelineResult
from .params import Config
from .stages.rectify import Rectification


class Pipeline(Method):
    """Stereo pair in, potholes out: the method with the executor that runs it."""

    def __init__(self, config: Config, calibration: StereoCalibration,
                 backend: Backend = CPU, rectification: Rectification | None = None) -> None:
        """``calibration``: the rectified pair's; ``rectification``: where the images come
        raw, the tables that rectify them into that pair's frame (stages/rectify.py)."""
        super().__init__(config, calibration, backend, rectification)
        self.executor = FrameExecutor(self)

    def run(self, left: np.ndarray, right: np.ndarray) -> PipelineResult:
        """Detect potholes in a pair of host images (HxW mono or HxWx3 RGB, uint8 or uint16):
        rectified, or raw where the pipeline has a rectification (then rectified on the
        backend; the results are in the rectified frame). Raises InputError, NoTextureError or
        NoRoadError with a message saying why."""
        return self.executor.run(left, right)

    def run_stream(self, pairs: Iterable[tuple[np.ndarray, np.ndarray]]
                   ) -> Iterator[PipelineResult | PotholeError]:
        """:meth:`run` over a sequence of pairs: yields, in order, each pair's result or the
        error it raised (the stream goes on after an error), the same results as :meth:`run`
        pair after pair; on the GPU the next pair is uploaded and queued while the device
        works on this one (execution.FrameExecutor.run_stream)."""
        yield from self.executor.run_stream(pairs)
