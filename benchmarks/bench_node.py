"""Node benchmark: start the node (its own process, ``--backend``) and feed it stereo pairs
over DDS from this process, as a camera driver would: for each image size, after a warm-up,
each rate for ``--seconds``. Prints a Markdown table (for docs/benchmarks.md): processed rate,
sets the node dropped, sets that never arrived, latency from publishing a set to receiving its
``potholes`` (p50/p95; "in node": from the set's arrival to its ``potholes``, over the node's
last 5 s), the worker's time on a set (p95 and longest, last 5 s) and, of it, decoding the two
images (p95), sets this process sent more
than a period late (its own stalls, which reach the node as bursts), and the node's CPU per
processed frame: all threads, and the worker thread split into message conversion (images in,
messages out) and the pipeline.

Run: python benchmarks/bench_node.py [--backend gpu] [--sizes 1280x720 2079x1040]
     [--rates 30 60] [--seconds 10] [--encoding mono8|rgb8|raw-jpeg]
``--encoding raw-jpeg``: colour JPEG CompressedImage of a raw, distorted and slightly rotated
camera (plumb_bob, with its camera_info) on .../image_rect/compressed, as a driver's
image_transport publishes them: the node decodes and rectifies every set.
On the GPU machine: source scripts/gpu_machine/env.sh first (docs/gpu-machine.md)."""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import rclpy

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from pothole_detector_msgs.msg import PotholeArray  # noqa: E402

from pothole_detector.recordings.camera import camera_info_message, camera_info_of  # noqa: E402
from pothole_detector.recordings.images import array_to_image, compressed_image  # noqa: E402
from pothole_detector.evaluation.synthetic import demo_scene, raw_camera, render, render_raw  # noqa
from pothole_detector.ros.transport import large_image_transport  # noqa: E402
from rosgraph import NodeProcess, Probe, header_at, isolate_ros_graph, stamp_ns  # noqa: E402

