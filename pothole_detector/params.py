"""The one parameter table: ROS parameter descriptors, config/*.yaml and the CLI come from it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import yaml

from .errors import ConfigError

NODE_NAME = "pothole_detector"


@dataclass(frozen=True)
class Param:
    """One parameter: name, Python type, default, inclusive range or choices, description."""

    name: str
    type: type
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    group: str = "pipeline"

    def validate(self, value: Any) -> Any:
        """Return ``value`` converted to this parameter's type, or raise ConfigError."""
        if self.type is bool:
            if not isinstance(value, bool):
                raise ConfigError(f"{self.name} must be true or false, got {value!r}")
            return value
        if self.type is int:
            if isinstance(value, bool) or not isinstance(value, int):
                if isinstance(value, float) and value.is_integer():
                    value = int(value)
                else:
                    raise ConfigError(f"{self.name} must be an integer, got {value!r}")
        elif self.type is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{self.name} must be a number, got {value!r}")
            value = float(value)
            if value != value:
                raise ConfigError(f"{self.name} must be a number, got NaN")
        elif self.type is str:
            if not isinstance(value, str):
                raise ConfigError(f"{self.name} must be a string, got {value!r}")
            if self.choices is not None and value not in self.choices:
                raise ConfigError(
                    f"{self.name} must be one of {', '.join(self.choices)}, got {value!r}"
                )
            return value
        if self.low is not None and value < self.low:
            raise ConfigError(f"{self.name} must be >= {self.low}, got {value}")
        if self.high is not None and value > self.high:
            raise ConfigError(f"{self.name} must be <= {self.high}, got {value}")
        return value


