"""The paper's metrics on datasets with ground truth (formats of shared/data/README.md)."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, TextIO

import cv2
import numpy as np

from .backend import Backend
from .calibration import StereoCalibration
from .errors import InputError, PotholeError
from .imageio import read_image
from .params import Config
from .pipeline import Pipeline
from .stages import matching, perspective
from .stages.road_model import fit_road

# Calibrations used when a dataset ships none (metric outputs only; pixel metrics ignore them).
FAN_POTHOLES_FOCAL_PX, FAN_POTHOLES_BASELINE_M = 1390.0, 0.1194
KITTI_FOCAL_PX, KITTI_BASELINE_M = 721.5, 0.54
MIDDLEBURY_FOCAL_PX, MIDDLEBURY_BASELINE_M = 1000.0, 0.16


@dataclass
class Sample:
    """One evaluation pair: images, and pothole mask + ROI or ground-truth disparity."""

    name: str
    left: Path
    right: Path
    focal_px: float
    baseline_m: float
    pothole_mask: Path | None = None
    roi: Path | None = None
    disparity: Path | None = None
    disparity_format: str = ""

    def ground_truth_disparity(self) -> np.ndarray:
        """float32 HxW px, NaN = unknown."""
        assert self.disparity is not None
        if self.disparity_format == "npz":
            with np.load(self.disparity) as data:
                values = np.asarray(data[data.files[0]], dtype=np.float32)
            return np.where(np.isfinite(values) & (values > 0), values, np.nan)
        raw = cv2.imread(str(self.disparity), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise InputError(f"cannot read ground truth {self.disparity}")
        if raw.ndim == 3:
            raw = raw[:, :, 0]
        scale = {"kitti": 256.0, "middlebury4": 4.0, "middlebury1": 1.0}[self.disparity_format]
        values = raw.astype(np.float32) / scale
        return np.where(raw > 0, values, np.nan).astype(np.float32)


def discover(root: str | Path) -> list[Sample]:
    """Every evaluable pair under ``root`` (fan_potholes frames, KITTI, Middlebury)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root} is not a directory")
    samples: list[Sample] = []
    for mask in sorted(root.rglob("pothole_mask.png")):
        folder = mask.parent
        samples.append(Sample(folder.name, folder / "left.png", folder / "right.png",
                              FAN_POTHOLES_FOCAL_PX, FAN_POTHOLES_BASELINE_M, pothole_mask=mask,
                              roi=folder / "label_roi.png"))
    for left_dir, right_dir, gt_dir in (("colored_0", "colored_1", "disp_occ"),
                                        ("image_2", "image_3", "disp_occ_0")):
        for gt_folder in sorted(root.rglob(gt_dir)):
            base = gt_folder.parent
            for gt in sorted(gt_folder.glob("*.png")):
                left, right = base / left_dir / gt.name, base / right_dir / gt.name
                if left.is_file() and right.is_file():
                    samples.append(Sample(f"{base.name}/{gt.stem}", left, right, KITTI_FOCAL_PX,
                                          KITTI_BASELINE_M, disparity=gt,
                                          disparity_format="kitti"))
    for gt in sorted(root.rglob("disp2.png")):
        folder = gt.parent
        left, right = folder / "im2.png", folder / "im6.png"
        if left.is_file() and right.is_file():
            samples.append(Sample(folder.name, left, right, MIDDLEBURY_FOCAL_PX,
                                  MIDDLEBURY_BASELINE_M, disparity=gt,
                                  disparity_format="middlebury4"))
    for gt in sorted(root.rglob("aloeGT.png")):
        folder = gt.parent
        samples.append(Sample(folder.name, folder / "aloeL.jpg", folder / "aloeR.jpg",
                              MIDDLEBURY_FOCAL_PX, MIDDLEBURY_BASELINE_M, disparity=gt,
                              disparity_format="middlebury1"))
    for gt in sorted(root.rglob("motorcycle_disp.npz")):
        folder = gt.parent
        lefts = sorted(folder.glob("*left*.png")) or sorted(folder.glob("im0*.png"))
        rights = sorted(folder.glob("*right*.png")) or sorted(folder.glob("im1*.png"))
        if lefts and rights:
            samples.append(Sample(folder.name, lefts[0], rights[0], MIDDLEBURY_FOCAL_PX,
                                  MIDDLEBURY_BASELINE_M, disparity=gt, disparity_format="npz"))
    return samples


