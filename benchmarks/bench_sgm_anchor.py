"""Our census SGM beside the speed anchor, fixstars libSGM, in one run on the GPU machine.

libSGM is built from ANCHORS (``../shared/anchors``: its sources, its timing harness
``libsgm_bench.cu`` and ``run_libsgm.sh``, which need CMake and nvcc) and timed on the same
rectified 8-bit pairs as our matcher; machines differ by up to a fifth, so only ratios from one
run count. Prints a Markdown table for docs/benchmarks.md.

    python3 benchmarks/bench_sgm_anchor.py [--data DIR] [--anchors DIR] [--frames 100]

Pairs: the first real frame of ``--data`` (fan_potholes layout, 2079x1040) and our synthetic
road at 1280x720. Ours: the census matcher on the frame's GPT band (per-pixel shifts, as the
pipeline runs it: census with the GPT's gather, the path sweeps, the winner and left-right
check, the finish with the median), CUDA events per kernel, median over ``--frames`` calls.
libSGM: 8 paths, census 9x7, subpixel, left-right check, the same level count from 0, images
and result on the device, CUDA events, median of 100 after 10 warm-ups.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from datetime import date
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_gpu import frames, sgm_kernel_times  # noqa: E402

LIBSGM_LINE = re.compile(r"libSGM (\d+)x(\d+) disp (\d+): median ([\d.]+) ms.*valid ([\d.]+) %")


def libsgm_ms(anchors: Path, left, right, levels: int) -> tuple[float, float]:
    """libSGM's median ms and valid share (%) on one pair at ``levels`` disparities, built and
    run by the anchors' run_libsgm.sh."""
    with tempfile.TemporaryDirectory() as folder:
        paths = [str(Path(folder) / name) for name in ("left.png", "right.png")]
        for path, image in zip(paths, (left, right)):
            cv2.imwrite(path, image)
        printed = subprocess.run(["bash", str(anchors / "run_libsgm.sh"), *paths, str(levels)],
                                 check=True, capture_output=True, text=True).stdout
    found = LIBSGM_LINE.search(printed)
    if found is None:
        raise RuntimeError(f"run_libsgm.sh printed no timing: {printed!r}")
    return float(found.group(4)), float(found.group(5))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data"
                        / "fan_potholes")
    parser.add_argument("--anchors", type=Path, default=ROOT.parent / "shared" / "anchors")
    parser.add_argument("--frames", type=int, default=100)
    args = parser.parse_args()
    import cupy  # the benchmark's own device query; the package imports CuPy in backend.py
    device = cupy.cuda.runtime.getDeviceProperties(0)["name"].decode()
    print(f"SGM against libSGM, {date.today()}, {device}; ours: kernels' CUDA events, median "
          f"of {args.frames} calls; libSGM: run_libsgm.sh, median of 100.\n")
    print("| pair | levels | libSGM ms (valid %) | ours ms | of which paths | libSGM / ours |")
    print("| --- | --- | --- | --- | --- | --- |")
    data = args.data if args.data.is_dir() else None
    for name, left, right, calibration in frames(data, 1):
        if "1920" in name:
            continue
        levels, _, parts = sgm_kernel_times(left, right, calibration, args.frames, "pixel")
        ours = sum(parts.values())
        anchor, valid = libsgm_ms(args.anchors, left, right, levels)
        print(f"| {name} | {levels} | {anchor:.3f} ({valid:.0f} %) | {ours:.3f} | "
              f"{parts.get('paths', float('nan')):.3f} | {anchor / ours:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