PARAMETERS: tuple[Param, ...] = (
    # seed pass and perspective transformation
    Param("max_disparity_px", int, 384,
          "Largest disparity (px, full resolution) searched by the coarse seed pass and by "
          "matching when GPT is off.", 16, 2048),
    Param("coarse_scale", int, 4,
          "Downscale factor of the coarse full-range pass that seeds the road model; 0: from "
          "the image width (the seed then works on about 512 columns).", 0, 8),
    Param("gpt_enabled", bool, True,
          "Match the perspective-transformed pair in a narrow band (true) or the raw pair over "
          "the full range (false)."),
    Param("gpt_shift", str, "auto",
          "How GPT shifts the right image: pixel (each column by the road's disparity there less "
          "delta_PT, so the band need not hold the road's slope across a row that the roll "
          "makes: 64 levels instead of 80-96 on the real frames), row (each row by its lowest "
          "road disparity less delta_PT, the paper), or auto (pixel with the census matcher, "
          "row with OpenCV SGBM).",
          choices=("auto", "pixel", "row")),
    Param("gpt_margin_below_px", float, 40.0,
          "delta_PT: band margin below the road (px); bounds the deepest pothole seen.", 0, 512),
    Param("gpt_margin_above_px", float, 16.0,
          "Band margin above the road (px), for bumps and noise.",
          0, 512),
    # matching
    Param("matcher", str, "census",
          "Stereo matcher: census (our census SGM: CUDA kernels on the GPU, Numba kernels on "
          "the CPU, the same disparities on both) or opencv (OpenCV SGBM, on the host).",
          choices=("census", "opencv")),
    Param("census_p1", int, 3, "Census SGM penalty for |dd| = 1 (census bits: 0 .. 31); low "
          "penalties keep pothole rims sharp.", 0, 95),
    Param("census_p2", int, 20, "Census SGM penalty for |dd| > 1 (> census_p1).", 1, 96),
    Param("sgm_block_size", int, 5, "Matching block size (px, odd).", 1, 11),
    Param("sgm_p1", int, 8, "SGM penalty for |dd| = 1, per block pixel (OpenCV: x block area).",
          0, 1000),
    Param("sgm_p2", int, 32, "SGM penalty for |dd| > 1, per block pixel (> sgm_p1).", 1, 4000),
    Param("sgm_mode", str, "3way", "OpenCV SGBM path mode on the CPU: 3way, sgbm (5 paths) or "
          "hh (8 paths, more memory).", choices=("3way", "sgbm", "hh")),
    Param("sgm_uniqueness_percent", int, 5,
          "Winner must beat the runner-up cost by this margin (%), else invalid.", 0, 100),
    Param("lr_max_diff_px", int, 1,
          "Left-right consistency tolerance (px); -1 turns the check off.", -1, 64),
    Param("speckle_window_px", int, 100,
          "Blobs of at most this many pixels that differ from their surround are removed "
          "(0 = off).", 0, 10000),
    Param("speckle_range_px", int, 2, "Disparity variation (px) allowed inside one blob.", 0, 64),
    Param("median_filter", bool, True, "3x3 median on the disparity map after matching."),
    Param("max_camera_height_m", float, 10.0,
          "The seed pass takes no plane for the road that puts the camera higher above it "
          "than this (m): walls, far trees and sky are not the road.", 0.1, 1000),
    Param("min_valid_fraction", float, 0.05,
          "Fewer valid disparities than this fraction of the image means no texture, and "
          "a road plane holding less of the seed pass's pixels is scattered matches, not a "
          "road: errors.", 0, 1),
    # road model and disparity transformation
    Param("road_model", str, "auto",
          "planar (paper), quadratic in the rotated row, or auto (quadratic only where it "
          "lowers the inlier residual by road_quadratic_gain).",
          choices=("auto", "planar", "quadratic")),
    Param("road_quadratic_gain", float, 0.05,
          "Relative residual drop that auto needs to pick the quadratic model.", 0, 1),
    Param("road_fit_stride", int, 4, "Fit the road on every n-th pixel in each axis.", 1, 16),
    Param("road_fit_rounds", int, 3, "Robust refit rounds after the first fit.", 0, 10),
    Param("road_outlier_k", float, 2.5,
          "Pixels whose residual exceeds k robust sigmas are dropped before the next round.",
          0.5, 20),
    Param("road_prior_change_deg", float, 1.0,
          "How far the camera may turn about its x axis between frames (deg): a frame's road "
          "fit takes the pixels within the disparity such a turn moves the road (at least 2 "
          "px) of the previous frame's road, so cars, walls and trees do not tilt it; 0 takes "
          "every valid pixel.", 0, 45),
    Param("min_road_inlier_fraction", float, 0.2,
          "Below this fraction of valid pixels on the road, report no road and no potholes.",
          0, 1),
    Param("delta_dt_px", float, 32.0, "delta_DT: value of the road in the transformed map (px).",
          0, 1024),
    # superpixels
    Param("slic_region_size_px", int, 0,
          "SLIC grid step S in full-resolution px (the SLIC image uses S / slic_downsample); "
          "0: the image width / 64 (32 px at 2079 px wide, 10 px at 640), so that superpixels "
          "take the same share of the view on any image size, shrunk where the optical axis "
          "meets the seeded road at less than 30 deg (in proportion to the sine, to at most "
          "half: rows foreshorten such a road), at least 8 px.", 0, 512),
    Param("slic_compactness", float, 2.0,
          "SLIC m: a spatial distance of S weighs like m px of transformed disparity.", 0.01, 100),
    Param("slic_iterations", int, 6, "Fixed number of SLIC k-means iterations.", 1, 50),
    Param("slic_downsample", int, 2,
          "SLIC runs on the transformed map reduced by this factor; labels are scaled back.",
          1, 8),
    # threshold and selection
    Param("histogram_bin_px", float, 0.25, "Bin width of the 2D histogram (px).", 0.01, 10),
    Param("threshold_reference", str, "auto",
          "What delta_PD is subtracted from: the road model's own level delta_DT (road_fit), "
          "the mean D2 of the histogram's road cluster (road_mean, the paper's text), the "
          "histogram split t_r itself (split), or auto (road_fit in metres mode, road_mean in "
          "pixels mode).", choices=("auto", "road_fit", "road_mean", "split")),
    Param("threshold_mode", str, "metres",
          "Pothole tolerance delta_PD as a depth below the road (metres: the same on any rig) "
          "or as a disparity drop in pixels (the paper's, which fits one rig only).",
          choices=("pixels", "metres")),
    Param("delta_pd_px", float, 2.36, "delta_PD in pixels (paper: 2.36).", 0, 100),
    Param("delta_pd_m", float, 0.004,
          "delta_PD as a depth below the road (m), converted per superpixel into the "
          "disparity drop of a point that deep.", 0, 1),
    Param("threshold_noise_sigmas", float, 3.0,
          "Metres mode: where the matcher cannot resolve delta_pd_m, the threshold is the "
          "depth whose disparity drop is this many sigmas of the road's disparity noise (with "
          "the local road reference, the spread of the road's superpixels about it around "
          "each superpixel; else the road fit's robust sigma).", 0, 20),
    Param("max_threshold_m", float, 0.03,
          "Metres mode: the road counts as observed (potholes are looked for) only where the "
          "threshold depth is at most this (m); the observed range in the outputs says where.",
          0, 10),
    Param("road_reference", str, "local",
          "What a superpixel's depth is measured from: the road around it (local: a robust "
          "plane fitted to the superpixels within local_road_radius_m on the road, potholes "
          "left out, that follows crowns, cross slopes and edges that fall away) or the one "
          "road model of the frame (global, the paper's).", choices=("local", "global")),
    Param("local_road_radius_m", float, 1.5,
          "Half the side of the window of the local road reference, along and across the "
          "road (m): larger than a pothole, smaller than the road's bends.", 0.1, 50),
    Param("photometric_factor", float, 3.0,
          "A component is no pothole where most of its superpixels disagree between the two "
          "views on the brightness of what was matched by more than this many times the "
          "road's mean disagreement in the frame (glossy or saturated markings, wet patches); "
          "0 turns the test off.", 0, 100),
    Param("bump_noise_sigmas", float, 4.0,
          "A component is no pothole where it touches a superpixel that stands above the road "
          "around it by more than this many of the road's local noise sigmas: a matcher that "
          "moved an edge (a lane marking's) reads one side as a dip and the other as a bump; "
          "0 turns the test off.", 0, 20),
    Param("texture_noise", bool, True,
          "With the local road reference, each superpixel's disparity noise is the road's "
          "around it times how much less texture it has than the road's typical superpixel "
          "(the ratio of their RMS horizontal image gradients, at least 1): a match is as "
          "precise as the image is textured along the rows, and the inside of a lane marking "
          "or a smooth, overexposed patch has little texture; false takes the road's noise "
          "as it is."),
    Param("superpixel_min_valid_fraction", float, 0.0,
          "A superpixel needs more than this fraction of valid disparities to be selectable "
          "(occluded pothole walls are often invalid: keep it low).", 0, 1),
    Param("refine_depth_fraction", float, 0.25,
          "Pixel-level refinement: pixels within half a superpixel of a pothole join it where "
          "their depth below the road (a 7x7 mean) exceeds this fraction of the threshold, so "
          "that rims are not cut at superpixel edges; 0 turns it off.", 0, 1),
    # components
    Param("corner_fraction", float, 0.1,
          "Potholes reaching into a far (top) corner square of this fraction of the short "
          "side are dropped, unless corner_significance keeps them.",
          0, 0.5),
    Param("corner_significance", float, 2.0,
          "A pothole reaching into a far corner is kept when more than half of its pixels "
          "lie on superpixels deeper below the road around them than this many times their "
          "threshold: the far corners are where the road model is extrapolated, so a pothole "
          "there needs this much more evidence than elsewhere; 0 drops every such pothole.",
          0, 100),
    Param("min_pothole_superpixels", int, 2, "Components of fewer superpixels are dropped.",
          1, 1000),
    Param("min_pothole_area_m2", float, 0.0005, "Components smaller on the road are dropped.",
          0, 100),
    Param("min_pothole_depth_m", float, 0.008,
          "Components whose mean depth below the road is less are dropped (shallow dips, "
          "noise).", 0, 1),
    Param("max_pothole_depth_m", float, 0.5,
          "Components whose mean depth below the road is more, or more than their width (the "
          "square root of their area), are dropped (mismatched disparities, not potholes).",
          0, 100),
    # device
    Param("cuda_graph", bool, True,
          "GPU backend: replay each frame's SGM and later stages as CUDA graphs per image "
          "size, level count and SLIC grid step (same results, two launches instead of about "
          "fifty); per-stage timings need it off. Not used for seed frames."),
    # input: how the recorded or live images come
    Param("rectify", str, "auto",
          "Rectify the images from camera_info before matching: auto (where camera_info says "
          "they are not rectified: distortion D not zero, R not the identity or K not P's), "
          "on, or off (take them as rectified). Results are in the rectified frame that the "
          "right P defines, as stereo_image_proc's.", choices=("auto", "on", "off"),
          group="input"),
    Param("image_transport", str, "raw",
          "Node: subscribe to sensor_msgs/Image on left/image_rect and right/image_rect (raw) "
          "or to sensor_msgs/CompressedImage on left/image_rect/compressed and "
          "right/image_rect/compressed (compressed: jpeg or png, as image_transport writes).",
          choices=("raw", "compressed"), group="input"),
    Param("baseline_m", float, 0.0,
          "Baseline (m) to use where the right camera_info has none (P[0,3] = 0); 0: take it "
          "from camera_info only.", 0.0, 10.0, group="input"),
    Param("focal_px", float, 0.0,
          "Focal length (px) to use where camera_info has none in K or P; 0: take it from "
          "camera_info only.", 0.0, 100000.0, group="input"),
    # node
    Param("backend", str, "auto", "Array backend: gpu (CuPy), cpu (NumPy), or auto (gpu when "
          "CuPy sees a device, else cpu).", choices=("auto", "cpu", "gpu"), group="node"),
    Param("use_odometry", bool, False,
          "Track potholes with the vehicle's motion from nav_msgs/Odometry on the relative "
          "topic odom (the planar pose of the road point below the camera); without it ids "
          "hold while a pothole moves less than track_match_distance_m between frames.",
          group="node"),
    Param("approximate_sync", bool, False,
          "Pair left and right images whose stamps differ by at most "
          "approximate_sync_tolerance_seconds (false: identical stamps only).", group="node"),
    Param("approximate_sync_tolerance_seconds", float, 0.01,
          "Largest stamp difference (s) of an approximately synchronized pair.", 0, 10,
          group="node"),
    Param("queue_size", int, 10, "Unpaired images kept per side while waiting for a partner.",
          1, 1000, group="node"),
    Param("max_waiting_sets", int, 3,
          "Synchronized stereo sets that may wait for the worker, so that sets delivered in a "
          "burst are all processed; when one more arrives the oldest waiting set is dropped, "
          "and while the worker is slower than the camera only the newest waiting set is "
          "kept (drops counted in dropped_sets). 1 always processes the newest set.",
          1, 100, group="node"),
    Param("qos_depth", int, 5,
          "QoS history depth of the inputs (sensor data: best effort) and outputs (reliable); "
          "per topic, the qos_overrides.<topic>.subscription|publisher.depth|history|"
          "reliability parameters override it and the rest at start-up.",
          1, 1000, group="node"),
    Param("diagnostics_period_seconds", float, 1.0, "Period of /diagnostics messages (s).",
          0.1, 60, group="node"),
    Param("input_timeout_seconds", float, 2.0,
          "/diagnostics warns when no stereo image arrived for this long (s).", 0.1, 3600,
          group="node"),
    Param("error_after_failed_frames", int, 5,
          "/diagnostics reports an error after this many failed frames in a row.", 1, 10000,
          group="node"),
    Param("log_throttle_seconds", float, 5.0,
          "The same input problem is logged at most once per this many seconds.", 0, 3600,
          group="node"),
    Param("severity_standard", str, "ltpp",
          "Survey: how severity is classed: by the largest depth alone (ltpp, the FHWA LTPP "
          "distress manual, with severity_moderate_depth_m and severity_high_depth_m) or by "
          "the largest depth and the average diameter on the road (astm_d6433, its pothole "
          "table).", choices=("ltpp", "astm_d6433"), group="survey"),
    Param("severity_moderate_depth_m", float, 0.025,
          "Survey: a pothole deeper than this (m, its largest depth) is of moderate severity "
          "(FHWA LTPP distress manual: 25 mm).", 0.001, 1.0, group="survey"),
    Param("severity_high_depth_m", float, 0.05,
          "Survey: a pothole deeper than this (m) is of high severity (FHWA LTPP: 50 mm).",
          0.001, 1.0, group="survey"),
    Param("report_tiles_url", str, "https://tile.openstreetmap.org/{z}/{x}/{y}.png",
          "Survey: the base map of report.html where the page is online (a tile URL "
          "template with {z}, {x}, {y}); offline the route's drawing stays.", group="survey"),
    Param("report_tiles_attribution", str, "&copy; OpenStreetMap contributors",
          "Survey: the attribution the base map's tiles require.", group="survey"),
    Param("gnss_window_m", float, 20.0,
          "Survey: GNSS corrects the odometry's drift over this much travel about each frame "
          "(m): long enough to average the fixes' noise, short enough that the odometry "
          "drifts little inside it (1 % of scale error drifts 0.1 m in 20 m).", 1, 100000,
          group="survey"),
    Param("map_cell_m", float, 0.02,
          "Survey and node: cell size (m) of the fused road elevation map, in which each "
          "frame's road is placed by the ego-motion and potholes are measured from all the "
          "views that saw them; 0 turns the map off (the survey's entries then come from "
          "the tracker alone).", 0, 1.0, group="survey"),
    Param("map_overview_cell_m", float, 0.10,
          "Survey: cell size (m) of the map of the whole road the survey writes (GeoTIFF or "
          "NumPy); the potholes' map (map_cell_m) keeps only the road around them.", 0.01, 10.0,
          group="survey"),
    Param("map_publish_rate_hz", float, 1.0,
          "Node: publish the local road map (map_cloud, map_potholes) at most this often "
          "while somebody subscribes to them; 0 never.", 0, 30, group="node"),
    Param("map_radius_m", float, 15.0,
          "Node: the live road map keeps, and publishes, the road within this distance of "
          "the camera (m); older road is forgotten.", 2, 500, group="node"),
    Param("track_match_distance_m", float, 0.25,
          "Survey: a sighting joins a tracked pothole whose position on the road (m, after "
          "ego-motion) is this close, or closer than the sum of their radii.", 0.01, 10.0,
          group="survey"),
    Param("track_forget_frames", int, 30,
          "Survey and node: a tracked pothole not seen for this many frames takes no more "
          "sightings (it left the view).", 1, 100000, group="survey"),
    Param("min_sightings", int, 2,
          "Survey: a tracked pothole is reported when it was seen in at least this many "
          "frames.", 1, 1000, group="survey"),
    Param("chunk_frames", int, 600,
          "Survey: stereo frames per task when a bag is split for parallel work (--ray).",
          2, 1000000, group="survey"),
    Param("read_threads", int, 4,
          "Survey: threads that read and decompress the bag ahead of the pipeline, each a "
          "slice of a few dozen frames at a time (where camera_info comes with every image); "
          "1 reads in the pipeline's thread.", 1, 64, group="survey"),
    Param("read_processes", int, -1,
          "Survey: worker processes that read, decompress and decode the bag ahead of the "
          "pipeline instead of the read threads (the pixels come back through shared memory), "
          "so that a GPU pipeline's process keeps its interpreter. 0: the read threads; -1: on "
          "the GPU backend one per 4 of the process's host cores (at most 4), on the CPU "
          "none.", -1, 64, group="survey"),
    Param("chunk_overlap_frames", int, 2,
          "Survey: frames that a chunk also processes before its start (two more, at the "
          "bag's mean frame rate), so that visual odometry runs on across chunk boundaries.",
          1, 100, group="survey"),
)

