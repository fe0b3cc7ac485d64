"""A matrix of stereo rigs and roads for the synthetic evaluation: rig classes from a robot's
low camera to a survey vehicle's, each sampled into scenes with potholes, distractors (bumps,
raised manholes, shallow dips, markings, cracks, patches, stains, shadows), a crest, sag or
camber, sensor noise and a gain difference between the cameras (synthetic.py renders them)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .synthetic import BumpShape, Paint, PotholeShape, Scene

Range = tuple[float, float]


@dataclass(frozen=True)
class RigClass:
    """Ranges scenes of one kind of rig are drawn from. Lengths in m, angles in degrees; the
    focal length is in px of an image ``width`` x ``height``; potholes lie ``ahead_m`` along
    the road from the point below the camera."""

    name: str
    width: int
    height: int
    focal_px: Range
    baseline_m: Range
    camera_height_m: Range
    pitch_deg: Range
    ahead_m: Range
    semi_axis_m: Range
    depth_m: Range
    max_roll_deg: float = 5.0


RIG_CLASSES: tuple[RigClass, ...] = (
    RigClass("robot", 640, 480, (400.0, 600.0), (0.05, 0.10), (0.3, 0.5), (25.0, 45.0),
             (0.6, 2.5), (0.08, 0.2), (0.01, 0.08)),
    RigClass("paper", 1040, 520, (650.0, 750.0), (0.10, 0.14), (0.45, 0.7), (45.0, 70.0),
             (0.35, 1.4), (0.06, 0.14), (0.01, 0.08)),
    RigClass("vehicle", 1280, 720, (900.0, 1400.0), (0.12, 0.5), (1.0, 1.6), (5.0, 20.0),
             (2.5, 20.0), (0.3, 0.6), (0.01, 0.15)),
    RigClass("survey", 2080, 1040, (1400.0, 2000.0), (0.3, 0.5), (1.5, 2.0), (30.0, 60.0),
             (1.0, 6.0), (0.15, 0.45), (0.01, 0.12)),
)
RIG_CLASS_BY_NAME = {rig.name: rig for rig in RIG_CLASSES}


def visible_range_m(scene: Scene) -> tuple[float, float]:
    """Distance along the road (m, from the point below the camera) of the bottom image row's
    centre and of the top row's (inf where the top row sees the horizon), on a flat road."""
    half_rows = (scene.height - 1) / 2.0
    low = math.radians(scene.pitch_deg) + math.atan(half_rows / scene.focal_px)
    high = math.radians(scene.pitch_deg) - math.atan(half_rows / scene.focal_px)
    near = scene.camera_height_m / math.tan(low) if low < math.pi / 2 else 0.0
    far = scene.camera_height_m / math.tan(high) if high > 0 else math.inf
    return near, far


def half_width_m(scene: Scene, ahead_m: float) -> float:
    """Half the width of road (m) that the image spans at ``ahead_m`` along the road."""
    slant = math.hypot(scene.camera_height_m, ahead_m)
    return slant * (scene.width - 1) / 2.0 / scene.focal_px


def sample_scene(rig: RigClass, index: int, potholes: int = 3, distractors: int = 4,
                 seed: int = 0) -> Scene:
    """Scene ``index`` of ``rig``: a rig drawn from its ranges, ``potholes`` potholes (none
    overlapping, inside the view) and ``distractors`` distractors, a road shape (flat, crest or
    sag of 1,500 m radius, or cambered), sensor noise of 1-2 grey levels and a right camera
    gain within 5 %. The same (rig, index, seed) always gives the same scene."""
    rng = np.random.default_rng([seed, index, sum(map(ord, rig.name))])

    def draw(bounds: Range) -> float:
        return float(rng.uniform(*bounds))

    shape = rng.integers(0, 4)
    base = Scene(width=rig.width, height=rig.height, focal_px=draw(rig.focal_px),
                 baseline_m=draw(rig.baseline_m), camera_height_m=draw(rig.camera_height_m),
                 pitch_deg=draw(rig.pitch_deg),
                 roll_deg=draw((-rig.max_roll_deg, rig.max_roll_deg)),
                 texture_seed=int(rng.integers(1, 1 << 30)),
                 grade_radius_m=(0.0, 1500.0, -1500.0, 0.0)[shape],
                 crown_per_m=0.007 if shape == 3 else 0.0,
                 noise_grey=draw((1.0, 2.0)), right_gain=draw((0.95, 1.05)))
    near, far = visible_range_m(base)
    margin = 1.5 * rig.semi_axis_m[1]
    low, high = near + margin, max(near + margin, min(far, 1e3) - margin)
    ahead = (min(max(rig.ahead_m[0], low), high), max(min(rig.ahead_m[1], high), low))
    placed: list[tuple[float, float, float]] = []

    def place(radius: float) -> tuple[float, float] | None:
        for _ in range(50):
            y = draw(ahead)
            x = draw((-0.8, 0.8)) * max(half_width_m(base, y) - radius, 0.0)
            if all(math.hypot(x - px, y - py) > radius + pr + 0.05 for px, py, pr in placed):
                placed.append((x, y, radius))
                return x, y
        return None

    holes: list[PotholeShape] = []
    for _ in range(potholes):
        a, b = sorted((draw(rig.semi_axis_m), draw(rig.semi_axis_m)), reverse=True)
        spot = place(a)
        if spot is not None:
            holes.append(PotholeShape(*spot, a, b, draw(rig.depth_m), draw((-90.0, 90.0)),
                                      wall_power=draw((2.0, 8.0))))
    relief: list[PotholeShape | BumpShape] = []
    paint: list[Paint] = []
    scale = 0.5 * sum(rig.semi_axis_m)
    for kind in rng.permutation(len(DISTRACTORS))[:distractors]:
        name = DISTRACTORS[kind]
        size = scale * draw((0.8, 1.4))
        spot = place(3.0 * size if name in ("speed_bump", "marking") else size)
        if spot is None:
            continue
        x, y = spot
        angle = draw((-90.0, 90.0))
        if name == "manhole":
            relief.append(BumpShape(x, y, size, size, draw((0.01, 0.02)), "disc"))
        elif name == "speed_bump":
            relief.append(BumpShape(x, y, 3.0 * size, 0.6 * size, draw((0.03, 0.07)),
                                    "ridge", draw((-10.0, 10.0))))
        elif name == "dip":
            relief.append(PotholeShape(x, y, size, 0.7 * size, draw((0.003, 0.008)), angle))
        elif name == "marking":
            paint.append(Paint(x, y, 3.0 * size, 0.12 * size, 1.8, "line",
                               90.0 + draw((-10.0, 10.0))))
        elif name == "crack":
            paint.append(Paint(x, y, size, 0.02 * size, 0.3, "line", angle))
        elif name == "patch":
            paint.append(Paint(x, y, size, 0.8 * size, 0.6, "ellipse", angle))
        elif name == "stain":
            paint.append(Paint(x, y, 0.7 * size, 0.5 * size, 0.4, "ellipse", angle))
        else:
            paint.append(Paint(x, y, 1.5 * size, size, 0.45, "ellipse", angle))
    return Scene(**{**base.__dict__, "potholes": tuple(holes), "relief": tuple(relief),
                    "paint": tuple(paint)})


DISTRACTORS = ("manhole", "speed_bump", "dip", "marking", "crack", "patch", "stain", "shadow")
RIG_CLASS_NAMES = tuple(RIG_CLASS_BY_NAME)