@dataclass
class PixelCounts:
    """Pixel confusion counts of pothole (positive) against road."""

    tp: int = 0
    fp: int = 0
    fn: int = 0
    tn: int = 0

    def add(self, predicted: np.ndarray, truth: np.ndarray, roi: np.ndarray) -> None:
        self.tp += int((predicted & truth & roi).sum())
        self.fp += int((predicted & ~truth & roi).sum())
        self.fn += int((~predicted & truth & roi).sum())
        self.tn += int((~predicted & ~truth & roi).sum())

    @property
    def precision(self) -> float:
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else 0.0

    @property
    def recall(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else 0.0

    @property
    def accuracy(self) -> float:
        total = self.tp + self.fp + self.fn + self.tn
        return (self.tp + self.tn) / total if total else 0.0

    @property
    def f_score(self) -> float:
        denominator = 2 * self.tp + self.fp + self.fn
        return 2 * self.tp / denominator if denominator else 0.0


@dataclass
class ObjectCounts:
    """Pothole-level outcomes: correct and incorrect detections, missed potholes."""

    correct: int = 0
    incorrect: int = 0
    missed: int = 0

    def add(self, labels: np.ndarray, truth: np.ndarray, roi: np.ndarray,
            min_precision: float = 0.5) -> None:
        """A detection is correct when at least ``min_precision`` of its pixels inside the ROI
        are pothole; a true pothole is missed when no correct detection overlaps it."""
        n_truth, truth_labels = cv2.connectedComponents(truth.astype(np.uint8), connectivity=8)
        hit = np.zeros(n_truth, dtype=bool)
        for label in np.unique(labels[roi & (labels > 0)]):
            inside = (labels == label) & roi
            overlap = inside & truth
            if overlap.sum() >= min_precision * inside.sum():
                self.correct += 1
                hit[np.unique(truth_labels[overlap])] = True
            else:
                self.incorrect += 1
        self.missed += int((~hit[1:]).sum())


def disparity_errors(estimate: np.ndarray, truth: np.ndarray, region: np.ndarray | None = None,
                     ) -> dict[str, float]:
    """PEP at 1/2/3 px (% of evaluated pixels off by more), RMSE (px) and density (%) over the
    pixels with ground truth (inside ``region`` if given). Invalid estimates count as errors
    in PEP and are left out of RMSE."""
    known = np.isfinite(truth)
    if region is not None:
        known &= region
    n = int(known.sum())
    if n == 0:
        return {"pep1": float("nan"), "pep2": float("nan"), "pep3": float("nan"),
                "rmse": float("nan"), "density": 0.0, "pixels": 0}
    error = np.abs(estimate[known] - truth[known])
    valid = np.isfinite(error)
    error_for_pep = np.where(valid, error, np.inf)
    result = {f"pep{e}": 100.0 * float((error_for_pep > e).mean()) for e in (1, 2, 3)}
    result["rmse"] = float(np.sqrt(np.mean(error[valid] ** 2))) if valid.any() else float("nan")
    result["density"] = 100.0 * float(valid.mean())
    result["pixels"] = n
    return result


def road_region(truth: np.ndarray) -> np.ndarray:
    """Ground-truth pixels on the dominant road plane: inliers of a robust road fit to the
    ground truth itself, in the lower half of the image."""
    model = fit_road(np, truth, rounds=3, outlier_k=2.5)
    height, width = truth.shape
    residual = np.abs(truth - model.disparity(np, height, width))
    lower = np.zeros_like(truth, dtype=bool)
    lower[height // 2:] = True
    return np.isfinite(truth) & (residual <= max(1.0, 2.5 * model.sigma_px)) & lower


@dataclass
class EvaluationReport:
    """Rows per sample and the totals."""

    pixels: PixelCounts = field(default_factory=PixelCounts)
    objects: ObjectCounts = field(default_factory=ObjectCounts)
    pothole_rows: list[dict] = field(default_factory=list)
    disparity_rows: list[dict] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def markdown(self) -> str:
        """The report as Markdown tables."""
        lines: list[str] = []
        if self.pothole_rows:
            lines += ["## Potholes (pixels inside the labelled ROI)", "",
                      "| frame | precision | recall | accuracy | F-score | detections | "
                      "correct | incorrect | missed | ms |",
                      "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
            for row in self.pothole_rows:
                lines.append(
                    f"| {row['name']} | {row['precision']:.4f} | {row['recall']:.4f} | "
                    f"{row['accuracy']:.4f} | {row['f_score']:.4f} | {row['detections']} | "
                    f"{row['correct']} | {row['incorrect']} | {row['missed']} | "
                    f"{row['ms']:.0f} |")
            p, o = self.pixels, self.objects
            lines.append(f"| **all** | {p.precision:.4f} | {p.recall:.4f} | {p.accuracy:.4f} | "
                         f"{p.f_score:.4f} | {o.correct + o.incorrect} | {o.correct} | "
                         f"{o.incorrect} | {o.missed} | |")
            lines.append("")
        if self.disparity_rows:
            lines += ["## Disparity (PEP % of pixels off by more than 1/2/3 px; RMSE px over "
                      "valid estimates; density % of ground-truth pixels with an estimate)", "",
                      "| pair | matcher | region | PEP1 | PEP2 | PEP3 | RMSE | density | "
                      "levels | ms |",
                      "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
            for row in self.disparity_rows:
                lines.append(
                    f"| {row['name']} | {row['matcher']} | {row['region']} | {row['pep1']:.2f} |"
                    f" {row['pep2']:.2f} | {row['pep3']:.2f} | {row['rmse']:.3f} | "
                    f"{row['density']:.1f} | {row['levels']} | {row['ms']:.0f} |")
            lines.append("")
        if self.errors:
            lines += ["## Pairs that failed", ""] + [f"- {e}" for e in self.errors] + [""]
        return "\n".join(lines)


def draw_progress(index: int, total: int, start: float, label: str,
                  stream: TextIO = sys.stderr) -> None:
    """Redraw a one-line progress bar: ``index`` of ``total`` done since ``start``
    (perf_counter seconds); a newline once complete."""
    done = int(30 * index / max(total, 1))
    stream.write(f"\r{label} [{'#' * done}{'.' * (30 - done)}] {index}/{total} "
                 f"{time.perf_counter() - start:5.1f}s" + ("\n" if index >= total else ""))
    stream.flush()


def progress(items: list, stream: TextIO = sys.stderr, label: str = "evaluate") -> Iterator:
    """Yield ``items`` while drawing a one-line progress bar on ``stream``."""
    start = time.perf_counter()
    for index, item in enumerate(items):
        draw_progress(index, len(items), start, label, stream)
        yield item
    draw_progress(len(items), len(items), start, label, stream)


def evaluate(root: str | Path, config: Config, backend: Backend,
             stream: TextIO = sys.stderr) -> EvaluationReport:
    """Run detection (pothole sets) or matching (disparity sets) on every pair under ``root``."""
    samples = discover(root)
    if not samples:
        raise InputError(f"no evaluable pairs under {root}: expected left.png/right.png/"
                         "pothole_mask.png folders, KITTI or Middlebury layouts")
    report = EvaluationReport()
    for sample in progress(samples, stream):
        try:
            if sample.pothole_mask is not None:
                _evaluate_potholes(sample, config, backend, report)
            else:
                _evaluate_disparity(sample, config, backend, report)
        except PotholeError as error:
            report.errors.append(f"{sample.name}: {error}")
    return report


def _evaluate_potholes(sample: Sample, config: Config, backend: Backend,
                       report: EvaluationReport) -> None:
    left, right = read_image(sample.left), read_image(sample.right)
    truth = cv2.imread(str(sample.pothole_mask), cv2.IMREAD_GRAYSCALE) > 0
    roi = (cv2.imread(str(sample.roi), cv2.IMREAD_GRAYSCALE) > 0 if sample.roi and
           sample.roi.is_file() else np.ones_like(truth))
    calibration = StereoCalibration.from_focal_baseline(
        sample.focal_px, sample.baseline_m, left.shape[1], left.shape[0])
    start = time.perf_counter()
    result = Pipeline(config, calibration, backend).run(left, right)
    elapsed = (time.perf_counter() - start) * 1e3
    labels = result.host("labels")
    pixels, objects = PixelCounts(), ObjectCounts()
    pixels.add(labels > 0, truth, roi)
    objects.add(labels, truth, roi)
    for total, part in ((report.pixels, pixels), (report.objects, objects)):
        for name in part.__dataclass_fields__:
            setattr(total, name, getattr(total, name) + getattr(part, name))
    report.pothole_rows.append({
        "name": sample.name, "precision": pixels.precision, "recall": pixels.recall,
        "accuracy": pixels.accuracy, "f_score": pixels.f_score,
        "detections": len(result.potholes), "correct": objects.correct,
        "incorrect": objects.incorrect, "missed": objects.missed, "ms": elapsed,
    })


def _evaluate_disparity(sample: Sample, config: Config, backend: Backend,
                        report: EvaluationReport) -> None:
    """GPT-SGM (our matcher) and plain SGBM over the full range with the same settings."""
    left, right = read_image(sample.left), read_image(sample.right)
    truth = sample.ground_truth_disparity()
    if truth.shape != left.shape[:2]:
        raise InputError(f"ground truth {truth.shape} and image {left.shape[:2]} differ")
    calibration = StereoCalibration.from_focal_baseline(
        sample.focal_px, sample.baseline_m, left.shape[1], left.shape[0])
    levels_full = perspective.round_up_levels(max(float(np.nanmax(truth)) + 1, 16))
    full_config = config.replace(max_disparity_px=levels_full)
    pipeline = Pipeline(full_config, calibration, backend)
    start = time.perf_counter()
    ours, levels = pipeline.match_pair(left, right)
    ours_ms = (time.perf_counter() - start) * 1e3
    gray_left, gray_right = matching.to_gray8(left), matching.to_gray8(right)
    start = time.perf_counter()
    plain = matching.sgm_disparity(gray_left, gray_right, levels_full, full_config)
    plain_ms = (time.perf_counter() - start) * 1e3
    ours = backend.to_host(ours)
    road = road_region(truth)
    for matcher, estimate, n_levels, ms in (("GPT-SGM (ours)", ours, levels, ours_ms),
                                            ("OpenCV SGBM", plain, levels_full, plain_ms)):
        for region_name, region in (("road", road), ("all", None)):
            errors = disparity_errors(estimate, truth, region)
            report.disparity_rows.append({"name": sample.name, "matcher": matcher,
                                          "region": region_name, "levels": n_levels, "ms": ms,
                                          **errors})
