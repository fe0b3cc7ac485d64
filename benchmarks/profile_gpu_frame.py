"""Where one GPU frame's time goes, kernel by kernel: runs a frame (the real 2079x1040 pair or
the synthetic 1280x720 road) a few times, then one more between cudaProfilerStart and Stop, so
that Nsight Compute times only that frame's kernels; then sums its CSV by kernel name.

    ncu --clock-control none --profile-from-start off --metrics gpu__time_duration.sum \\
        --csv --print-units base python3 benchmarks/profile_gpu_frame.py --frame real \\
        --data FRAMES > frame.csv
    python3 benchmarks/profile_gpu_frame.py --summarize frame.csv
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import Counter, defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_gpu import frames  # noqa: E402
from pothole_detector.backend import get_backend  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402

WARM_UP_FRAMES = 6


def profile(frame: str, data: Path, graph: bool) -> None:
    """One frame of ``frame`` ("real" or "synthetic") under the profiler's range, after
    WARM_UP_FRAMES frames that compile the kernels and capture the graphs."""
    import cupy  # the benchmark's own profiler range; the package imports CuPy in backend.py
    for name, left, right, calibration in frames(data if data.is_dir() else None, 1):
        if name.startswith(frame):
            break
    else:
        raise SystemExit(f"no {frame} frame (real frames need --data)")
    pipeline = Pipeline(Config({"cuda_graph": graph}), calibration, get_backend("gpu"))
    for _ in range(WARM_UP_FRAMES):
        pipeline.run(left, right)
    cupy.cuda.runtime.deviceSynchronize()
    cupy.cuda.profiler.start()
    result = pipeline.run(left, right)
    cupy.cuda.runtime.deviceSynchronize()
    cupy.cuda.profiler.stop()
    print(f"{name}: total GPU {result.timings_ms['total']:.3f} ms (under the profiler)",
          file=sys.stderr)


def summarize(path: Path, top: int) -> str:
    """A Markdown table of the ``top`` kernels by summed duration in ncu's CSV at ``path``,
    with the frame's kernel count and total."""
    rows = [row for row in csv.reader(path.open()) if len(row) > 10]
    header, rows = rows[0], rows[1:]
    name_at, value_at = header.index("Kernel Name"), header.index("Metric Value")
    total_ns: defaultdict[str, float] = defaultdict(float)
    launches: Counter[str] = Counter()
    for row in rows:
        name = row[name_at].split("(")[0].split("<")[0].strip()
        total_ns[name] += float(row[value_at].replace(",", ""))
        launches[name] += 1
    frame_us = sum(total_ns.values()) / 1e3
    lines = [f"{len(rows)} kernels, {frame_us:.0f} us in all", "",
             "| kernel | launches | us | share |", "| --- | --- | --- | --- |"]
    for name, value in sorted(total_ns.items(), key=lambda item: -item[1])[:top]:
        lines.append(f"| {name} | {launches[name]} | {value / 1e3:.1f} | "
                     f"{value / 1e3 / frame_us:.1%} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frame", choices=("real", "synthetic"), default="real")
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data"
                        / "fan_potholes")
    parser.add_argument("--no-graph", action="store_true", help="stages launched one by one")
    parser.add_argument("--summarize", type=Path, help="ncu CSV to sum by kernel")
    parser.add_argument("--top", type=int, default=20)
    args = parser.parse_args()
    if args.summarize:
        print(summarize(args.summarize, args.top))
    else:
        profile(args.frame, args.data, not args.no_graph)


if __name__ == "__main__":
    main()
