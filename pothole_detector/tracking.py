"""Pothole ids that stay the same while a pothole stays in view: each frame's potholes take the
id of the previous frame's pothole whose footprint on the road overlaps theirs."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .stages.measure import Pothole


# the largest id: the label image (pothole_labels) is mono16
MAX_ID = 65535


class StableIds:
    """Gives ids (1, 2, ...) to potholes frame after frame. Two potholes of consecutive frames
    are the same where their footprints overlap: circles of the pothole's area about its
    centroid (left optical frame, m) closer than the sum of their radii; the largest overlap
    pairs first. A pothole that matches none takes the next id; ids count up to MAX_ID (the
    label image is 16-bit) and then start again at 1."""

    def __init__(self) -> None:
        self._previous: list[tuple[int, np.ndarray, float]] = []
        self._next = 1

    def reset(self) -> None:
        """Forget the previous frame (a gap in the input, a new drive)."""
        self._previous = []

    def assign(self, potholes: Sequence[Pothole]) -> list[int]:
        """The id of each of ``potholes`` (this frame's, in order)."""
        current = [(np.asarray(p.centroid_cam_m, dtype=np.float64),
                    math.sqrt(max(p.area_m2, 0.0) / math.pi)) for p in potholes]
        pairs = sorted(((float(np.linalg.norm(c - pc)) - r - pr, i, j)
                        for i, (c, r) in enumerate(current)
                        for j, (_, pc, pr) in enumerate(self._previous)
                        if np.all(np.isfinite(c)) and np.all(np.isfinite(pc))))
        ids: list[int | None] = [None] * len(current)
        taken: set[int] = set()
        for gap, i, j in pairs:
            if gap < 0 and ids[i] is None and j not in taken:
                ids[i] = self._previous[j][0]
                taken.add(j)
        for i, given in enumerate(ids):
            if given is None:
                ids[i] = self._next
                self._next = self._next % MAX_ID + 1
        final = [int(i) for i in ids if i is not None]
        self._previous = [(final[i], c, r) for i, (c, r) in enumerate(current)]
        return final


def relabel(labels: np.ndarray, potholes: Sequence[Pothole], ids: Sequence[int]) -> np.ndarray:
    """``labels`` (int HxW, 0 = road, k = the pothole of label k) with each of ``potholes``
    renamed to its entry of ``ids``."""
    table = np.zeros(max((p.label for p in potholes), default=0) + 1, dtype=np.int64)
    for pothole, given in zip(potholes, ids):
        table[pothole.label] = given
    inside = (labels > 0) & (labels < table.size)
    renamed = np.where(inside, table[np.where(inside, labels, 0)], 0).astype(labels.dtype)
    return renamed
