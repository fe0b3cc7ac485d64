"""CPU speed of the whole pipeline, per stage, at 1280x720 (synthetic road) and on the real
2079x1040 pothole frames (when ../shared/data is present). Prints a Markdown table.

    python benchmarks/bench_cpu.py [--repeat N] [--threads T] [--matcher census|opencv]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from datetime import date
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pothole_detector.backend import CPU  # noqa: E402
from pothole_detector.calibration import StereoCalibration  # noqa: E402
from pothole_detector.imageio import read_image  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402
from pothole_detector.stages.matching import Matcher, set_host_threads, to_gray8  # noqa: E402
from pothole_detector.stages.perspective import no_shifts  # noqa: E402
from pothole_detector.stages.transform import road_grid  # noqa: E402
from pothole_detector.evaluation.synthetic import demo_scene, render  # noqa: E402

STAGES = ("seed", "gpt", "sgm", "road", "dt", "slic", "threshold", "components", "refine",
          "measure", "total")


def frames() -> list[tuple[str, np.ndarray, np.ndarray, StereoCalibration]]:
    sample = render(demo_scene(1280, 720))
    found = [("synthetic 1280x720", sample.left, sample.right, sample.calibration)]
    real = ROOT.parent / "shared" / "data" / "fan_potholes"
    for folder in sorted(real.glob("model1_0[1-3]")):
        left, right = read_image(folder / "left.png"), read_image(folder / "right.png")
        calibration = StereoCalibration.from_focal_baseline(1390, 0.1194, left.shape[1],
                                                            left.shape[0])
        found.append((f"real {folder.name} 2079x1040", left, right, calibration))
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--matcher", choices=("census", "opencv"), default=Config().matcher)
    args = parser.parse_args()
    set_host_threads(args.threads)
    config = Config({"matcher": args.matcher})
    print(f"CPU benchmark, {date.today()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, matcher {args.matcher}, OpenCV {cv2.__version__} and Numba "
          f"on {args.threads} threads, NumPy {np.__version__}; median ms over {args.repeat} "
          "runs after one warm-up (a fresh pipeline each run, so 'seed' runs every time); "
          "in a drive: the total of one pipeline run again on the pair, its road carried "
          "over as from the frame before (no seed)\n")
    print("| frame | " + " | ".join(STAGES) + " | in a drive | matcher alone, full range |")
    print("| --- |" + " --- |" * (len(STAGES) + 2))
    for name, left, right, calibration in frames():
        runs = []
        for index in range(args.repeat + 1):
            road_grid.cache_clear()  # every frame of a drive has a road of its own
            result = Pipeline(config, calibration).run(left, right)
            if index:
                runs.append(result.timings_ms)
        drive = Pipeline(config, calibration)
        drive.run(left, right)
        in_drive = []
        for _ in range(args.repeat):
            road_grid.cache_clear()
            in_drive.append(drive.run(left, right).timings_ms["total"])
        gray_left, gray_right = to_gray8(left), to_gray8(right)
        levels = 256 if left.shape[1] > 1500 else 128
        plain, matcher = [], Matcher(CPU)
        for _ in range(3):
            start = time.perf_counter()
            matcher(gray_left, gray_right, no_shifts(left.shape[0]), levels, config)
            plain.append((time.perf_counter() - start) * 1e3)
        medians = [np.median([r[s] for r in runs]) for s in STAGES]
        print(f"| {name} | " + " | ".join(f"{m:.0f}" for m in medians)
              + f" | {np.median(in_drive):.0f} | {np.median(plain):.0f} ({levels} levels) |")


if __name__ == "__main__":
    main()
