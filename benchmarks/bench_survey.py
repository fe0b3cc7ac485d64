"""Survey throughput: frames per second end to end (bag decoding, pipeline, visual odometry,
tracking, survey.csv and report.html) on a drive bag of our generator, per image size. Prints
a Markdown table for docs/benchmarks.md.

    python benchmarks/bench_survey.py [--sizes 1280x720 2079x1040] [--frames 60]
        [--backend cpu|gpu] [--jobs N [N ...]] [--ray] [--ray-gpus N [N ...]]
        [--chunk-frames 30] [--bags N]
        [--read-threads N [N ...]] [--read-processes N [N ...]] [--form rectified|raw-jpeg]
        [--map-cell-m M [M ...]]

The bag cycles a few rendered frames of the survey drive with fresh stamps (rendering every
frame at these sizes would take longer than the survey), with an odometry topic that follows
the cycle, as survey vehicles record it: the survey takes its motion from it (no visual
odometry) and tracks the same six potholes throughout. ``--form raw-jpeg`` records the drive as
a camera driver often does: raw images of a distorted, slightly rotated camera (plumb_bob, with
its camera_info), JPEG-compressed (image_transport's compressed topics), so the survey
decodes and rectifies every frame.

``--ray`` adds, after the ``--jobs`` rows, a row per ``--ray-gpus`` count (default: every
GPU the machine has): the chunks as tasks on a local Ray cluster that offers that many GPUs,
one task a GPU at a time (survey/fleet.py). The cluster starts before the clock does, as a
fleet's is up before a survey; its worker processes start, load the compiled kernels and fit
a road per chunk within the time measured."""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pothole_detector.recordings.writing import RecordingForm, write_drive_bag  # noqa: E402
from pothole_detector.survey.fleet import ray_chunks  # noqa: E402
from pothole_detector.params import PARAMETER_BY_NAME, Config  # noqa: E402
from pothole_detector.survey.report import write_report  # noqa: E402
from pothole_detector.survey.drive import (best_view_picture, chunk_runner,  # noqa: E402
                                           survey, write_csv)
from pothole_detector.evaluation.synthetic import (raw_camera, render, render_raw,  # noqa: E402
                                                   survey_drive)

try:
    import ray
except ImportError:
    ray = None

DISTINCT_FRAMES = 4


def make_bag(bag: Path, samples: list, forward_m: list[float], frames: int,
             form: RecordingForm) -> Path:
    """``frames`` frames at 30 Hz cycling ``samples`` (taken ``forward_m`` along the road)."""
    cycle = [i % len(samples) for i in range(frames)]
    write_drive_bag(bag, [forward_m[i] for i in cycle], [samples[i] for i in cycle], "odom",
                    rate_hz=30.0, ground_truth=False, form=form)
    return bag


def linked_bag(bag: Path, twin: Path) -> Path:
    """A second bag at ``twin`` whose files are hard links to those of ``bag``."""
    twin.mkdir()
    for path in bag.iterdir():
        os.link(path, twin / path.name)
    return twin


def raw_sample(scene: object, camera: object) -> object:
    """The scene's render with the raw camera's images in place of the rectified ones."""
    left, right = render_raw(scene, camera)
    return replace(render(scene), left=left, right=right)


