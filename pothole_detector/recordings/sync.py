"""Pairing of left and right images by stamp (exact or approximate). Knows nothing of ROS."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

Item = TypeVar("Item")
SIDES = ("left", "right")


@dataclass
class SyncOutcome(Generic[Item]):
    """What one :meth:`StereoSynchronizer.add` produced.

    ``pairs``: (left stamp ns, left item, right item), oldest first; ``dropped``: items that
    can no longer be paired and were discarded; ``backwards``: a message saying that the stamps
    went backwards (the queues were cleared; the new item was kept); ``duplicate``: a message
    saying that the item repeats its side's newest stamp (it was dropped and counted)."""

    pairs: list[tuple[int, Item, Item]] = field(default_factory=list)
    dropped: int = 0
    backwards: str | None = None
    duplicate: str | None = None


class StereoSynchronizer(Generic[Item]):
    """Pairs left and right items by stamp.

    Exact mode pairs identical stamps. Approximate mode pairs an item with the other side's
    item nearest in time when they differ by at most ``tolerance_ns``. Items older than a
    pair just made are dropped; each side keeps at most ``queue_size`` waiting items."""

    def __init__(self, queue_size: int = 10, approximate: bool = False,
                 tolerance_ns: int = 10_000_000) -> None:
        if queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        self.queue_size = queue_size
        self.approximate = approximate
        self.tolerance_ns = tolerance_ns if approximate else 0
        self._queues: dict[str, deque[tuple[int, Any]]] = {s: deque() for s in SIDES}
        self._newest: dict[str, int | None] = {s: None for s in SIDES}

    @classmethod
    def from_config(cls, config: Any) -> "StereoSynchronizer[Any]":
        """A synchronizer set by ``queue_size``, ``approximate_sync`` and
        ``approximate_sync_tolerance_seconds`` of a :class:`~pothole_detector.params.Config`."""
        return cls(config.queue_size, config.approximate_sync,
                   int(round(config.approximate_sync_tolerance_seconds * 1e9)))

    def reset(self) -> int:
        """Forget every waiting item; returns how many were dropped."""
        dropped = sum(len(q) for q in self._queues.values())
        for side in SIDES:
            self._queues[side].clear()
            self._newest[side] = None
        return dropped

    def waiting(self, side: str) -> int:
        """How many items of ``side`` wait for a partner."""
        return len(self._queues[side])

    def add(self, side: str, stamp_ns: int, item: Item) -> SyncOutcome[Item]:
        """Offer one item of ``side`` ('left' or 'right') stamped ``stamp_ns`` (ns)."""
        if side not in SIDES:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        outcome: SyncOutcome[Item] = SyncOutcome()
        newest = self._newest[side]
        if newest is not None and stamp_ns == newest:
            outcome.duplicate = (f"two {side} images stamped {stamp_ns / 1e9:.9f} s: the second "
                                 "was dropped (is a driver republishing, or two publishers on "
                                 "the topic?)")
            outcome.dropped += 1
            return outcome
        if newest is not None and stamp_ns < newest:
            outcome.backwards = (
                f"{side} image stamps went backwards by {(newest - stamp_ns) / 1e9:.3f} s "
                "(bag looped or clock reset); unpaired images were dropped and the road model "
                "is seeded afresh"
            )
            outcome.dropped += self.reset()
        self._newest[side] = stamp_ns
        other = SIDES[1 - SIDES.index(side)]
        match = self._partner(self._queues[other], stamp_ns)
        if match is None:
            queue = self._queues[side]
            queue.append((stamp_ns, item))
            while len(queue) > self.queue_size:
                queue.popleft()
                outcome.dropped += 1
            return outcome
        partner_stamp, partner = self._queues[other][match]
        outcome.dropped += match
        for _ in range(match + 1):
            self._queues[other].popleft()
        outcome.dropped += self._drop_older(self._queues[side], stamp_ns)
        left, right = (item, partner) if side == "left" else (partner, item)
        left_stamp = stamp_ns if side == "left" else partner_stamp
        outcome.pairs.append((left_stamp, left, right))
        return outcome

    def _partner(self, queue: deque[tuple[int, Any]], stamp_ns: int) -> int | None:
        best, best_gap = None, None
        for index, (stamp, _) in enumerate(queue):
            gap = abs(stamp - stamp_ns)
            if gap <= self.tolerance_ns and (best_gap is None or gap < best_gap):
                best, best_gap = index, gap
        return best

    @staticmethod
    def _drop_older(queue: deque[tuple[int, Any]], stamp_ns: int) -> int:
        dropped = 0
        while queue and queue[0][0] < stamp_ns:
            queue.popleft()
            dropped += 1
        return dropped
