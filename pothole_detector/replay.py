"""The method over a recording: the pipeline on a bag's synchronized stereo sets in order, one
pipeline per run of frames from the same camera, and the tally of frames that failed. The
offline tools (``process``) and the survey both run their frames through here."""

from __future__ import annotations

import itertools
import logging
import re
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterator, Sequence

import numpy as np
from rosbags.highlevel import AnyReader

from .errors import PotholeError
from .params import Config
from .pipeline import Pipeline
from .recordings.bags import (BagFrame, LogSpan, SetCounts, convert_set, message_count,
                              read_sets_ahead, stereo_sets)
from .recordings.camera import pipeline_inputs
from .recordings.readahead import decoded_frames
from .recordings.topics import StereoTopics

_log = logging.getLogger(__name__)


def _reason_kind(reason: str) -> str:
    """A failure's reason with its numbers left out: failures alike count together."""
    return re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "#", reason)


@dataclass
class FailureTally:
    """Frames that could not be processed: per kind of reason (the reason with its numbers
    left out) how many, the first one's reason and stamp (ns)."""

    kinds: dict[str, list[Any]] = field(default_factory=dict)

    def add(self, stamp_ns: int, reason: str) -> None:
        entry = self.kinds.setdefault(_reason_kind(reason), [0, reason, stamp_ns])
        entry[0] += 1

    @property
    def total(self) -> int:
        return sum(entry[0] for entry in self.kinds.values())

    def rows(self) -> list[tuple[int, str, int]]:
        """(count, first reason, first stamp ns) per kind, most frequent first."""
        return sorted(((count, reason, stamp) for count, reason, stamp in self.kinds.values()),
                      key=lambda row: (-row[0], row[2]))

    def lines(self) -> list[str]:
        """One line per kind of reason."""
        return [f"{count} frame{'s' if count != 1 else ''} failed: {reason} (first at stamp "
                f"{stamp})" for count, reason, stamp in self.rows()]


@dataclass
class ProcessSummary:
    """What a run over a recording did (ros.bagtools.process, the survey): frames processed,
    failed (by reason), potholes found, images without a partner, messages that could not be
    read, time per processed frame."""

    frames: int = 0
    potholes: int = 0
    counts: SetCounts = field(default_factory=SetCounts)
    failures: FailureTally = field(default_factory=FailureTally)
    milliseconds: list[float] = field(default_factory=list)

    @property
    def failed(self) -> int:
        return self.failures.total

    @property
    def unpaired(self) -> int:
        return self.counts.unpaired

    def text(self) -> str:
        per_frame = float(np.mean(self.milliseconds)) if self.milliseconds else 0.0
        corrupt = (f", {self.counts.corrupt} corrupt messages skipped"
                   if self.counts.corrupt else "")
        return (f"{self.frames} frames, {self.potholes} potholes found, {per_frame:.0f} ms per "
                f"frame, {self.failed} failed, {self.unpaired} unpaired images{corrupt}")


def frame_results(reader: AnyReader, stereo: StereoTopics, config: Config, backend: Any,
                  summary: ProcessSummary,
                  progress: Callable[[int, int], None] | None = None,
                  span: LogSpan | None = None, read_threads: int = 1,
                  others: Sequence[str] = (), collected: list | None = None,
                  read_processes: int = 0, colour: bool = False
                  ) -> Iterator[tuple[BagFrame, Any]]:
    """(frame, PipelineResult or the PotholeError that stopped it) for the synchronized sets
    of a bag, or of a :class:`LogSpan` of it (with the sets of its lead before it: their
    ``logged_ns`` is before the span's start), in order; each frame carries the rectified
    pair's calibration and, where its images come raw, the rectification (the ``rectify``
    parameter). One pipeline per run of frames with the same stereo camera (its notes and
    whether it rectifies are logged once); within a run the host prepares the next pair while
    the device works (Pipeline.run_stream). ``progress(done, total)`` is called per set (of
    the whole bag's left images, or of a span's share of them). ``read_threads`` > 1: the bag
    is read ahead in that many threads (recordings.bags.read_sets_ahead; ``summary`` then
    counts no unpaired images) where its camera_info topics hold a message per image or so (a
    block then finds its infos in itself; a bag with latched infos is read in this thread);
    ``read_processes`` > 0: read and decoded by that many worker processes instead
    (recordings.readahead, on the same condition). The messages of the ``others`` topics
    logged in the span go into ``collected`` in the same pass (complete once the frames
    are). The pipeline takes the images as the matcher does (recordings.images.decode's
    ``grey``); ``colour``: each frame also keeps its left image in colour, for pictures (not
    with ``read_processes``)."""
    images = total = message_count(reader, stereo.left)
    if span is not None:
        bag_ns = max(reader.end_time - reader.start_time + 1, 1)
        total = round(total * min(span.stop_ns - span.start_ns, bag_ns) / bag_ns)

    def prepared() -> Iterator[BagFrame | tuple[BagFrame, PotholeError]]:
        streamed_infos = all(2 * message_count(reader, topic) >= images
                             for topic in (stereo.left_info, stereo.right_info))
        if read_processes > 0 and streamed_infos and not colour:
            for index, item in enumerate(decoded_frames(reader, stereo, config, span,
                                                        read_processes, others, collected,
                                                        summary.counts)):
                if progress is not None:
                    progress(min(index, total), total)
                yield item
            return
        sets = read_sets_ahead(reader, stereo, config, span, read_threads, others,
                               collected, summary.counts) \
            if read_threads > 1 and streamed_infos \
            else stereo_sets(reader, stereo, config, summary.counts, span, others, collected)
        for index, (stamp, logged, left_msg, right_msg, left_cal, right_cal) in enumerate(sets):
            if progress is not None:
                progress(min(index, total), total)
            try:
                left_px, right_px, camera, left_colour = convert_set(
                    stereo, left_msg, right_msg, left_cal, right_cal, config, colour)
            except PotholeError as exc:
                yield BagFrame(stamp, left_msg.header, None, None, None, logged), exc
                continue
            yield BagFrame(stamp, left_msg.header, left_px, right_px, camera, logged,
                           left_colour=left_colour)

    def key(item: BagFrame | tuple[BagFrame, PotholeError]) -> Any:
        return None if isinstance(item, tuple) else item.camera

    for camera, run in itertools.groupby(prepared(), key):
        if camera is None:
            yield from run
            continue
        try:
            calibration, rectification = pipeline_inputs(camera, config.rectify)
        except PotholeError as exc:
            for frame in run:
                yield frame, exc
            continue
        for note in camera.notes():
            _log.info(note)
        if rectification is not None:
            _log.info(f"raw images ({camera.left.distortion_model}): rectifying them from "
                      "camera_info")
        frames, streamed = itertools.tee(run)
        outcomes = Pipeline(config, calibration, backend, rectification).run_stream(
            (frame.left, frame.right) for frame in streamed)
        for frame in frames:
            yield replace(frame, calibration=calibration, rectification=rectification), \
                next(outcomes)
    if progress is not None:
        progress(total, total)