PARAMETER_BY_NAME: dict[str, Param] = {p.name: p for p in PARAMETERS}


class Config:
    """Validated parameter values, read as attributes (``config.sgm_p1``)."""

    __slots__ = ("_values",)

    def __init__(self, values: Mapping[str, Any] | None = None, group: str | None = None):
        table = [p for p in PARAMETERS if group is None or p.group == group]
        merged = {p.name: p.default for p in table}
        for name, value in (values or {}).items():
            if name not in merged:
                raise ConfigError(f"unknown parameter {name!r}; see config/{NODE_NAME}.yaml")
            merged[name] = PARAMETER_BY_NAME[name].validate(value)
        for low, high in (("sgm_p1", "sgm_p2"), ("census_p1", "census_p2"),
                          ("severity_moderate_depth_m", "severity_high_depth_m")):
            if high in merged and merged[high] <= merged[low]:
                raise ConfigError(f"{high} must be larger than {low}")
        object.__setattr__(self, "_values", merged)

    def __getattr__(self, name: str) -> Any:
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(name) from None

    def __reduce__(self) -> tuple[Any, tuple[dict[str, Any]]]:
        """Pickled as its values: a worker process gets the same Config."""
        return _config_of, (dict(self._values),)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("Config is immutable: use replace()")

    def replace(self, **changes: Any) -> "Config":
        """A copy with ``changes`` applied and validated."""
        return Config({**self._values, **changes})

    def as_dict(self) -> dict[str, Any]:
        return dict(self._values)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Config) and other._values == self._values

    def __repr__(self) -> str:
        return f"Config({self._values!r})"


