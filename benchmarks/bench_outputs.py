"""What each output topic costs the host: the time to make the node's output messages from one
pipeline result (ros/outputs.output_messages: the arrays read back, converted and drawn), all of
them together and each alone, on results of the survey drive's frames. The node makes an output
only while somebody subscribes to it, on its worker thread, before it takes the next stereo
set. Prints a Markdown table for docs/benchmarks.md.

    python benchmarks/bench_outputs.py [--sizes 640x480 1280x720] [--backend cpu|gpu]
        [--repeat 10] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from datetime import date
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pothole_detector.backend import get_backend  # noqa: E402
from pothole_detector.evaluation.synthetic import render, survey_drive  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402
from pothole_detector.recordings.messages import header_at  # noqa: E402
from pothole_detector.ros.outputs import ON_REQUEST, output_messages  # noqa: E402
from pothole_detector.stages.matching import set_host_threads  # noqa: E402

DISTINCT_FRAMES = 4


def median_ms(results: Sequence[Any], lefts: Sequence[np.ndarray], calibration: Any,
              wanted: Sequence[str], repeat: int) -> float:
    """Median time (ms) of one result's messages of ``wanted``, over ``repeat`` rounds of
    every result after one untimed round."""
    header = header_at(0, "left")
    times = []
    for round_index in range(repeat + 1):
        for result, left in zip(results, lefts):
            start = time.perf_counter()
            output_messages(result, left, calibration, header, wanted)
            if round_index:
                times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["640x480", "1280x720"])
    parser.add_argument("--backend", choices=("cpu", "gpu"), default="cpu")
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    set_host_threads(args.threads)
    backend = get_backend(args.backend)
    print(f"Output messages from one result, {backend.name} backend, {date.today()}, "
          f"{platform.machine()} with {os.cpu_count()} cores, {args.threads} threads; median ms "
          f"over {args.repeat} rounds of {DISTINCT_FRAMES} results\n")
    print("| size | potholes a frame | all outputs | " + " | ".join(ON_REQUEST) + " |")
    print("| --- | --- | --- | " + " | ".join("---" for _ in ON_REQUEST) + " |", flush=True)
    for size in args.sizes:
        width, height = (int(v) for v in size.lower().split("x"))
        scenes = [replace(s, supersample=1) for s in survey_drive(
            frames=DISTINCT_FRAMES * 4, width=width, height=height)[::4]]
        with ProcessPoolExecutor(len(scenes), mp_context=get_context("spawn")) as pool:
            samples = list(pool.map(render, scenes))
        calibration = samples[0].calibration
        pipeline = Pipeline(Config({"backend": args.backend}), calibration, backend)
        pairs = [(sample.left, sample.right) for sample in samples]
        results = list(pipeline.run_stream(pairs + pairs))[len(pairs):]
        lefts = [sample.left for sample in samples]
        every = median_ms(results, lefts, calibration, ON_REQUEST, args.repeat)
        alone = [median_ms(results, lefts, calibration, (name,), args.repeat)
                 for name in ON_REQUEST]
        potholes = np.mean([len(result.potholes) for result in results])
        print(f"| {width}x{height} | {potholes:.1f} | {every:.1f} | "
              + " | ".join(f"{ms:.1f}" for ms in alone) + " |", flush=True)


if __name__ == "__main__":
    main()
