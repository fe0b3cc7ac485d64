"""Probe of row sweeps for the GPU path costs (docs/gpu-notes.md, thirteenth and fourteenth
sessions).

Times benchmarks/probe_row_sweeps.cu beside the matcher's two path passes on a real frame in
one process: both senses' three-direction sweeps (block edges stale, handed over through
global memory as tagged words, or through cluster shared memory), the two horizontal walks
into volumes of their own, and all eight directions in one launch. Checks the sweeps and the
horizontal walks against the NumPy reference's path costs on crops of the frame. Needs a GPU
and a frame folder with left.png and right.png whose GPT band has 96 levels (model1_01 of the
pothole data). Usage:
python3 benchmarks/probe_row_sweeps.py [--data .devdata/fan_potholes/model1_01]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pothole_detector.backend import StageClock, get_backend
from pothole_detector.calibration import StereoCalibration
from pothole_detector.imageio import read_image
from pothole_detector.params import Config
from pothole_detector.pipeline import Pipeline
from pothole_detector.stages import census_sgm
from pothole_detector.stages.matching import to_gray8
from pothole_detector.stages.perspective import SHIFT_FIRST

# sgm.cu inlined where the probe includes it, so that CuPy's compile cache sees its text
SOURCE = Path(__file__).with_name("probe_row_sweeps.cu").read_text().replace(
    '#include "sgm.cu"',
    (Path(census_sgm.__file__).resolve().parents[1] / "kernels" / "sgm.cu").read_text())
LEVELS = 96
# (columns a block, census rows ahead, exchange through global memory (2: tagged words; 0:
# none), cluster size)
VARIANTS = ((8, 4, 0, 0), (8, 4, 2, 0), (16, 4, 2, 0), (8, 2, 2, 0), (8, 6, 2, 0),
            (8, 4, 0, 8))
# what a launch walks: (first kind, end), kinds 0 / 1 horizontal, 2 / 3 sweeps
LAUNCHES = {"sweeps": (2, 4), "horizontals": (0, 2), "all eight": (0, 4)}


def sweep_kernel(cp, columns: int, ahead: int, exchange: int, cluster: int):
    """The probe kernel, built on kernels/sgm.cu (its helpers for 16 lanes at LEVELS)."""
    defines = {"LEVELS": LEVELS, "LANES": 16, "CENSUS_RY": census_sgm.CENSUS_RADIUS_Y,
               "CENSUS_RX": census_sgm.CENSUS_RADIUS_X,
               "INVALID_COST": census_sgm.INVALID_COST, "BORDER_Y": census_sgm.BORDER_Y,
               "BORDER_X": census_sgm.BORDER_X, "COLS": columns, "ROWS_AHEAD": ahead,
               "EXCHANGE": exchange, "CLUSTER": cluster}
    options = ("-std=c++17",) + tuple(f"-D{name}={value}" for name, value in defines.items())
    return cp.RawModule(code=SOURCE, options=options).get_function("sweep_probe")


class Sweeps:
    """Launches of one probe kernel with its exchange buffers (kept, so that timing sees only
    the kernel; EXCHANGE 2 tells launches apart by an epoch in its tags)."""

    def __init__(self, cp, kernel, height: int, width: int, columns: int, cluster: int):
        self.kernel, self.columns = kernel, columns
        blocks = -(-width // columns)
        if cluster:
            blocks = -(-blocks // cluster) * cluster
        self.blocks = blocks
        self.edges = cp.zeros(2 * blocks * 2 * 4 * LEVELS, dtype=cp.uint64)
        self.failed_flag = cp.zeros(1, dtype=cp.uint32)
        self.epoch = 0

    def __call__(self, census_left, census_right, kappa, out, kinds: tuple[int, int],
                 p1: int, p2: int, horizontal_out=None) -> None:
        """Kinds ``kinds[0]`` to ``kinds[1] - 1`` (0 / 1: horizontal walks into
        ``horizontal_out`` (uint8 2xHxWxLEVELS), 2 / 3: sweeps into ``out``)."""
        height, width = census_left.shape
        blocks = self.blocks if kinds[1] > 2 else -(-height // self.columns)
        if kinds[0] < 2:
            blocks = max(blocks, -(-height // self.columns))
        horizontal = out if horizontal_out is None else horizontal_out
        self.epoch += 1
        self.kernel((blocks, kinds[1] - kinds[0]), (self.columns * 16,),
                    (census_left, census_right, kappa, out[0], out[1], np.int32(height),
                     np.int32(width), np.int32(p1), np.int32(p2), self.edges, self.failed_flag,
                     horizontal[0], horizontal[1], np.uint32(self.epoch),
                     np.int32(kinds[0])))

    def failed(self) -> bool:
        """Whether a wait for a neighbour's edge gave up (EXCHANGE 2)."""
        return bool(int(self.failed_flag.get()[0]))


