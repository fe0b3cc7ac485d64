"""GPU speed of the whole pipeline and of each stage (CUDA events), beside OpenCV SGBM.

Frames: the synthetic road at 1280x720 and 1920x1080 and the real 2079x1040 pothole frames
(fan_potholes layout under --data). Each frame runs with the GPT band (the default per-pixel
shifts, and the paper's row shifts) and with the full range the frame needs without GPT.
Prints a Markdown table for docs/benchmarks.md.

    python benchmarks/bench_gpu.py [--frames 100] [--data DIR] [--long 10000] [--sgm-kernels]
        [--sgm-lanes 16 32]

``--sgm-lanes``: with ``--sgm-kernels``, the matcher's kernels also with each of these lane
counts per path line in place of the one the matcher picks (the same disparities; where a lane
count leaves no whole number of levels a lane, it is skipped).
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import sys
import time
from datetime import date
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pothole_detector.backend import StageClock, get_backend  # noqa: E402
from pothole_detector.calibration import StereoCalibration  # noqa: E402
from pothole_detector.imageio import read_image  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402
from pothole_detector.stages import census_sgm  # noqa: E402
from pothole_detector.stages.matching import sgm_disparity, to_gray8  # noqa: E402
from pothole_detector.stages.perspective import round_up_levels  # noqa: E402
from pothole_detector.evaluation.synthetic import demo_scene, render  # noqa: E402

STAGES = ("gpt", "sgm", "road", "dt", "slic", "threshold", "components", "refine", "measure",
          "graph", "readback")


def frames(data: Path | None, real_count: int):
    for width, height in ((1280, 720), (1920, 1080)):
        sample = render(demo_scene(width, height))
        yield (f"synthetic {width}x{height}", to_gray8(sample.left), to_gray8(sample.right),
               sample.calibration)
    if data is None:
        return
    for folder in sorted(data.glob("model1_*"))[:real_count]:
        left, right = to_gray8(read_image(folder / "left.png")), \
            to_gray8(read_image(folder / "right.png"))
        calibration = StereoCalibration.from_focal_baseline(1390, 0.1194, left.shape[1],
                                                            left.shape[0])
        yield f"real {folder.name} 2079x1040", left, right, calibration


def measure(config: Config, calibration: StereoCalibration, left: np.ndarray,
            right: np.ndarray, count: int, stream: bool = False) -> dict:
    """Median stage times of ``count`` frames after 5 warm-up frames, by Pipeline.run one
    frame at a time or (``stream``) by Pipeline.run_stream (the next pair staged in
    page-locked memory while the device works); ``period``: wall ms per frame."""
    backend = get_backend("gpu")
    gc.collect()  # earlier pipelines and their graphs' memory
    backend.release_memory()
    pipeline = Pipeline(config, calibration, backend)
    for _ in range(5):
        result = pipeline.run(left, right)
    runs = []
    started = time.perf_counter()
    outcomes = pipeline.run_stream((left, right) for _ in range(count)) if stream else \
        (pipeline.run(left, right) for _ in range(count))
    for outcome in outcomes:  # only the last result is kept, as a consumer would
        if isinstance(outcome, Exception):
            raise outcome
        result = outcome
        runs.append(result.timings_ms)
    period = (time.perf_counter() - started) * 1e3 / count
    medians = {key: float(np.median([r[key] for r in runs])) for key in runs[0]}
    medians["period"] = period
    medians["host_busy"] = float(np.median([r["host"] - r["host_wait"] for r in runs]))
    medians["levels"] = result.band[1]
    medians["range_hi"] = result.disparity_range[1]
    medians["memory_mib"] = backend.memory_bytes() / 2**20
    medians["potholes"] = len(result.potholes)
    return medians


class FixedLanes(census_sgm.GpuMatcher):
    """The GPU matcher with ``lanes`` threads per path line whatever the image."""

    def __init__(self, backend: Any, lanes: int) -> None:
        super().__init__(backend)
        self.fixed_lanes = lanes

    def lanes(self, height: int, width: int, levels: int) -> int:
        held = census_sgm.path_levels(levels)
        if held % self.fixed_lanes:
            raise ValueError(f"{held} levels held do not split into {self.fixed_lanes} lanes")
        return self.fixed_lanes


def sgm_kernel_times(left: np.ndarray, right: np.ndarray, calibration: StereoCalibration,
                     count: int, shift: str, lanes: int | None = None
                     ) -> tuple[int, int, dict[str, float]]:
    """The census matcher kernel by kernel on the GPT band of a frame (``shift``: the
    gpt_shift mode): its level count, lanes and median ms of census (with the GPT's gather of
    the right census words), paths (two launches), select and finish over ``count`` calls;
    with ``lanes``, that many threads per path line (FixedLanes) instead of the matcher's
    choice."""
    backend = get_backend("gpu")
    config = Config({"gpt_shift": shift})
    pipeline = Pipeline(config, calibration, backend)
    pipeline.run(left, right)
    shifts, levels = pipeline.band(left.shape)
    left_dev, right_dev, shifts_dev = backend.upload_many(left, right, shifts)
    matcher = census_sgm.GpuMatcher(backend) if lanes is None else FixedLanes(backend, lanes)
    runs = []
    for index in range(count + 5):
        clock = StageClock(backend)
        matcher(left_dev, right_dev, shifts_dev, levels, config.census_p1, config.census_p2,
                config.sgm_uniqueness_percent, config.lr_max_diff_px, config.median_filter,
                clock=clock)
        if index >= 5:
            runs.append(clock.timings())
    parts = {key: float(np.median([r[key] for r in runs])) for key in runs[0]}
    return levels, matcher.lanes(left.shape[0], left.shape[1], levels), parts


def sgm_kernels(left: np.ndarray, right: np.ndarray, calibration: StereoCalibration,
                count: int, shift: str, lanes: int | None = None) -> str:
    """:func:`sgm_kernel_times` as a line of text."""
    try:
        levels, lanes, parts = sgm_kernel_times(left, right, calibration, count, shift, lanes)
    except ValueError as exc:
        return f"{shift} shifts, {lanes} lanes: skipped ({exc})"
    return (f"{shift} shifts, {levels} levels, {lanes} lanes: "
            + ", ".join(f"{key} {value:.3f} ms" for key, value in parts.items())
            + f", sum {sum(parts.values()):.3f} ms")


def opencv_ms(left: np.ndarray, right: np.ndarray, levels: int, threads: int) -> float:
    cv2.setNumThreads(threads)
    config = Config({"lr_max_diff_px": -1, "speckle_window_px": 0, "median_filter": False})
    times = []
    for _ in range(3):
        start = time.perf_counter()
        sgm_disparity(left, right, levels, config)
        times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times))


def long_run(count: int) -> str:
    sample = render(demo_scene(1280, 720))
    backend = get_backend("gpu")
    backend.release_memory()
    pipeline = Pipeline(Config(), sample.calibration, backend)
    left, right = to_gray8(sample.left), to_gray8(sample.right)
    for _ in range(100):
        pipeline.run(left, right)
    before = backend.memory_bytes()
    start = time.perf_counter()
    for _ in range(count):
        pipeline.run(left, right)
    seconds = time.perf_counter() - start
    after = backend.memory_bytes()
    start = time.perf_counter()
    for outcome in pipeline.run_stream((left, right) for _ in range(count)):
        if isinstance(outcome, Exception):
            raise outcome
    streamed = time.perf_counter() - start
    final = backend.memory_bytes()
    return (f"{count} frames at 1280x720 in {seconds:.1f} s: device pool {before / 2**20:.1f} "
            f"MiB after 100 frames, {after / 2**20:.1f} MiB after {count} more; {count} more "
            f"by run_stream in {streamed:.1f} s, pool {final / 2**20:.1f} MiB")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data"
                        / "fan_potholes")
    parser.add_argument("--real", type=int, default=3,
                        help="real frames to time (the third has an 80-level band)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--long", type=int, default=0, help="frames of the memory-growth run")
    parser.add_argument("--sgm-kernels", action="store_true",
                        help="also time the census matcher kernel by kernel on each frame")
    parser.add_argument("--sgm-lanes", type=int, nargs="*", default=[],
                        help="with --sgm-kernels, also time these lanes per path line")
    args = parser.parse_args()
    import cupy  # the benchmark's own device query; the package imports CuPy in backend.py
    device = cupy.cuda.runtime.getDeviceProperties(0)["name"].decode()
    print(f"GPU benchmark, {date.today()}, {device}, CuPy {cupy.__version__}, "
          f"{platform.processor() or platform.machine()} with {os.cpu_count()} cores; median "
          f"over {args.frames} frames after 5 warm-up frames (same pair each frame, road model "
          "carried over as in a drive). Stage and total: CUDA events, ms; host: wall time of "
          "Pipeline.run (streamed: from the frame's start to its result, less the queueing of "
          "the next frame), ms; host busy: host less the waits for the frame's two readbacks "
          "(the host's own work per frame), ms; period: wall time of the whole run per frame, "
          "ms; stream: Pipeline.run_stream, the next pair staged in page-locked memory while "
          "the device works on this one and queued as soon as this one's road fit is read "
          "back; graph: SGM to measure replayed as CUDA graphs (the stage column graph; no "
          "graph: every stage timed on its own). SGBM / our SGM: against the no-graph sgm "
          f"stage. OpenCV SGBM 3WAY on {args.threads} threads, same "
          "frame, no LR check.\n")
    print("| frame | range | levels | " + " | ".join(STAGES)
          + " | total GPU | host | host busy | period | pool MiB | OpenCV SGBM "
          "| SGBM / our SGM | SGBM / pipeline |")
    print("| --- |" + " --- |" * (len(STAGES) + 10))
    data = args.data if args.data.is_dir() else None
    kernel_lines: list[str] = []
    staged = Config({"cuda_graph": False})
    for name, left, right, calibration in frames(data, args.real):
        stages = measure(staged, calibration, left, right, args.frames)
        stages_streamed = measure(staged, calibration, left, right, args.frames, stream=True)
        band = measure(Config(), calibration, left, right, args.frames)
        streamed = measure(Config(), calibration, left, right, args.frames, stream=True)
        rows = measure(Config({"gpt_shift": "row"}), calibration, left, right, args.frames)
        full_levels = round_up_levels(band["range_hi"] + 1)
        full_config = Config({"gpt_enabled": False, "max_disparity_px": full_levels})
        full = measure(full_config, calibration, left, right, args.frames)
        sgbm = opencv_ms(left, right, full_levels, args.threads)
        for label, row in (("GPT band, no graph", stages),
                           ("GPT band, no graph, stream", stages_streamed),
                           ("GPT band, graph", band), ("GPT band, graph, stream", streamed),
                           ("GPT band of row shifts, graph", rows), ("full, graph", full)):
            print(f"| {name} | {label} | {row['levels']} | "
                  + " | ".join(f"{row.get(s, 0.0):.3f}" for s in STAGES)
                  + f" | {row['total']:.3f} | {row['host']:.2f} | {row['host_busy']:.2f} | "
                  + f"{row['period']:.2f} | "
                  + f"{row['memory_mib']:.0f} | "
                  + f"{sgbm:.0f} ({full_levels} levels) | {sgbm / stages['sgm']:.0f}x | "
                  + f"{sgbm / row['total']:.0f}x |", flush=True)
        if args.sgm_kernels:
            kernel_lines += [
                f"- {name}: {sgm_kernels(left, right, calibration, args.frames, shift)}"
                for shift in ("pixel", "row")]
            kernel_lines += [
                f"- {name}: {sgm_kernels(left, right, calibration, args.frames, 'pixel', lanes)}"
                for lanes in args.sgm_lanes]
    if kernel_lines:
        print("\nCensus matcher kernel by kernel (CUDA events, median):\n"
              + "\n".join(kernel_lines))
    if args.long:
        print("\n" + long_run(args.long))


if __name__ == "__main__":
    main()
