"""The paper's metrics on datasets with ground truth (formats of shared/data/README.md), and the
scores we are judged by on the independent renderer's validation scenes."""

from __future__ import annotations

import hashlib
import json
import math
import pickle
import sys
import time
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, fields
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Iterable, Iterator, TextIO

import cv2
import numpy as np
import yaml

from ..backend import Backend
from ..calibration import StereoCalibration
from ..errors import InputError, PotholeError
from ..imageio import read_image
from ..params import Config
from ..pipeline import Pipeline
from ..stages import matching, perspective
from ..stages.road_model import fit_road
from ..survey.drive import survey
from .rig_matrix import RIG_CLASS_BY_NAME, RIG_CLASSES, sample_scene
from .synthetic import render

# validation scenes: potholes with fewer visible pixels are "don't care"
MIN_SCORED_PIXELS = 100
# validation drives: a pothole is to be found when seen (as above) in this many frames
MIN_DRIVE_SIGHTINGS = 3

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
    scene: Path | None = None
    group: str = ""

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
    """Every evaluable pair under ``root`` (fan_potholes frames, validation scenes: a folder of
    left.png, right.png, labels_gt.png, camera_info.yaml and meta.json; KITTI, Middlebury)."""
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
    for meta in sorted(root.rglob("meta.json")):
        folder = meta.parent
        if all((folder / name).is_file() for name in ("left.png", "right.png", "labels_gt.png",
                                                      "camera_info.yaml")):
            samples.append(Sample(f"{folder.parent.name}/{folder.name}", folder / "left.png",
                                  folder / "right.png", 0.0, 0.0, scene=folder,
                                  group=folder.parent.name))
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
    scene_tallies: dict[str, "RigTally"] = field(default_factory=dict)
    drive_rows: list[dict] = field(default_factory=list)
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
        if self.scene_tallies:
            lines += ["## Validation scenes (pixels over the whole frame; potholes at IoU 0.3, "
                      f"those under {MIN_SCORED_PIXELS} visible pixels not counted either way; "
                      "false potholes per frame)", "",
                      validation_markdown(self.scene_tallies)]
        if self.drive_rows:
            lines += ["## Validation drives (the survey's entries against the potholes seen "
                      f"with at least {MIN_SCORED_PIXELS} px in at least {MIN_DRIVE_SIGHTINGS} "
                      "frames; an entry within half a pothole's largest extent of its centre "
                      "is its)", "",
                      "| drive | frames | failed | entries | potholes seen | found | "
                      "duplicates | false | position error median / max m |",
                      "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
            for row in self.drive_rows:
                lines.append(
                    f"| {row['name']} | {row['frames']} | {row['failed']} | {row['entries']} "
                    f"| {row['seen']} | {row['found']} | {row['duplicates']} | {row['false']} "
                    f"| {row['error_median_m']:.2f} / {row['error_max_m']:.2f} |")
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


def progress(items: Iterable, stream: TextIO = sys.stderr, label: str = "evaluate",
             total: int | None = None) -> Iterator:
    """Yield ``items`` (``total`` of them: by default their len) while drawing a one-line
    progress bar on ``stream``."""
    count = len(items) if total is None else total  # type: ignore[arg-type]
    start = time.perf_counter()
    for index, item in enumerate(items):
        draw_progress(index, count, start, label, stream)
        yield item
    draw_progress(count, count, start, label, stream)


def evaluate(root: str | Path, config: Config, backend: Backend,
             stream: TextIO = sys.stderr) -> EvaluationReport:
    """Run detection (pothole sets) or matching (disparity sets) on every pair under ``root``."""
    samples = discover(root)
    drives = sorted(path.parent for path in Path(root).rglob("sequence.json")
                    if (path.parent / "metadata.yaml").is_file())
    if not samples and not drives:
        raise InputError(f"no evaluable pairs under {root}: expected left.png/right.png/"
                         "pothole_mask.png folders, validation scenes or drives, KITTI or "
                         "Middlebury layouts")
    report = EvaluationReport()
    for drive in drives:
        try:
            report.drive_rows.append(score_drive(drive, config))
        except PotholeError as error:
            report.errors.append(f"{drive.name}: {error}")
    for sample in progress(samples, stream):
        try:
            if sample.scene is not None:
                _evaluate_scene(sample, config, backend, report)
            elif sample.pothole_mask is not None:
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


def _evaluate_scene(sample: Sample, config: Config, backend: Backend,
                    report: EvaluationReport) -> None:
    """One validation scene: its pair through the pipeline with the calibration of its
    camera_info.yaml, scored into its group's tally (:func:`score_scene`)."""
    assert sample.scene is not None
    info = yaml.safe_load((sample.scene / "camera_info.yaml").read_text())
    meta = json.loads((sample.scene / "meta.json").read_text())
    calibration = StereoCalibration.from_projections(info["left"]["P"], info["right"]["P"])
    truth = cv2.imread(str(sample.scene / "labels_gt.png"), cv2.IMREAD_UNCHANGED)
    tally = report.scene_tallies.setdefault(sample.group, RigTally())
    try:
        result = Pipeline(config, calibration, backend).run(read_image(sample.left),
                                                            read_image(sample.right))
    except PotholeError:
        tally.failed += 1
        raise
    score_scene(tally, result, truth.astype(np.int64), meta)


def score_scene(tally: "RigTally", result: Any, truth: np.ndarray, meta: dict) -> None:
    """Score a result against a validation scene's instance labels (HxW, k = pothole ``id``
    k of ``meta["potholes"]``) as we are judged: pixels over the whole frame; detections
    matched one to one to potholes at IoU >= 0.3, those of fewer than MIN_SCORED_PIXELS
    visible pixels "don't care" (a detection matched to one counts neither way); recall
    also of the potholes whose centre lies in the observed range (m ahead along the road:
    world y from the left camera's); relative errors of largest depth, area and volume of
    the matched ones (area also of those the frame's edge does not cut: the truth's area is
    the whole pothole's); reports that no road can give (not finite, not positive, deeper than
    max_pothole_depth_m)."""
    labels = result.host("labels")
    tally.scenes += 1
    tally.pixels_all.add(labels > 0, truth > 0, np.ones(truth.shape, dtype=bool))
    tally.pixels_observed.add(labels > 0, truth > 0, result.host("observed"))
    visible = np.bincount(truth.ravel(), minlength=len(meta["potholes"]) + 1)
    scored = {p["id"]: p for p in meta["potholes"]
              if p["id"] < len(visible) and visible[p["id"]] >= MIN_SCORED_PIXELS}
    pairs = match_potholes(labels, truth)
    ignored = {d for d, t in pairs if t not in scored}
    pairs = [(d, t) for d, t in pairs if t in scored]
    matched = {t for _, t in pairs}
    near, far = result.observed_range_m
    camera_y = float(meta["C_left_world"][1])
    for pothole_id, pothole in scored.items():
        tally.truths_all += 1
        if near <= pothole["centroid_world_m"][1] - camera_y <= far:
            tally.truths_observed += 1
            tally.matched_observed += pothole_id in matched
    detections = [p for p in result.potholes if p.label not in ignored]
    tally.detections += len(detections)
    tally.matched += len(pairs)
    tally.false_on_clean += len(detections) - len(pairs)
    by_label = {p.label: p for p in result.potholes}
    edge = np.zeros(truth.shape, dtype=bool)
    edge[[0, -1], :] = edge[:, [0, -1]] = True
    cut = set(np.unique(truth[edge]).tolist())
    for d, t in pairs:
        found, truth_pothole = by_label.get(d), scored[t]
        if found is None:
            continue
        for errors, ours, theirs in ((tally.depth_errors, found.max_depth_m, "max_depth_m"),
                                     (tally.area_errors, found.area_m2, "area_m2"),
                                     (tally.volume_errors, found.volume_m3, "volume_m3")):
            errors.append(abs(ours - truth_pothole[theirs]) / truth_pothole[theirs])
        if t not in cut:
            tally.whole_area_errors.append(tally.area_errors[-1])
    for found in result.potholes:
        numbers = (found.area_m2, found.max_depth_m, found.mean_depth_m, found.volume_m3)
        tally.bad_reports += not all(math.isfinite(x) and x > 0 for x in numbers)


def score_drive(folder: Path, config: Config) -> dict:
    """Survey a validation drive (its bag in ``folder``) and score the entries against its
    potholes (per frame ``NNNNNN/meta.json``): those seen with at least MIN_SCORED_PIXELS px in
    at least MIN_DRIVE_SIGHTINGS frames are to be found; an entry within half a pothole's
    largest extent of its centre (on the road) is its (any pothole's), a second one a
    duplicate, one in none false. The survey's motion
    frame (the first frame's road frame: x forward, y left) is put into the world by the first
    frame's camera pose. Position error: each found pothole's nearest entry, m."""
    sequence = json.loads((folder / "sequence.json").read_text())
    seen: dict[int, int] = {}
    truth_xy: dict[int, np.ndarray] = {}
    radius: dict[int, float] = {}
    for frame in sequence["frames"]:
        meta = json.loads((folder / frame["dir"] / "meta.json").read_text())
        for pothole in meta["potholes"]:
            truth_xy[pothole["id"]] = np.asarray(pothole["centroid_world_m"][:2], dtype=float)
            radius[pothole["id"]] = float(pothole["max_extent_m"]) / 2
            if pothole["pixels"] >= MIN_SCORED_PIXELS:
                seen[pothole["id"]] = seen.get(pothole["id"], 0) + 1
    first = json.loads((folder / sequence["frames"][0]["dir"] / "meta.json").read_text())
    optical_axis = np.asarray(first["R_world_from_cam"], dtype=float)[:, 2]
    forward = optical_axis[:2] / np.linalg.norm(optical_axis[:2])
    left = np.array([-forward[1], forward[0]])
    origin = np.asarray(first["C_left_world"][:2], dtype=float)
    (drive,) = survey([folder], config)
    entries = [origin + p.row["odom_x_m"] * forward + p.row["odom_y_m"] * left
               for p in drive.potholes]
    wanted = [pothole_id for pothole_id, count in seen.items()
              if count >= MIN_DRIVE_SIGHTINGS]
    claimed: dict[int, list[float]] = {}
    false = 0
    for position in entries:
        distances = {pothole_id: float(np.linalg.norm(position - xy))
                     for pothole_id, xy in truth_xy.items()
                     if np.linalg.norm(position - xy) <= radius[pothole_id]}
        if not distances:
            false += 1
            continue
        nearest = min(distances, key=distances.__getitem__)
        claimed.setdefault(nearest, []).append(distances[nearest])
    found = [pothole_id for pothole_id in wanted if pothole_id in claimed]
    errors = [min(claimed[pothole_id]) for pothole_id in found]
    return {"name": folder.name, "frames": drive.frames, "failed": drive.failed,
            "entries": len(entries), "seen": len(wanted), "found": len(found),
            "duplicates": sum(len(claimed[pothole_id]) - 1 for pothole_id in claimed),
            "false": false,
            "error_median_m": float(np.median(errors)) if errors else math.nan,
            "error_max_m": float(max(errors)) if errors else math.nan}


def validation_markdown(tallies: dict[str, "RigTally"]) -> str:
    """The table of validation scenes per group (vehicle_1280x720, robot_640x480, ...), with a
    row of the groups pooled where there are several. False potholes: detections matched to
    no scored pothole (and to no "don't care" one), per frame."""
    lines = ["| group | scenes | pixel P / R / F | pothole P / R / F (all >= "
             f"{MIN_SCORED_PIXELS} px) | pothole R (observed range) | false per frame | "
             "depth / area / volume error median | area error median (in full view) | "
             "bad reports | failed |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    rows = dict(tallies)
    if len(rows) > 1:
        rows["**all**"] = pooled(tallies.values())

    def median(values: list[float]) -> str:
        return f"{100 * float(np.median(values)):.0f} %" if values else "-"

    for name, t in rows.items():
        every = t.pixels_all
        p, r, f = t.pothole_scores(False)
        _, r_observed, _ = t.pothole_scores(True)
        lines.append(
            f"| {name} | {t.scenes} | {every.precision:.2f} / {every.recall:.2f} / "
            f"{every.f_score:.2f} | {p:.2f} / {r:.2f} / {f:.2f} | {r_observed:.2f} | "
            f"{t.false_on_clean / max(t.scenes, 1):.2f} | {median(t.depth_errors)} / "
            f"{median(t.area_errors)} / {median(t.volume_errors)} | "
            f"{median(t.whole_area_errors)} ({len(t.whole_area_errors)} of "
            f"{len(t.area_errors)}) | {t.bad_reports} | {t.failed} |")
    return "\n".join(lines) + "\n"


def _evaluate_disparity(sample: Sample, config: Config, backend: Backend,
                        report: EvaluationReport) -> None:
    """The configured matcher on the GPT band (our pipeline) and over the full range of the
    ground truth without GPT, with the same settings."""
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
    gray_left = backend.upload(matching.to_gray8(left))
    gray_right = backend.upload(matching.to_gray8(right))
    shifts = backend.upload(perspective.no_shifts(left.shape[0]))
    start = time.perf_counter()
    plain = backend.to_host(matching.Matcher(backend)(gray_left, gray_right, shifts,
                                                      levels_full, full_config))
    plain_ms = (time.perf_counter() - start) * 1e3
    ours = backend.to_host(ours)
    road = road_region(truth)
    for matcher, estimate, n_levels, ms in ((f"{config.matcher}, GPT band", ours, levels, ours_ms),
                                            (f"{config.matcher}, full range", plain, levels_full,
                                             plain_ms)):
        for region_name, region in (("road", road), ("all", None)):
            errors = disparity_errors(estimate, truth, region)
            report.disparity_rows.append({"name": sample.name, "matcher": matcher,
                                          "region": region_name, "levels": n_levels, "ms": ms,
                                          **errors})


@dataclass
class RigTally:
    """Per rig class: pixel and pothole counts (inside the observed range and overall), roll
    errors, relative measurement errors of matched potholes, and what went wrong."""

    scenes: int = 0
    pixels_observed: PixelCounts = field(default_factory=PixelCounts)
    pixels_all: PixelCounts = field(default_factory=PixelCounts)
    detections: int = 0
    matched: int = 0
    truths_observed: int = 0
    matched_observed: int = 0
    truths_all: int = 0
    clean_scenes: int = 0
    false_on_clean: int = 0
    roll_errors_deg: list[float] = field(default_factory=list)
    depth_errors: list[float] = field(default_factory=list)
    area_errors: list[float] = field(default_factory=list)
    whole_area_errors: list[float] = field(default_factory=list)
    volume_errors: list[float] = field(default_factory=list)
    bad_reports: int = 0
    failed: int = 0

    def pothole_scores(self, observed: bool) -> tuple[float, float, float]:
        """Pothole precision, recall and F at IoU 0.3 (recall of the potholes inside the
        observed range, or of all)."""
        truths, hits = ((self.truths_observed, self.matched_observed) if observed
                        else (self.truths_all, self.matched))
        precision = self.matched / self.detections if self.detections else 1.0
        recall = hits / truths if truths else 1.0
        total = precision + recall
        return precision, recall, 2 * precision * recall / total if total else 0.0


def pooled(tallies: Iterable[RigTally]) -> RigTally:
    """One tally of several rig classes: counts summed, errors together."""
    total = RigTally()
    for tally in tallies:
        for item in fields(RigTally):
            mine, theirs = getattr(total, item.name), getattr(tally, item.name)
            if isinstance(mine, PixelCounts):
                for count in ("tp", "fp", "fn", "tn"):
                    setattr(mine, count, getattr(mine, count) + getattr(theirs, count))
            elif isinstance(mine, list):
                mine.extend(theirs)
            else:
                setattr(total, item.name, mine + theirs)
    return total


def truth_roll_deg(sample: Any) -> float:
    """The road model's roll (deg, RoadModel convention) of a rendered scene's flat road: from
    the world's up axis in the left optical frame."""
    up = sample.camera_from_world @ np.array([0.0, 0.0, 1.0])
    return float(np.degrees(np.arctan2(up[0], -up[1])))


def match_potholes(labels: np.ndarray, truth: np.ndarray, min_iou: float = 0.3
                   ) -> list[tuple[int, int]]:
    """One-to-one (detection label, truth label) pairs whose pixel IoU is at least
    ``min_iou``, best first. ``labels`` and ``truth``: integer HxW, 0 = none."""
    both = (labels > 0) & (truth > 0)
    pairs, overlap = np.unique(np.stack([labels[both], truth[both]]), axis=1,
                               return_counts=True)
    detected = np.bincount(labels.ravel())
    true = np.bincount(truth.ravel())
    scored = sorted(((count / (detected[d] + true[t] - count), int(d), int(t))
                     for (d, t), count in zip(pairs.T, overlap)), reverse=True)
    used_d: set[int] = set()
    used_t: set[int] = set()
    found = []
    for iou, d, t in scored:
        if iou >= min_iou and d not in used_d and t not in used_t:
            used_d.add(d)
            used_t.add(t)
            found.append((d, t))
    return found


def _along_road_m(sample: Any, shape: Any) -> float:
    """Distance (m) along the road from the point below the camera to a pothole's centre."""
    return float(shape.y_m - sample.camera_origin_world[1])


def _score_scene(tally: RigTally, sample: Any, result: Any) -> None:
    labels = result.host("labels")
    truth = sample.labels.astype(np.int64)
    observed = result.host("observed")
    predicted, is_pothole = labels > 0, truth > 0
    everywhere = np.ones_like(predicted)
    tally.pixels_all.add(predicted, is_pothole, everywhere)
    tally.pixels_observed.add(predicted, is_pothole, observed)
    near, far = result.observed_range_m
    pairs = match_potholes(labels, truth)
    matched_truths = {t for _, t in pairs}
    for index, shape in enumerate(sample.potholes, start=1):
        if not np.any(truth == index):
            continue
        tally.truths_all += 1
        if near <= _along_road_m(sample, shape) <= far:
            tally.truths_observed += 1
            tally.matched_observed += index in matched_truths
    tally.detections += len(result.potholes)
    tally.matched += len(pairs)
    by_label = {p.label: p for p in result.potholes}
    for d, t in pairs:
        found, shape = by_label.get(d), sample.potholes[t - 1]
        if found is None:
            continue
        tally.depth_errors.append(abs(found.max_depth_m - shape.depth_m) / shape.depth_m)
        tally.area_errors.append(abs(found.area_m2 - shape.area_m2) / shape.area_m2)
        tally.volume_errors.append(abs(found.volume_m3 - shape.volume_m3) / shape.volume_m3)
    for found in result.potholes:
        numbers = (found.area_m2, found.max_depth_m, found.mean_depth_m, found.volume_m3)
        tally.bad_reports += not all(math.isfinite(x) and x > 0 for x in numbers)


def _rendered(scene: Any, cache: Path | None) -> Any:
    """The scene rendered, from ``cache`` (a folder of .pkl files keyed by the scene) when
    it holds it."""
    if cache is None:
        return render(scene)
    key = f"{type(scene).__module__}.{scene!r}"
    path = cache / f"{hashlib.sha1(key.encode()).hexdigest()[:16]}.pkl"
    if path.is_file():
        return pickle.loads(path.read_bytes())
    sample = render(scene)
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(sample))
    return sample


def evaluate_synthetic(config: Config, backend: Backend, classes: Iterable[str] | None = None,
                       scenes: int = 3, clean_scenes: int = 1, seed: int = 0,
                       cache: str | Path | None = None, stream: TextIO = sys.stderr,
                       jobs: int = 1) -> dict[str, RigTally]:
    """Render ``scenes`` scenes with potholes and distractors and ``clean_scenes`` scenes with
    distractors only per rig class (rig_matrix.RIG_CLASSES, or those named), run the pipeline
    on each (a fresh pipeline per scene, so each is seeded) and tally them per class. With
    ``jobs`` > 1 the scenes are rendered ahead in that many worker processes."""

    rigs = [RIG_CLASS_BY_NAME[name] for name in classes] if classes else list(RIG_CLASSES)
    jobs_list = [(rig, index, index >= scenes) for rig in rigs
                 for index in range(scenes + clean_scenes)]
    tallies = {rig.name: RigTally() for rig in rigs}
    cache_dir = Path(cache) if cache else None
    drawn = [sample_scene(rig, index, potholes=0 if clean else 3,
                          distractors=6 if clean else 4, seed=seed)
             for rig, index, clean in jobs_list]
    samples = _render_all(drawn, cache_dir, jobs)
    for (rig, _, clean), sample in progress(zip(jobs_list, samples), stream,
                                            "evaluate --synthetic", len(jobs_list)):
        tally = tallies[rig.name]
        try:
            result = Pipeline(config, sample.calibration, backend).run(sample.left,
                                                                       sample.right)
        except PotholeError:
            tally.failed += 1
            continue
        tally.roll_errors_deg.append(abs(result.road.roll_deg - truth_roll_deg(sample)))
        if clean:
            tally.clean_scenes += 1
            tally.false_on_clean += len(result.potholes)
        else:
            tally.scenes += 1
            _score_scene(tally, sample, result)
    return tallies


def _render_all(scenes: list, cache: Path | None, jobs: int) -> Iterator[Any]:
    """The rendered ``scenes`` in order (through ``cache``); with ``jobs`` > 1 rendered in
    that many worker processes, at most 2 ``jobs`` ahead of the one asked for."""
    if jobs <= 1:
        yield from (_rendered(scene, cache) for scene in scenes)
        return

    # started afresh, not forked: a fork of a process whose matcher's threads ran is unsafe
    with ProcessPoolExecutor(jobs, mp_context=get_context("spawn")) as pool:
        waiting: deque = deque()
        for scene in scenes:
            waiting.append(pool.submit(_rendered, scene, cache))
            if len(waiting) > 2 * jobs:
                yield waiting.popleft().result()
        while waiting:
            yield waiting.popleft().result()


def synthetic_markdown(tallies: dict[str, RigTally]) -> str:
    """The per-class table of :func:`evaluate_synthetic`, with a row of all classes pooled
    where there are several."""
    lines = ["| rig class | scenes | pixel P / R / F (observed) | pixel F (all) | "
             "pothole P / R / F (observed) | pothole R / F (all) | false on clean roads | "
             "roll error median (deg) | depth / area / volume error median | bad reports | "
             "failed |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    rows = dict(tallies)
    if len(rows) > 1:
        rows["**all**"] = pooled(tallies.values())
    for name, t in rows.items():
        obs, every = t.pixels_observed, t.pixels_all
        p, r, f = t.pothole_scores(True)
        _, r_all, f_all = t.pothole_scores(False)

        def median(values: list[float]) -> str:
            return f"{100 * float(np.median(values)):.0f} %" if values else "-"

        roll = f"{float(np.median(t.roll_errors_deg)):.2f}" if t.roll_errors_deg else "-"
        lines.append(
            f"| {name} | {t.scenes} + {t.clean_scenes} clean | {obs.precision:.2f} / "
            f"{obs.recall:.2f} / {obs.f_score:.2f} | {every.f_score:.2f} | {p:.2f} / {r:.2f} /"
            f" {f:.2f} | {r_all:.2f} / {f_all:.2f} | {t.false_on_clean} | {roll} | "
            f"{median(t.depth_errors)} / {median(t.area_errors)} / {median(t.volume_errors)} "
            f"| {t.bad_reports} | {t.failed} |")
    return "\n".join(lines) + "\n"