def _config_of(values: dict[str, Any]) -> Config:
    """The Config of values that were validated when it was first made (unpickling)."""
    config = object.__new__(Config)
    object.__setattr__(config, "_values", values)
    return config


def parameters(group: str | None = None) -> Iterable[Param]:
    """The table rows, optionally of one group (pipeline or node)."""
    return (p for p in PARAMETERS if group is None or p.group == group)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Parameter values from a ROS parameter file (``node: ros__parameters: {...}``) or a flat
    mapping. Raises ConfigError when the file is missing or malformed."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of parameter names")
    for value in data.values():
        if isinstance(value, dict) and "ros__parameters" in value:
            return dict(value["ros__parameters"] or {})
    if "ros__parameters" in data:
        return dict(data["ros__parameters"] or {})
    return data


def default_yaml() -> str:
    """The text of config/pothole_detector.yaml, generated from the table."""
    lines = [
        "# Generated from pothole_detector/params.py (python -m pothole_detector.params).",
        "# Every parameter with its default; ranges and meaning in the comments. The key /**",
        "# applies them to the node under any namespace and name.",
        "/**:",
        "  ros__parameters:",
    ]
    for param in PARAMETERS:
        if param.choices:
            allowed = "one of " + ", ".join(param.choices)
        elif param.type is bool:
            allowed = "true or false"
        else:
            allowed = f"{param.low} .. {param.high}"
        lines.append(f"    # {param.description} ({allowed})")
        lines.append(f"    {param.name}: {yaml.safe_dump(param.default).splitlines()[0]}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(default_yaml(), end="")
