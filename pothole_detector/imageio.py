"""Reading images and writing the detector's pictures (no ROS)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .errors import InputError
from .stages.measure import Pothole


def read_image(path: str | Path) -> np.ndarray:
    """An image file as HxW (mono) or HxWx3 RGB uint8/uint16. Raises InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"image {path} does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path} is not an image OpenCV can read (PNG, JPEG, PGM, ...)")
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB
        image = cv2.cvtColor(image, code)
    return image


def write_labels(path: str | Path, labels: np.ndarray) -> None:
    """Labels as a 16-bit PNG (0 = road, k = pothole k)."""
    cv2.imwrite(str(path), labels.astype(np.uint16))


PALETTE = np.array([(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48),
                    (145, 30, 180), (70, 240, 240), (240, 50, 230)], dtype=np.uint8)


UNSEARCHED_SHADE, UNOBSERVED_SHADE = 0.4, 0.7


def _shade_table(shade: float) -> np.ndarray:
    """uint8 (256,): each value times ``shade``, truncated."""
    return (np.arange(256, dtype=np.uint8) * shade).astype(np.uint8)


def _tint_table(colour: np.ndarray) -> np.ndarray:
    """uint8 (256, 1, 3): each value blended with the RGB ``colour``, 0.55 of the value and
    0.45 of the colour, truncated (a table for cv2.LUT of an RGB image)."""
    values = np.arange(256, dtype=np.uint8)[:, None]
    return (0.55 * values + 0.45 * colour).astype(np.uint8).reshape(256, 1, 3)


def overlay(image: np.ndarray, labels: np.ndarray, potholes: list[Pothole],
            observed: np.ndarray | None = None,
            searched: np.ndarray | None = None) -> np.ndarray:
    """RGB uint8 HxWx3: ``image`` with each pothole tinted and outlined, its id, maximum depth
    (cm) and area (m^2) written beside it; where the bool HxW ``searched`` is false (the road
    is too far or too noisy for a pothole to show) dimmed to UNSEARCHED_SHADE, and where it
    is searched but the bool HxW ``observed`` is false (a pothole would show in a
    superpixel's mean, not in one pixel) to UNOBSERVED_SHADE; without ``searched``, the road
    not observed to UNSEARCHED_SHADE."""
    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / max(float(image.max()), 1.0))
    canvas = image.copy()
    if observed is not None:
        looked = observed if searched is None else searched
        for shaded, shade in ((~looked, UNSEARCHED_SHADE),
                              (looked & ~observed, UNOBSERVED_SHADE)):
            cv2.copyTo(cv2.LUT(canvas, _shade_table(shade)), shaded.view(np.uint8), canvas)
    if canvas.ndim == 2:
        canvas = cv2.cvtColor(canvas, cv2.COLOR_GRAY2RGB)
    scale = max(0.5, min(image.shape[:2]) / 700.0)
    thickness = max(1, int(round(2 * scale)))
    for pothole in potholes:
        colour = PALETTE[(pothole.label - 1) % len(PALETTE)]
        rows, cols = pothole.window(labels.shape)
        mask = (labels[rows, cols] == pothole.label).view(np.uint8)
        window = canvas[rows, cols]
        cv2.copyTo(cv2.LUT(window, _tint_table(colour)), mask, window)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE,
                                       offset=(cols.start, rows.start))
        cv2.drawContours(canvas, contours, -1, tuple(int(c) for c in colour), thickness)
        write_label(canvas, pothole, scale, thickness)
    return canvas


def write_label(canvas: np.ndarray, pothole: Pothole, scale: float, thickness: int) -> None:
    """The pothole's id, maximum depth (cm) and area (m^2) in white on black beside its box's
    top right corner, kept inside the RGB uint8 HxWx3 ``canvas`` (drawn in place)."""
    _, v0, u1, _ = pothole.bbox_px
    text = f"#{pothole.label} {pothole.max_depth_m * 100:.1f} cm {pothole.area_m2:.3f} m2"
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, thickness)
    x = int(min(max(u1 + 4, 0), max(canvas.shape[1] - tw - 2, 0)))
    y = int(min(max(v0 + th + 2, th + 2), canvas.shape[0] - 2))
    cv2.rectangle(canvas, (x - 2, y - th - 4), (x + tw + 2, y + 4), (0, 0, 0), -1)
    cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale,
                (255, 255, 255), thickness, cv2.LINE_AA)


def write_rgb(path: str | Path, image: np.ndarray) -> None:
    """Write an RGB (or mono) uint8 image."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), image):
        raise InputError(f"could not write {path}")