def bench(bags: list[Path], config: Config, ray_gpus: int | None, jobs: int, out: Path
          ) -> tuple[float, float, int, int]:
    """Survey ``bags`` together into ``out``: in ``jobs`` processes, or, where ``ray_gpus`` is not
    None, as tasks on a local Ray cluster of that many GPUs (-1: the machine's), started
    before the clock. Returns (seconds, of which observing the chunks: until the last chunk's
    result, frames, potholes of all the bags); the rest is this process's: planning,
    assembling (poses, tracking, the road maps, the rows), survey.csv and report.html."""
    runner = ray_chunks() if ray_gpus is not None else chunk_runner(jobs)
    observing: list[float] = []

    def timed(plans: Any, values: Config, progress: Any) -> Any:
        start = time.perf_counter()
        yield from runner(plans, values, progress)
        observing.append(time.perf_counter() - start)

    if ray_gpus is not None:
        ray.init(num_gpus=None if ray_gpus < 0 else ray_gpus, include_dashboard=False,
                 log_to_driver=False, configure_logging=False)
    try:
        start = time.perf_counter()
        surveys = survey(bags, config, chunks=timed)
        write_csv(surveys, out / "survey.csv")
        write_report(surveys, out / "report.html", lambda d, p: best_view_picture(
            d.bag, d.topics, p.row["best_stamp_ns"], p.bbox_px, config))
        return (time.perf_counter() - start, sum(observing),
                sum(one.frames for one in surveys), sum(len(one.potholes) for one in surveys))
    finally:
        if ray_gpus is not None:
            ray.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["1280x720", "2079x1040"])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--backend", default="cpu", choices=("cpu", "gpu", "auto"))
    parser.add_argument("--ray", action="store_true",
                        help="also rows of chunks as tasks on a local Ray cluster")
    parser.add_argument("--ray-gpus", type=int, nargs="+", default=[-1],
                        help="GPUs the local Ray cluster offers (a row each; -1: all)")
    parser.add_argument("--jobs", type=int, nargs="+", default=[1],
                        help="chunks in this many worker processes here (several: a row each)")
    parser.add_argument("--chunk-frames", type=int, default=600)
    parser.add_argument("--bags", type=int, default=1,
                        help="the drive as this many bags (links to one bag's files: as many "
                             "recordings of the road), surveyed together")
    parser.add_argument("--read-threads", type=int, nargs="+", default=[4],
                        help="threads per process that read the bag ahead (several: a row "
                             "each)")
    parser.add_argument("--form", choices=("rectified", "raw-jpeg"), default="rectified",
                        help="how the drive is recorded (raw-jpeg: raw distorted images, "
                             "JPEG-compressed)")
    parser.add_argument("--read-processes", type=int, nargs="+",
                        default=[PARAMETER_BY_NAME["read_processes"].default],
                        help="worker processes that read and decode the bag ahead instead of "
                             "the threads (0: the threads; -1: the parameter's default, by "
                             "the backend; several: a row each)")
    parser.add_argument("--map-cell-m", type=float, nargs="+",
                        default=[PARAMETER_BY_NAME["map_cell_m"].default],
                        help="the road map's cell (0: no map; several: a row each)")
    args = parser.parse_args()
    if args.ray and ray is None:
        parser.error("--ray needs Ray: pip install '.[fleet]'")
    config = Config({"backend": args.backend, "chunk_frames": args.chunk_frames})
    if args.backend == "cpu":
        device = f"CPU backend ({platform.machine()}, {os.cpu_count()} cores)"
    else:
        from pothole_detector.backend import get_backend
        device = f"{get_backend(args.backend).name} backend, host {os.cpu_count()} cores"
    print(f"survey throughput, {device}, {args.bags} bag(s) of {args.frames} frames "
          f"({args.form}), {datetime.date.today().isoformat()}")
    print("| size | processes | reading ahead (each) | road map cell | frames | potholes | "
          "seconds | of which observing | frames/s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |", flush=True)
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        for size in args.sizes:
            width, height = (int(v) for v in size.lower().split("x"))
            scenes = [replace(s, supersample=1) for s in survey_drive(
                frames=DISTINCT_FRAMES * 4, width=width, height=height)[::4]]
            form = RecordingForm()
            with ProcessPoolExecutor(len(scenes), mp_context=get_context("spawn")) as pool:
                if args.form == "raw-jpeg":
                    camera = raw_camera(scenes[0].calibration, width, height, "plumb_bob")
                    form = RecordingForm(compression="jpeg", camera=camera)
                    samples = list(pool.map(raw_sample, scenes, [camera] * len(scenes)))
                else:
                    samples = list(pool.map(render, scenes))
            forward = [s.camera_y_m for s in scenes]
            bags = [make_bag(folder / f"drive_{size}", samples, forward, args.frames, form)]
            bags += [linked_bag(bags[0], folder / f"drive_{size}_{k}")
                     for k in range(1, args.bags)]
            warm = folder / f"warm_{size}"
            warm.mkdir()
            bench([make_bag(warm / "drive", samples, forward, 3, form)], config, None, 1,
                  warm)  # compiles kernels
            runs = [(jobs, threads, readers, cell)
                    for jobs in args.jobs + ([-1] if args.ray else [])
                    for threads, readers in [(t, 0) for t in args.read_threads
                                             if 0 in args.read_processes]
                    + [(args.read_threads[0] if p < 0 else 1, p)
                       for p in args.read_processes if p != 0]
                    for cell in args.map_cell_m]
            runs = [(jobs, gpus, threads, readers, cell)
                    for jobs, threads, readers, cell in runs
                    for gpus in (args.ray_gpus if jobs < 0 else [None])]
            for jobs, gpus, threads, readers, cell in runs:
                out = folder / f"out_{size}_{jobs}_{gpus}_{threads}_{readers}_{cell}"
                out.mkdir()
                seconds, observing, frames, potholes = bench(
                    bags, config.replace(read_threads=threads, read_processes=readers,
                                        map_cell_m=cell), gpus, max(jobs, 1), out)
                on = ("all GPUs" if gpus is not None and gpus < 0 else
                      "CPU cores" if gpus == 0 else f"{gpus} GPU{'s' if gpus != 1 else ''}")
                mode = f"Ray on {on}, chunks of {args.chunk_frames}" if jobs < 0 else (
                    f"{jobs} (chunks of {args.chunk_frames})" if jobs > 1 else "1")
                reading = (f"{readers} processes" if readers > 0 else
                           f"{threads} thread{'s' if threads > 1 else ''}")
                if readers < 0:
                    reading = f"default ({reading} on the CPU, processes on a GPU)"
                print(f"| {size} | {mode} | {reading} | "
                      f"{f'{cell * 100:g} cm' if cell else 'none'} | {frames} | "
                      f"{potholes} | {seconds:.1f} | {observing:.1f} | {frames / seconds:.1f} |",
                      flush=True)


if __name__ == "__main__":
    main()
