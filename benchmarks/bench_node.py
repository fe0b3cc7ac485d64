"""Node benchmark: feed the node (its own process) 1280x720 stereo over DDS at 10, 20 and
30 Hz; print processed rate, dropped sets, latency p50/p95, CPU and memory as a Markdown
table. Run: python benchmarks/bench_node.py [--seconds 15] [--rates 10 20 30]."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import rclpy

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from pothole_detector_msgs.msg import PotholeArray  # noqa: E402

from pothole_detector import conversions  # noqa: E402
from pothole_detector.transport import large_image_transport  # noqa: E402
from pothole_detector.synthetic import demo_scene, render  # noqa: E402
from rosgraph import NodeProcess, Probe, header_at, isolate_ros_graph, stamp_ns  # noqa: E402


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run(rate: float, seconds: float, frame: dict, log: Path) -> dict:
    node = NodeProcess(log, backend="cpu")
    probe = Probe(outputs=("potholes",))
    try:
        probe.wait_connected()
        sent: dict[int, float] = {}
        arrived: dict[int, float] = {}
        probe.node.create_subscription(
            PotholeArray, "/stereo/potholes", lambda m: arrived.setdefault(stamp_ns(m.header),
                                                            time.monotonic()), 50)
        pid = node.process.pid
        cpu0, wall0 = cpu_seconds(pid), time.monotonic()
        period = 1.0 / rate
        start = time.monotonic()
        index = 0
        rss = []
        while time.monotonic() - start < seconds:
            stamp = 1_900_000_000_000_000_000 + index * int(period * 1e9)
            for role in ("left_info", "right_info", "left", "right"):
                frame[role].header = header_at(stamp)
                probe.inputs[role].publish(frame[role])
            sent[stamp] = time.monotonic()
            index += 1
            rss.append(rss_mib(pid))
            probe.spin(max(0.0, start + index * period - time.monotonic()))
        probe.spin(3.0)
        cpu = (cpu_seconds(pid) - cpu0) / (time.monotonic() - wall0)
        latencies = np.array([(arrived[s] - sent[s]) * 1e3 for s in arrived if s in sent])
        diagnostics = probe.diagnostics()
        return {"rate": rate, "sent": len(sent), "processed": len(arrived),
                "processed_hz": len(arrived) / seconds,
                "dropped": int(diagnostics.get("dropped_sets", "0")),
                "p50": float(np.percentile(latencies, 50)) if latencies.size else float("nan"),
                "p95": float(np.percentile(latencies, 95)) if latencies.size else float("nan"),
                "cpu": cpu * 100, "rss": max(rss)}
    finally:
        probe.close()
        node.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--rates", type=float, nargs="+", default=[10.0, 20.0, 30.0])
    args = parser.parse_args()
    isolate_ros_graph()
    large_image_transport()
    rclpy.init()
    sample = render(demo_scene(1280, 720))
    header = header_at(0)
    height, width = sample.left.shape
    frame = {
        "left": conversions.array_to_image(sample.left, "mono8", header),
        "right": conversions.array_to_image(sample.right, "mono8", header),
        "left_info": conversions.camera_info_message(sample.calibration, width, height, header),
        "right_info": conversions.camera_info_message(sample.calibration, width, height,
                                                      header, right=True),
    }
    rows = [run(rate, args.seconds, frame, Path(f"/tmp/bench_node_{int(rate)}.log"))
            for rate in args.rates]
    print(f"node, CPU backend, 1280x720 mono8 stereo, {args.seconds:.0f} s per rate, "
          f"{os.cpu_count()} cores")
    print("| input Hz | sets sent | processed | processed Hz | dropped (counted) | "
          "latency p50 ms | latency p95 ms | node CPU % | node RSS MiB |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['rate']:.0f} | {r['sent']} | {r['processed']} | {r['processed_hz']:.1f} | "
              f"{r['dropped']} | {r['p50']:.0f} | {r['p95']:.0f} | {r['cpu']:.0f} | "
              f"{r['rss']:.0f} |")
    rclpy.shutdown()


if __name__ == "__main__":
    main()
