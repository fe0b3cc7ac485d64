"""How fast a bag is written (recordings/bagwriter.py), the part of `process` and `record` that
compresses and writes: the messages `process` writes for one frame of a rendered road (the
stereo pair as it came, and every offline output topic of the pipeline's result) are written
``--frames`` times into a new mcap bag with each compression, by zstd's own threads or by the
writer's thread alone. Prints a Markdown table for docs/benchmarks.md.

    python benchmarks/bench_bagwriter.py [--size 1280x720] [--frames 60] [--workers 0 8]
        [--compression zstd zstd_fast lz4 none] [--rounds 2]

"ms a frame": from the first write to the bag closed, per frame; "MB/s": raw message bytes a
second through the writer.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pothole_detector.params import Config  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402
from pothole_detector.recordings.bagwriter import (MCAP_COMPRESSIONS, BagWriter,  # noqa: E402
                                                   compression_workers)
from pothole_detector.recordings.images import array_to_image  # noqa: E402
from pothole_detector.recordings.messages import header_at, serialize, typestore  # noqa: E402
from pothole_detector.ros.outputs import OFFLINE_OUTPUTS, OUTPUT_TYPES, output_messages  # noqa: E402
from pothole_detector.evaluation.synthetic import demo_scene, render  # noqa: E402

IMAGE = "sensor_msgs/msg/Image"


def frame_messages(width: int, height: int) -> dict[str, tuple[str, bytes]]:
    """Topic name -> (message type, CDR bytes) of one frame as `process` writes it."""
    sample = render(demo_scene(width, height))
    result = Pipeline(Config({"backend": "cpu"}), sample.calibration).run(sample.left,
                                                                          sample.right)
    header = header_at(1, "left")
    made = output_messages(result, sample.left, sample.calibration, header, OFFLINE_OUTPUTS)
    messages = {name: (OUTPUT_TYPES[name], serialize(message, OUTPUT_TYPES[name]))
                for name, message in made.messages.items()}
    encoding = "rgb8" if sample.left.ndim == 3 else "mono8"
    for side, image in (("left", sample.left), ("right", sample.right)):
        messages[side] = (IMAGE, serialize(array_to_image(image, encoding, header), IMAGE))
    return messages


def write_ms(messages: dict[str, tuple[str, bytes]], frames: int, compression: str,
             workers: int, folder: Path) -> tuple[float, float]:
    """ms a frame through a BagWriter, and the bag's bytes over the raw messages'."""
    out = folder / f"bag_{compression}_{workers}_{time.monotonic_ns()}"
    writer = BagWriter(out, "mcap", compression, workers=workers)
    store = typestore()
    connections = {name: writer.add_connection(f"/drive/{name}", msgtype, typestore=store)
                   for name, (msgtype, _) in messages.items()}
    started = time.perf_counter()
    for frame in range(frames):
        for name, (_, data) in messages.items():
            writer.write(connections[name], 1_000 + frame, data)
    writer.close()
    seconds = time.perf_counter() - started
    raw = frames * sum(len(data) for _, data in messages.values())
    return seconds * 1e3 / frames, sum(p.stat().st_size for p in out.iterdir()) / raw


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--workers", type=int, nargs="+",
                        default=sorted({0, compression_workers()}))
    parser.add_argument("--compression", nargs="+", choices=tuple(MCAP_COMPRESSIONS),
                        default=list(MCAP_COMPRESSIONS))
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    width, height = (int(n) for n in args.size.split("x"))
    messages = frame_messages(width, height)
    megabytes = sum(len(data) for _, data in messages.values()) / 1e6
    print(f"Bag writing, {date.today()}, {platform.processor() or platform.machine()} with "
          f"{len(os.sched_getaffinity(0))} cores; one {args.size} frame's messages "
          f"({megabytes:.1f} MB: the pair and the offline outputs) written {args.frames} "
          "times\n")
    print("| size | compression | zstd threads | ms a frame | MB/s | bag / raw |")
    print("| --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(args.rounds):
            for compression in args.compression:
                zstd = MCAP_COMPRESSIONS[compression][0] == "zstd"
                for workers in args.workers if zstd else args.workers[:1]:
                    ms, ratio = write_ms(messages, args.frames, compression, workers,
                                         Path(folder))
                    threads = str(workers) if zstd else "-"
                    print(f"| {args.size} | {compression} | {threads} | {ms:.1f} | "
                          f"{megabytes * 1e3 / ms:.0f} | {ratio:.2f} |", flush=True)


if __name__ == "__main__":
    main()
