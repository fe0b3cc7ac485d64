from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pothole_detector.synthetic import PotholeShape, Scene, demo_scene, render

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def demo_sample():
    """The demo road (three potholes) at 640x360."""
    return render(demo_scene(640, 360))


@pytest.fixture(scope="session")
def flat_sample():
    """The demo rig over a road without potholes."""
    scene = demo_scene(640, 360)
    return render(Scene(**{**scene.__dict__, "potholes": ()}))


@pytest.fixture(scope="session")
def bowl_sample():
    """One large bowl in the middle of the view, rendered without supersampling."""
    scene = Scene(width=480, height=360, focal_px=0.67 * 480, camera_height_m=0.6,
                  pitch_deg=60.0, roll_deg=2.0, supersample=1,
                  potholes=(PotholeShape(0.0, 0.38, 0.12, 0.09, 0.05, 10.0),))
    return render(scene)


def shared_data(*parts: str) -> Path:
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data {path} is not available")
    return path


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = (a | b).sum()
    return float((a & b).sum() / union) if union else 1.0
