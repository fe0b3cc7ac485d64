"""Survey accuracy on our generator's drive (48 frames, six potholes 1.5-8.5 cm deep, known
poses): per motion source, potholes reported against the truth, duplicates, false entries,
position errors, the largest depth's error from the fused road map and from the best single
view, severity classes and the visual odometry's drift. Prints a Markdown table for
docs/accuracy.md.

    python benchmarks/survey_accuracy.py [--width 480]
"""

from __future__ import annotations

import argparse
import datetime
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pothole_detector.recordings.writing import write_drive_bag  # noqa: E402
from pothole_detector.geodesy import enu_of  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.survey.drive import severity, survey  # noqa: E402
from pothole_detector.evaluation.synthetic import render, survey_drive  # noqa: E402

ORIGIN = (48.137, 11.575)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--width", type=int, default=480)
    args = parser.parse_args()
    scenes = [replace(s, supersample=1) for s in survey_drive(width=args.width,
                                                               height=args.width * 9 // 16)]
    samples = [render(s) for s in scenes]
    start = scenes[0].camera_y_m
    travelled = scenes[-1].camera_y_m - start
    config = Config({"backend": "cpu"})
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for kind, label in (("none", "visual odometry"), ("odom", "nav_msgs/Odometry"),
                            ("gnss", "NavSatFix (GNSS)")):
            bag = Path(scratch) / kind
            write_drive_bag(bag, [s.camera_y_m - start for s in scenes], samples,
                                     kind, ORIGIN)
            (drive,) = survey([bag], config)
            truths = []
            for shape in scenes[0].potholes:
                forward, left = shape.y_m - start, -shape.x_m
                truths.append((np.array((-left, forward) if kind == "gnss" else (forward, left)),
                               shape.depth_m))
            errors, matched, right_class, map_depth, view_depth = [], set(), 0, [], []
            for pothole in drive.potholes:
                position = np.array([pothole.row["odom_x_m"], pothole.row["odom_y_m"]])
                if kind == "gnss":
                    position = enu_of(np.array([pothole.row["lat"]]),
                                      np.array([pothole.row["lon"]]), *ORIGIN)[0]
                gaps = [np.linalg.norm(position - t) for t, _ in truths]
                nearest = int(np.argmin(gaps))
                if gaps[nearest] < 0.2:
                    matched.add(nearest)
                    errors.append(gaps[nearest])
                    right_class += pothole.row["severity"] == severity(truths[nearest][1], config)
                    map_depth.append(abs(pothole.row["max_depth_m"] - truths[nearest][1]))
                    view_depth.append(abs(pothole.best_view_depth_m - truths[nearest][1]))
            false = len(drive.potholes) - len(errors)
            duplicates = len(errors) - len(matched)
            drift = ""
            if kind == "none":
                along, across = drive.route_xy[-1] - [travelled, 0.0]
                drift = (f"{100 * abs(along) / travelled:.1f} % along, "
                         f"{100 * abs(across) / travelled:.1f} % across")
            rows.append((label, len(drive.potholes), len(truths), duplicates, false,
                         np.median(errors) if errors else np.nan,
                         max(errors) if errors else np.nan, right_class, drift,
                         1e3 * np.median(map_depth), 1e3 * np.median(view_depth)))
    print(f"survey accuracy, generator drive {args.width}x{args.width * 9 // 16}, 48 frames, "
          f"{travelled:.2f} m, six potholes; {datetime.date.today().isoformat()}")
    print("| motion from | reported / truth | duplicates | false | position error median / "
          "max (m) | depth error median, map / best view (mm) | severity right | odometry "
          "drift at the end |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for label, found, total, dup, false, median, worst, right, drift, by_map, by_view in rows:
        print(f"| {label} | {found} / {total} | {dup} | {false} | {median:.3f} / {worst:.3f} | "
              f"{by_map:.1f} / {by_view:.1f} | {right} / {found} | {drift or '-'} |")


if __name__ == "__main__":
    main()