FIRST_STAMP_NS = 1_900_000_000_000_000_000


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (all threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


class Feeder:
    """Publishes one rendered stereo set at a fixed rate with fresh stamps and records when
    each set went out and when its ``potholes`` came back."""

    def __init__(self, probe: Probe, frame: dict) -> None:
        self.probe = probe
        self.frame = frame
        self.index = 0
        self.sent: dict[int, float] = {}
        self.arrived: dict[int, float] = {}
        self.late = 0
        probe.node.create_subscription(
            PotholeArray, f"{probe.namespace}/potholes",
            lambda m: self.arrived.setdefault(stamp_ns(m.header), time.monotonic()), 100)

    def feed(self, rate: float, seconds: float) -> list[int]:
        """Publish at ``rate`` Hz for ``seconds``; the stamps sent."""
        period, start, stamps = 1.0 / rate, time.monotonic(), []
        self.late = 0
        while time.monotonic() - start < seconds:
            stamp = FIRST_STAMP_NS + self.index * 1_000_000
            self.late += time.monotonic() > start + (len(stamps) + 1) * period
            self.probe.publish(self.frame, stamp)
            self.sent[stamp] = time.monotonic()
            stamps.append(stamp)
            self.index += 1
            self.probe.spin(max(0.0, start + len(stamps) * period - time.monotonic()))
        self.probe.spin(2.0)
        return stamps


def measure(feeder: Feeder, pid: int, rate: float, seconds: float) -> dict:
    dropped_before = int(feeder.probe.diagnostics().get("dropped_sets", "0"))
    cpu0 = cpu_seconds(pid)
    stamps = feeder.feed(rate, seconds)
    cpu = cpu_seconds(pid) - cpu0
    diagnostics = feeder.probe.diagnostics()
    arrived = [s for s in stamps if s in feeder.arrived]
    latencies = np.array([(feeder.arrived[s] - feeder.sent[s]) * 1e3 for s in arrived])
    dropped = int(diagnostics.get("dropped_sets", "0")) - dropped_before
    return {
        "rate": rate, "sent": len(stamps), "processed": len(arrived),
        "processed_hz": len(arrived) / seconds, "dropped": dropped,
        "lost": len(stamps) - len(arrived) - dropped,
        "p50": float(np.percentile(latencies, 50)) if latencies.size else float("nan"),
        "p95": float(np.percentile(latencies, 95)) if latencies.size else float("nan"),
        "cpu_ms": cpu * 1e3 / max(len(arrived), 1),
        "conversion_ms": float(diagnostics.get("conversion_cpu_ms_per_frame", "nan")),
        "pipeline_ms": float(diagnostics.get("pipeline_cpu_ms_per_frame", "nan")),
        "work_p95": float(diagnostics.get("work_p95_ms", "nan")),
        "node_p95": float(diagnostics.get("latency_p95_ms", "nan")),
        "work_max": float(diagnostics.get("work_max_ms", "nan")), "late": feeder.late,
        "decode_p95": float(diagnostics.get("decode_p95_ms", "nan")),
        "rss": rss_mib(pid), "backend": diagnostics.get("backend", "?"),
    }


def bench_size(width: int, height: int, rates: list[float], seconds: float, backend: str,
               encoding: str, node_params: dict[str, str]) -> list[dict]:
    scene = demo_scene(width, height)
    sample = render(scene)
    header = header_at(0)
    images = {side: sample.left if side == "left" else sample.right for side in ("left", "right")}
    infos = [camera_info_message(sample.calibration, width, height, header,
                                             right=right) for right in (False, True)]
    if encoding == "raw-jpeg":
        camera = raw_camera(sample.calibration, width, height, "plumb_bob")
        images = dict(zip(("left", "right"), render_raw(scene, camera)))
        infos = [camera_info_of(model, header)
                 for model in (camera.left, camera.right)]
        node_params = {"image_transport": "compressed", **node_params}
    if encoding in ("rgb8", "raw-jpeg"):
        images = {side: np.repeat(image[..., None], 3, axis=2) for side, image in images.items()}
    make = (lambda pixels: compressed_image(pixels, "jpeg", header)) \
        if encoding == "raw-jpeg" else \
        (lambda pixels: array_to_image(pixels, encoding, header))
    frame = {"left": make(images["left"]), "right": make(images["right"]),
             "left_info": infos[0], "right_info": infos[1]}
    node = NodeProcess(Path(f"/tmp/bench_node_{width}x{height}.log"), backend=backend,
                       **node_params)
    probe = Probe(outputs=(), compressed=encoding == "raw-jpeg")
    try:
        probe.wait_connected(timeout=60.0)
        feeder = Feeder(probe, frame)
        feeder.feed(5.0, 4.0)
        if not feeder.arrived:
            feeder.feed(2.0, 20.0)
        if not feeder.arrived:
            raise SystemExit(f"the node processed no {width}x{height} frame; its log: "
                             f"{node.log}\n{node.text()[-2000:]}")
        rows = []
        for rate in rates:
            row = measure(feeder, node.process.pid, rate, seconds)
            rows.append({"size": f"{width}x{height}", **row})
        return rows
    finally:
        probe.close()
        node.stop()


def device_name(backend: str) -> str:
    if backend == "cpu":
        return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    from pothole_detector.backend import get_backend
    return f"{get_backend(backend).name}, host {os.cpu_count()} cores"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--backend", default="cpu", choices=("cpu", "gpu", "auto"))
    parser.add_argument("--sizes", nargs="+", default=["1280x720"])
    parser.add_argument("--rates", type=float, nargs="+", default=[10.0, 20.0, 30.0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--encoding", default="mono8", choices=("mono8", "rgb8", "raw-jpeg"))
    parser.add_argument("--node-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="a parameter of the node (repeatable)")
    args = parser.parse_args()
    isolate_ros_graph()
    large_image_transport()
    rclpy.init()
    rows = []
    for size in args.sizes:
        width, height = (int(v) for v in size.lower().split("x"))
        rows += bench_size(width, height, args.rates, args.seconds, args.backend, args.encoding,
                           dict(item.split(":=", 1) for item in args.node_param))
    rclpy.shutdown()
    print(f"node benchmark, backend {rows[0]['backend']} ({device_name(args.backend)}), "
          f"{args.encoding} stereo over DDS from another process, {args.seconds:.0f} s per "
          f"rate, {datetime.date.today().isoformat()}"
          + "".join(f", {item}" for item in args.node_param))
    print("| size | input Hz | sets sent | processed | processed Hz | dropped by node | "
          "never arrived | sent late | latency p50 ms | latency p95 ms | in node p95 ms | "
          "worker p95 ms | worker max ms | decoding p95 ms | CPU ms/frame all | conversion | "
          "pipeline | node RSS MiB |")
    print("| --- " * 18 + "|")
    for r in rows:
        print(f"| {r['size']} | {r['rate']:.0f} | {r['sent']} | {r['processed']} | "
              f"{r['processed_hz']:.1f} | {r['dropped']} | {r['lost']} | {r['late']} | "
              f"{r['p50']:.1f} | {r['p95']:.1f} | {r['node_p95']:.1f} | {r['work_p95']:.1f} | "
              f"{r['work_max']:.1f} | {r['decode_p95']:.1f} | {r['cpu_ms']:.1f} | "
              f"{r['conversion_ms']:.1f} | "
              f"{r['pipeline_ms']:.1f} | {r['rss']:.0f} |")


if __name__ == "__main__":
    main()
