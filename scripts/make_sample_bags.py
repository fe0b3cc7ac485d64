"""Regenerate the sample bags in bags/ (deterministic): python scripts/make_sample_bags.py."""

from __future__ import annotations

import shutil
from pathlib import Path

from pothole_detector.recordings.writing import write_stereo_bag
from pothole_detector.calibration import load_stereo_camera_info
from pothole_detector.imageio import read_image
from pothole_detector.evaluation.synthetic import drive_scenes, render

BAGS = Path(__file__).resolve().parents[1] / "bags"
START_NS = 1_700_000_000_000_000_000
RATE_HZ = 10.0


class RealPair:
    """The bundled real pair in the shape write_stereo_bag expects."""

    def __init__(self, folder: Path) -> None:
        self.left = read_image(folder / "left.png")
        self.right = read_image(folder / "right.png")
        camera, _ = load_stereo_camera_info(folder / "left_camera_info.yaml",
                                            folder / "right_camera_info.yaml")
        self.calibration = camera.calibration()


def main() -> None:
    drive = BAGS / "sample_drive"
    shutil.rmtree(drive, ignore_errors=True)
    scenes = drive_scenes(frames=16, rate_hz=RATE_HZ)
    frames = ((START_NS + int(i * 1e9 / RATE_HZ), render(s)) for i, s in enumerate(scenes))
    print("sample_drive:", write_stereo_bag(drive, frames), "frames")
    real = BAGS / "sample_real"
    shutil.rmtree(real, ignore_errors=True)
    pair = RealPair(BAGS / "sample_pair")
    print("sample_real:", write_stereo_bag(real, [(START_NS, pair)], ground_truth=False),
          "frame")


if __name__ == "__main__":
    main()
