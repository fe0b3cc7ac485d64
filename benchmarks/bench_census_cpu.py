"""CPU speed of the census SGM's Numba kernels alone (stages/census_cpu.py): the matching
cost, the eight path costs and the winner search, on census words of a textured pair shifted
by 5 px (the real pipeline's band sizes). Prints a Markdown table.

    python benchmarks/bench_census_cpu.py [--repeat N] [--threads T]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from datetime import date
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pothole_detector.stages import census_cpu  # noqa: E402
from pothole_detector.stages.matching import set_host_threads  # noqa: E402

SIZES = ((640, 480, 64), (1280, 720, 64), (2079, 1040, 64))
P1, P2, UNIQUENESS, LR = 3, 20, 5, 1


def median_ms(run: Callable[[], object], repeat: int) -> float:
    """Median wall time (ms) of ``repeat`` calls after one warm-up."""
    run()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        run()
        times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    set_host_threads(args.threads)
    print(f"Census SGM CPU kernels, {date.today()}, {platform.processor() or platform.machine()}"
          f", {os.cpu_count()} cores, Numba on {args.threads} threads; median ms over "
          f"{args.repeat} runs after one warm-up\n")
    print("| size | levels | cost | paths | select | total |")
    print("| --- | --- | --- | --- | --- | --- |")
    rng = np.random.default_rng(0)
    for width, height, levels in SIZES:
        left = rng.integers(0, 1 << 31, (height, width), dtype=np.uint32)
        noise = (rng.random((height, width)) < 0.05).astype(np.uint32)
        right = np.roll(left, -5, axis=1) ^ noise
        first = np.zeros(height, dtype=np.int64)
        cost = census_cpu.matching_cost(left, right, first, levels, 31)
        total = census_cpu.path_sums(cost, P1, P2)
        times = [median_ms(lambda: census_cpu.matching_cost(left, right, first, levels, 31),
                           args.repeat),
                 median_ms(lambda: census_cpu.path_sums(cost, P1, P2), args.repeat),
                 median_ms(lambda: census_cpu.select_disparities(total, UNIQUENESS, LR),
                           args.repeat)]
        print(f"| {width}x{height} | {levels} | " + " | ".join(f"{t:.1f}" for t in times)
              + f" | {sum(times):.1f} |")


if __name__ == "__main__":
    main()