def median_ms(cp, launch, repeats: int = 30) -> float:
    start, stop = cp.cuda.Event(), cp.cuda.Event()
    times = []
    for _ in range(repeats):
        start.record()
        launch()
        stop.record()
        stop.synchronize()
        times.append(cp.cuda.get_elapsed_time(start, stop))
    return float(np.median(times[5:]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path(".devdata/fan_potholes/model1_01"))
    args = parser.parse_args()
    backend = get_backend("gpu")
    cp = backend.xp
    config = Config({"cuda_graph": False, "gpt_shift": "row"})
    p1, p2 = config.census_p1, config.census_p2
    left = to_gray8(read_image(args.data / "left.png"))
    right = to_gray8(read_image(args.data / "right.png"))
    height, width = left.shape
    pipeline = Pipeline(config, StereoCalibration.from_focal_baseline(1390, 0.1194, width,
                                                                     height), backend)
    pipeline.run(left, right)
    pipeline.run(left, right)
    shifts, levels = pipeline._band(left.shape)
    if levels != LEVELS:
        raise SystemExit(f"the frame's band has {levels} levels; the probe is built for 96")
    matcher = census_sgm.GpuMatcher(backend)
    device_left, device_right = backend.upload(left), backend.upload(right)
    device_shifts = backend.upload(shifts)
    device_kappa = device_shifts[SHIFT_FIRST]  # row shifts: each row's shift
    matcher(device_left, device_right, device_shifts, levels, p1, p2, 5, 1, True)
    # the winner search writes over the matcher's right census words: the host's own
    census = [cp.asarray(census_sgm.census_transform(image)) for image in (left, right)]
    out = cp.empty((2, height, width, LEVELS), dtype=cp.uint8)
    stage_ms = matcher_ms(matcher, backend, device_left, device_right, device_shifts, levels,
                          p1, p2)
    print(f"matcher paths (both passes, 8 directions): {stage_ms:.3f} ms")
    horizontal = cp.empty_like(out)
    for columns, ahead, exchange, cluster in VARIANTS:
        kernel = sweep_kernel(cp, columns, ahead, exchange, cluster)
        sweeps = Sweeps(cp, kernel, height, width, columns, cluster)
        for name, kinds in LAUNCHES.items():
            if cluster and kinds[0] < 2:
                continue
            try:
                ms = median_ms(cp, lambda: sweeps(census[0], census[1], device_kappa, out,
                                                  kinds, p1, p2, horizontal))
            except cp.cuda.driver.CUDADriverError as error:
                print(f"columns {columns} cluster {cluster}: {error}")
                break
            print(f"columns {columns}, {ahead} ahead, exchange {exchange}, cluster {cluster}: "
                  f"{name} {ms:.3f} ms{' (a wait gave up)' if sweeps.failed() else ''}")
    check_crops(cp, left, right, shifts, p1, p2)


def matcher_ms(matcher, backend, device_left, device_right, device_shifts, levels, p1,
               p2) -> float:
    """The matcher's two path passes (its ``paths`` stage), median ms."""
    samples = []
    for _ in range(30):
        clock = StageClock(backend)
        matcher(device_left, device_right, device_shifts, levels, p1, p2, 5, 1, True,
                clock=clock)
        samples.append(clock.timings()["paths"])
    return float(np.median(samples[5:]))


def check_crops(cp, left, right, shifts, p1: int, p2: int) -> None:
    """Exchanged sweeps and the horizontal walks against the NumPy reference's path costs on
    bottom-left crops (one of them a partial last block); ``shifts``: row shifts."""
    rows = 60
    crop_shifts = np.ascontiguousarray(shifts[:, -rows:])
    crop_kappa = crop_shifts[SHIFT_FIRST]
    for columns, exchange, cluster, crop_width in ((8, 2, 0, 200), (8, 2, 0, 203),
                                                   (16, 2, 0, 203), (8, 0, 8, 64)):
        crop_left = np.ascontiguousarray(left[-rows:, :crop_width])
        crop_right = np.ascontiguousarray(right[-rows:, :crop_width])
        census_left = census_sgm.census_transform(crop_left)
        census_right = census_sgm.census_transform(crop_right)
        cost = census_sgm.matching_cost(census_left, census_right, crop_shifts, LEVELS)
        paths = census_sgm.aggregate(cost, p1, p2).astype(np.int32)
        expected = (paths[2] + paths[4] + paths[5], paths[3] + paths[6] + paths[7],
                    paths[0], paths[1])
        out = cp.zeros((2, rows, crop_width, LEVELS), dtype=cp.uint8)
        horizontal = cp.zeros_like(out)
        kernel = sweep_kernel(cp, columns, 4, exchange, cluster)
        sweeps = Sweeps(cp, kernel, rows, crop_width, columns, cluster)
        sweeps(cp.asarray(census_left), cp.asarray(census_right), cp.asarray(crop_kappa), out,
               (0, 4) if not cluster else (2, 4), p1, p2, horizontal)
        got = np.concatenate([cp.asnumpy(out), cp.asnumpy(horizontal)])
        equal = [bool(np.array_equal(got[k], expected[k])) for k in range(4 if not cluster
                                                                            else 2)]
        print(f"{rows}x{crop_width}, columns {columns}, exchange {exchange}, cluster "
              f"{cluster}: down, up, left to right, right to left equal to the reference: "
              f"{equal}{' (a wait gave up)' if sweeps.failed() else ''}")


if __name__ == "__main__":
    main()
