"""`pothole-detector process` against OpenCV's SGBM alone, in the same run: a drive bag of our
generator (the survey drive, every frame rendered, or ``--distinct`` of its frames cycled with
fresh stamps) is processed end to end (bag reading, the pipeline on ``--backend``, every output
topic written into a new bag), and OpenCV's StereoSGBM (3WAY, block 5, 128 disparities, no
left-right check) matches the distinct pairs on the host's ``--threads``. Prints a Markdown
table for docs/benchmarks.md.

    python benchmarks/bench_process.py [--size 640x480] [--frames 20] [--threads 2]
        [--backend cpu|gpu] [--distinct N] [--storage mcap|sqlite3]
        [--compression zstd_fast [zstd lz4 none]] [--rounds 1]

With several ``--compression`` values (the mcap chunks' compression, recordings/bagwriter.py)
the drive is processed once with each, in turn, ``--rounds`` times; a row per run, with the
output bag's size.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import date
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pothole_detector.recordings.bagwriter import MCAP_COMPRESSIONS  # noqa: E402
from pothole_detector.recordings.writing import write_drive_bag  # noqa: E402
from pothole_detector.ros.bagtools import process  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.stages.matching import (set_host_threads, sgm_disparity,  # noqa: E402
                                               to_gray8)
from pothole_detector.evaluation.synthetic import render, survey_drive  # noqa: E402

SGBM_LEVELS = 128


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--backend", choices=("cpu", "gpu"), default="cpu")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                        help="process's output bag: mcap (compressed chunks) or sqlite3 (plain)")
    parser.add_argument("--distinct", type=int, default=0,
                        help="render this many frames of the drive and cycle them (0: all)")
    parser.add_argument("--compression", nargs="+", choices=tuple(MCAP_COMPRESSIONS),
                        default=["zstd_fast"], help="the mcap output's chunk compression(s)")
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    width, height = (int(n) for n in args.size.split("x"))
    set_host_threads(args.threads)
    cv2.setNumThreads(args.threads)
    scenes = survey_drive(frames=args.frames, width=width, height=height)
    if args.distinct:
        scenes = scenes[::max(1, args.frames // args.distinct)][:args.distinct]
    with ProcessPoolExecutor(args.threads, mp_context=get_context("spawn")) as pool:
        samples = list(pool.map(render, scenes))
    cycle = [i % len(samples) for i in range(args.frames)]
    with tempfile.TemporaryDirectory() as folder:
        bag = Path(folder) / "drive"
        write_drive_bag(bag, [scenes[i].camera_y_m for i in cycle],
                        [samples[i] for i in cycle], "odom", ground_truth=False)
        config = Config({"backend": args.backend})
        process(bag, Path(folder) / "warm", config, args.storage)  # compiled, caches warm
        runs = []
        for round_index in range(args.rounds):
            for compression in args.compression:
                out = Path(folder) / f"out_{compression}_{round_index}"
                started = time.perf_counter()
                summary = process(bag, out, config, args.storage, compression=compression)
                seconds = time.perf_counter() - started
                frames = max(summary.frames, 1)
                size = sum(path.stat().st_size for path in out.iterdir())
                runs.append((compression, summary, seconds * 1e3 / frames, size / frames / 1e6))
    sgbm_config = Config({"lr_max_diff_px": -1, "speckle_window_px": 0,
                          "median_filter": False})
    pairs = [(to_gray8(s.left), to_gray8(s.right)) for s in samples]
    sgbm_ms = []
    for left, right in pairs:
        begun = time.perf_counter()
        sgm_disparity(left, right, SGBM_LEVELS, sgbm_config)
        sgbm_ms.append((time.perf_counter() - begun) * 1e3)
    sgbm = float(np.mean(sgbm_ms))
    print(f"`process` on the {args.backend.upper()} against OpenCV SGBM alone, {date.today()}, "
          f"{platform.processor() or platform.machine()} with {os.cpu_count()} cores, "
          f"{args.threads} threads; {args.frames} frames of the survey drive at {args.size}"
          f"{f' ({len(samples)} distinct)' if args.distinct else ''}, output {args.storage}\n")
    print("| size | frames | output | processed | process ms/frame (all) | ms a frame, median "
          "| output MB a frame | OpenCV SGBM ms/frame | process / SGBM |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for compression, summary, process_ms, megabytes in runs:
        output = args.storage if args.storage == "sqlite3" else f"mcap, {compression}"
        print(f"| {args.size} | {args.frames} | {output} | {summary.frames} | "
              f"{process_ms:.1f} | {float(np.median(summary.milliseconds)):.1f} | "
              f"{megabytes:.2f} | {sgbm:.1f} | {process_ms / sgbm:.2f}x |")


if __name__ == "__main__":
    main()
