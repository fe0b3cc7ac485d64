"""Command line: ``pothole-detector detect | evaluate | play | process | record``."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from . import __version__
from .backend import BACKEND_CHOICES, get_backend
from .calibration import StereoCalibration, load_stereo_camera_info
from .errors import ConfigError, InputError, PotholeError
from .evaluation.scores import draw_progress, evaluate, evaluate_synthetic, synthetic_markdown
from .imageio import overlay, read_image, write_labels, write_rgb
from .params import Config, load_yaml
from .method import PipelineResult
from .pipeline import Pipeline
from .recordings.bagwriter import MCAP_COMPRESSIONS
from .recordings.camera import RECTIFY_CHOICES, pipeline_inputs
from .ros.bagtools import play, process, record
from .evaluation.rig_matrix import RIG_CLASS_NAMES
from .stages.rectify import Rectification


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pothole-detector",
        description="Stereo road pothole detection (GPT-SGM, disparity transformation, SLIC).")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)

    detect = commands.add_parser("detect", help="detect potholes in one stereo pair")
    detect.add_argument("--left", required=True, help="left image (rectified, or raw with "
                                                      "camera-info files that rectify it)")
    detect.add_argument("--right", required=True, help="right image")
    detect.add_argument("--camera-info-left", help="left ROS calibration YAML")
    detect.add_argument("--camera-info-right", help="right ROS calibration YAML")
    detect.add_argument("--cx", type=float, help="principal point x (px; default image centre)")
    detect.add_argument("--cy", type=float, help="principal point y (px; default image centre)")
    detect.add_argument("--out", required=True, help="output directory")
    _common(detect)
    _calibration_overrides(detect, "without camera-info files: the rectified pair's; with "
                                    "them: used where they lack it")

    evaluate_cmd = commands.add_parser(
        "evaluate", help="the paper's metrics over a directory of pairs with ground truth, or "
                         "over rendered scenes of a matrix of rigs (--synthetic)")
    evaluate_cmd.add_argument("directory", nargs="?",
                              help="fan_potholes, KITTI or Middlebury folder")
    evaluate_cmd.add_argument("--synthetic", action="store_true",
                              help="render scenes of each rig class and score them")
    evaluate_cmd.add_argument("--rig-class", action="append", choices=RIG_CLASS_NAMES,
                              help="with --synthetic: only this class (repeatable)")
    evaluate_cmd.add_argument("--scenes", type=int, default=3,
                              help="with --synthetic: scenes with potholes per class")
    evaluate_cmd.add_argument("--clean-scenes", type=int, default=1,
                              help="with --synthetic: pothole-free scenes per class")
    evaluate_cmd.add_argument("--seed", type=int, default=0,
                              help="with --synthetic: which draw of scenes")
    evaluate_cmd.add_argument("--cache", help="with --synthetic: keep renders in this folder")
    evaluate_cmd.add_argument("--jobs", type=int, default=1,
                              help="with --synthetic: render scenes in this many processes")
    evaluate_cmd.add_argument("--out", help="also write the report (Markdown) here")
    _common(evaluate_cmd)

    play = commands.add_parser("play", help="publish a recorded bag into the live ROS graph")
    play.add_argument("bag", help="ROS 2 bag directory (mcap or sqlite3) or ROS 1 .bag")
    play.add_argument("--rate", type=float, default=1.0, help="playback speed factor")
    play.add_argument("--loop", action="store_true", help="start again at the end")
    play.add_argument("--remap", action="append", default=[], metavar="OLD:=NEW",
                      help="publish topic OLD as NEW (repeatable)")
    play.add_argument("--qos", choices=("reliable", "best_effort"), default="reliable",
                      help="publisher reliability")
    play.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    play.add_argument("--wait-for-subscribers", type=float, default=0.0, metavar="S",
                      help="wait up to S seconds until every topic has a subscriber")

    process_cmd = commands.add_parser(
        "process", help="run the detector over every stereo pair of a bag into a new bag")
    process_cmd.add_argument("bag", help="ROS 2 bag directory (mcap or sqlite3) or ROS 1 .bag")
    process_cmd.add_argument("--out", required=True, help="output bag directory (new)")
    process_cmd.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    _compression(process_cmd, "zstd_fast")
    process_cmd.add_argument("--no-inputs", action="store_true",
                             help="write only the output topics")
    process_cmd.add_argument("--pictures", help="also write overlay PNGs into this folder")
    for name in ("left", "right", "left-info", "right-info"):
        process_cmd.add_argument(f"--{name}-topic",
                                 help=f"{name.replace('-info', ' camera_info')} topic "
                                      "(default: found in the bag)")
    _common(process_cmd)
    _calibration_overrides(process_cmd, "used where the camera_info lacks it")

    survey_cmd = commands.add_parser(
        "survey", help="survey recorded drives: one entry per physical pothole, with severity, "
                       "as survey.csv, survey.geojson (with GNSS) and report.html")
    survey_cmd.add_argument("bags", nargs="+", metavar="BAG", help="ROS 2 bags of drives")
    survey_cmd.add_argument("--out", required=True, help="output folder")
    survey_cmd.add_argument("--ray", nargs="?", const="", metavar="ADDRESS",
                            help="run chunks of the bags on Ray (a worker per GPU, else per "
                                 "core), on the cluster at ADDRESS or a local one")
    survey_cmd.add_argument("--jobs", type=int, default=1, metavar="N",
                            help="run chunks of the bags (chunk_frames frames each) in N "
                                 "worker processes here (default 1: in this process)")
    survey_cmd.add_argument("--read-processes", type=int, metavar="N",
                            help="read and decode the bags in N worker processes ahead of the "
                                 "pipeline (the read_processes parameter; 0: in threads; default: "
                                 "-1, processes for a GPU pipeline)")
    survey_cmd.add_argument("--odometry-topic", help="nav_msgs/Odometry topic (default: the "
                                                     "bag's only one; else /tf, GNSS or "
                                                     "visual odometry)")
    survey_cmd.add_argument("--gnss-topic", help="sensor_msgs/NavSatFix topic (default: the "
                                                 "bag's only one)")
    survey_cmd.add_argument("--base-frame", default="base_link",
                            help="the /tf child frame of the vehicle (default base_link)")
    for name in ("left", "right", "left-info", "right-info"):
        survey_cmd.add_argument(f"--{name}-topic",
                                help=f"{name.replace('-info', ' camera_info')} topic "
                                     "(default: found in the bag)")
    _common(survey_cmd)
    _calibration_overrides(survey_cmd, "used where the camera_info lacks it")

    record_cmd = commands.add_parser("record", help="record live topics into a bag")
    record_cmd.add_argument("out", help="output bag directory (new)")
    record_cmd.add_argument("--topics", nargs="+", required=True, help="topics to record")
    record_cmd.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    _compression(record_cmd, "zstd")
    record_cmd.add_argument("--duration", type=float, help="stop after this many seconds")
    record_cmd.add_argument("--qos", choices=("reliable", "best_effort"), default="reliable",
                            help="subscription reliability")
    return parser


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="parameter YAML (config/pothole_detector.yaml format)")
    parser.add_argument("--backend", choices=BACKEND_CHOICES,
                        help="override the config's backend (auto, cpu, gpu)")


def _compression(parser: argparse.ArgumentParser, default: str) -> None:
    parser.add_argument("--compression", choices=tuple(MCAP_COMPRESSIONS), default=default,
                        help="mcap chunk compression: zstd (level 3, the smallest bag), "
                             "zstd_fast (level 1), lz4 or none (the fastest to write); "
                             f"sqlite3 bags are uncompressed (default: {default})")


def _calibration_overrides(parser: argparse.ArgumentParser, use: str) -> None:
    parser.add_argument("--baseline", type=float, help=f"baseline (m; {use})")
    parser.add_argument("--focal", type=float, help=f"focal length (px; {use})")
    parser.add_argument("--rectify", choices=RECTIFY_CHOICES,
                        help="override the config's rectify: rectify the images from their "
                             "calibration (auto: where it says they are not rectified)")


def _config(path: str | None, backend: str | None = None,
            args: argparse.Namespace | None = None) -> Config:
    """The parameters of ``path`` (defaults without), with the command line's backend and,
    where ``args`` has them, its baseline, focal length and rectify."""
    config = Config(load_yaml(path) if path else {})
    config = config.replace(backend=backend) if backend else config
    if args is not None:
        changes = {name: value for name, value in (
            ("baseline_m", getattr(args, "baseline", None)),
            ("focal_px", getattr(args, "focal", None)),
            ("rectify", getattr(args, "rectify", None))) if value is not None}
        config = config.replace(**changes)
    return config


def _calibration(args: argparse.Namespace, config: Config, width: int, height: int
                 ) -> tuple[StereoCalibration, Rectification | None]:
    """The rectified pair's calibration of ``detect``'s arguments and, where the images need
    it (the rectify parameter), their rectification."""
    if args.camera_info_left or args.camera_info_right:
        given = [f"--{name}" for name in ("cx", "cy") if getattr(args, name) is not None]
        if given:
            verb = "conflicts" if len(given) == 1 else "conflict"
            raise InputError(f"{' and '.join(given)} {verb} with the camera-info files, "
                             "which hold the calibration: give one or the other")
        if not (args.camera_info_left and args.camera_info_right):
            raise InputError("give both --camera-info-left and --camera-info-right")
        camera, size = load_stereo_camera_info(args.camera_info_left, args.camera_info_right,
                                               config.baseline_m, config.focal_px)
        if size != (width, height):
            raise InputError(f"camera info is for {size[0]}x{size[1]} images but the images "
                             f"are {width}x{height}")
        for note in camera.notes():
            print(note)
        return pipeline_inputs(camera, config.rectify)
    if args.focal is None or args.baseline is None:
        raise InputError("give --camera-info-left/--camera-info-right or --focal and --baseline")
    return StereoCalibration.from_focal_baseline(args.focal, args.baseline, width, height,
                                                 args.cx, args.cy), None


def detection_json(result: PipelineResult) -> dict:
    """The potholes.json document of one result."""
    def clean(value: float) -> float | None:
        return None if not math.isfinite(value) else value

    return {
        "road": {key: (clean(v) if isinstance(v, float) else v)
                 for key, v in result.road.as_dict().items()},
        "backend": result.backend,
        "threshold_px": clean(result.threshold_px),
        "band_px": {"min_shift": result.band[0], "levels": result.band[1]},
        "observed_range_m": {"near": clean(result.observed_range_m[0]),
                             "far": clean(result.observed_range_m[1])},
        "timings_ms": {k: round(v, 3) for k, v in result.timings_ms.items()},
        "potholes": [{k: (clean(v) if isinstance(v, float) else v)
                      for k, v in p.as_dict().items()} for p in result.potholes],
    }


def run_detect(args: argparse.Namespace) -> int:
    left, right = read_image(args.left), read_image(args.right)
    config = _config(args.config, args.backend, args)
    calibration, rectification = _calibration(args, config, left.shape[1], left.shape[0])
    backend = get_backend(config.backend)
    pipeline = Pipeline(config, calibration, backend, rectification)
    result = pipeline.run(left, right)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    labels = result.host("labels")
    np.save(out / "disparity.npy", result.host("disparity").astype(np.float32))
    np.save(out / "disparity_transformed.npy",
            result.host("transformed").astype(np.float32))
    write_labels(out / "labels.png", labels)
    (out / "potholes.json").write_text(json.dumps(detection_json(result), indent=2) + "\n")
    write_rgb(out / "overlay.png", overlay(pipeline.view(left), labels, result.potholes,
                                           result.host("observed"), result.host("searched")))
    print(f"{len(result.potholes)} pothole(s); road roll {result.road.roll_deg:.2f} deg, "
          f"inliers {result.road.inlier_fraction:.0%}; {result.timings_ms['total']:.0f} ms on "
          f"{result.backend}; wrote {out}")
    for pothole in result.potholes:
        print(f"  #{pothole.label}: area {pothole.area_m2:.4f} m2, max depth "
              f"{pothole.max_depth_m * 100:.1f} cm, volume {pothole.volume_m3 * 1e3:.2f} L")
    return 0


def run_evaluate(args: argparse.Namespace) -> int:
    if args.synthetic == bool(args.directory):
        raise InputError("evaluate needs a DIRECTORY of pairs or --synthetic (not both)")
    config = _config(args.config, args.backend)
    if args.synthetic:
        if args.scenes < 0 or args.clean_scenes < 0 or args.scenes + args.clean_scenes == 0:
            raise InputError("--scenes and --clean-scenes must be >= 0, one of them > 0")
        text = synthetic_markdown(evaluate_synthetic(
            config, get_backend(config.backend), args.rig_class, args.scenes,
            args.clean_scenes, args.seed, args.cache, jobs=max(args.jobs, 1)))
    else:
        text = evaluate(args.directory, config, get_backend(config.backend)).markdown()
    print(text)
    if args.out:
        Path(args.out).write_text(text)
    return 0


def run_play(args: argparse.Namespace) -> int:
    count = play(args.bag, rate=args.rate, loop=args.loop, remaps=args.remap,
                 reliability=args.qos, wait_for_subscribers=args.wait_for_subscribers,
                 clock=not args.no_clock)
    print(f"published {count} messages from {args.bag}")
    return 0


def run_process(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    summary = process(
        args.bag, args.out, _config(args.config, args.backend, args), storage=args.storage,
        keep_inputs=not args.no_inputs, left=args.left_topic, right=args.right_topic,
        left_info=args.left_info_topic, right_info=args.right_info_topic,
        progress=lambda index, total: draw_progress(index, total, start, "process"),
        pictures=args.pictures, compression=args.compression)
    for line in summary.failures.lines():
        print(f"  {line}")
    if summary.counts.corrupt:
        print(f"  {summary.counts.corrupt} corrupt messages skipped; the last: "
              f"{summary.counts.last_problem}")
    print(f"{summary.text()}; wrote {args.out}")
    if summary.frames == 0:
        reason = summary.failures.rows()[0][1] if summary.failed else "the bag has no stereo set"
        print(f"pothole-detector: error: no frame of {args.bag} could be processed: {reason}",
              file=sys.stderr)
        return 1
    return 0


def run_survey(args: argparse.Namespace) -> int:
    from .survey.fleet import ray_chunks
    from .survey.gis import write_gis, write_maps
    from .survey.report import write_report
    from .survey.drive import best_view_picture, survey, write_csv, write_geojson, write_summary

    config = _config(args.config, args.backend, args)
    if args.read_processes is not None:
        config = config.replace(read_processes=args.read_processes)
    names = dict(odometry=args.odometry_topic, gnss=args.gnss_topic,
                 base_frame=args.base_frame, left=args.left_topic, right=args.right_topic,
                 left_info=args.left_info_topic, right_info=args.right_info_topic)
    for bag in args.bags:
        if not Path(bag).exists():
            raise InputError(f"{bag} does not exist")
    if args.jobs < 1:
        raise InputError(f"--jobs must be at least 1, got {args.jobs}")
    if args.jobs > 1 and args.ray is not None:
        raise InputError("--jobs and --ray both say where chunks run: give one of them")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    label = "survey (chunks)" if args.ray is not None or args.jobs > 1 else "survey"
    surveys = survey(args.bags, config, chunks=None if args.ray is None else ray_chunks(args.ray),
                     progress=lambda index, total: draw_progress(index, total, start, label),
                     jobs=args.jobs, **names)
    write_csv(surveys, out / "survey.csv")
    summary = write_summary(surveys, out / "summary.json")
    geojson = write_geojson(surveys, out / "survey.geojson")
    try:
        gis_files = write_gis(surveys, out)
    except ConfigError as exc:
        gis_files = []
        print(f"survey.gpkg and survey.kml not written: {exc}", file=sys.stderr)
    try:
        gis_files += write_maps(surveys, out)
    except ConfigError as exc:
        print(f"the road map's GeoTIFF not written: {exc}", file=sys.stderr)
    write_report(surveys, out / "report.html", lambda drive, pothole: best_view_picture(
        drive.bag, drive.topics, pothole.row["best_stamp_ns"], pothole.bbox_px, config),
        (config.report_tiles_url, config.report_tiles_attribution))
    potholes = [p for drive in surveys for p in drive.potholes]
    by_class = ", ".join(f"{sum(p.row['severity'] == s for p in potholes)} {s}"
                         for s in ("low", "moderate", "high"))
    frames = sum(d.frames for d in surveys)
    elapsed = time.perf_counter() - start
    for drive in surveys:
        if drive.error:
            print(f"{drive.bag.name}: not surveyed: {drive.error}")
            continue
        print(f"{drive.bag.name}: {drive.frames} frames ({drive.failed} failed), "
              f"{len(drive.potholes)} potholes, {drive.observed_length_m:.1f} m of road "
              f"observed, motion from {drive.motion_source}"
              + (f"; {drive.left_out} tracked left out (seen in fewer than min_sightings "
                 f"({config.min_sightings}) frames, or no depression in the road map)"
                 if drive.left_out else ""))
        for line in drive.failure_tally().lines():
            print(f"  {line}")
    print(f"{len(potholes)} potholes ({by_class}) in {frames} frames, "
          f"{frames / max(elapsed, 1e-9):.1f} frames/s; wrote {out / 'survey.csv'}, "
          f"{out / 'summary.json'}"
          + (f", {out / 'survey.geojson'}" if geojson else "")
          + "".join(f", {path}" for path in gis_files) + f", {out / 'report.html'}")
    if summary["processed"] == 0:
        reasons = [line for drive in surveys for line in
                   ([drive.error] if drive.error else
                    [row[1] for row in drive.failure_tally().rows()[:1]])]
        print(f"pothole-detector: error: no frame could be processed: "
              f"{reasons[0] if reasons else 'the bags hold no stereo set'}", file=sys.stderr)
        return 1
    return 0


def run_record(args: argparse.Namespace) -> int:
    counts = record(args.out, args.topics, storage=args.storage, duration=args.duration,
                    reliability=args.qos, compression=args.compression)
    summary = ", ".join(f"{topic}: {count}" for topic, count in counts.items())
    print(f"{summary}; wrote {args.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``pothole-detector`` console script."""
    # notices (which backend runs) go to stdout, so that an error is stderr's one line
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    args = _parser().parse_args(argv)
    try:
        commands = {"detect": run_detect, "evaluate": run_evaluate, "play": run_play,
                    "process": run_process, "record": run_record, "survey": run_survey}
        return commands[args.command](args)
    except PotholeError as error:
        print(f"pothole-detector: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"pothole-detector: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
