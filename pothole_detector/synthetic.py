"""Synthetic stereo roads with potholes of known shape, for tests and sample bags.

A rectified rig at height h above a road, pitched down and rolled, looks at a road height field
with elliptic-paraboloid potholes. Both views are ray cast against the height field (the first
crossing along each ray, so pothole walls occlude what lies behind them), the road carries a
multi-scale value-noise texture fixed to the ground so that stereo matching works, and every
output comes with exact ground truth: disparity, pothole labels and per-pothole area, depth and
volume. World frame: X right, Y forward, Z up, road surface at Z = 0 outside potholes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .calibration import StereoCalibration


@dataclass(frozen=True)
class PotholeShape:
    """An elliptic paraboloid pothole: depth(r) = depth_m (1 - r^2) inside the ellipse of
    semi-axes (a, b) m centred at (x, y) m on the road, rotated by ``angle_deg``."""

    x_m: float
    y_m: float
    a_m: float
    b_m: float
    depth_m: float
    angle_deg: float = 0.0

    @property
    def area_m2(self) -> float:
        return math.pi * self.a_m * self.b_m

    @property
    def volume_m3(self) -> float:
        return self.area_m2 * self.depth_m / 2.0

    def depth_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Depth below the road surface (m, >= 0) at world points (x, y) m."""
        c, s = math.cos(math.radians(self.angle_deg)), math.sin(math.radians(self.angle_deg))
        dx, dy = x - self.x_m, y - self.y_m
        r2 = ((c * dx + s * dy) / self.a_m) ** 2 + ((-s * dx + c * dy) / self.b_m) ** 2
        return np.where(r2 < 1.0, self.depth_m * (1.0 - r2), 0.0)


@dataclass(frozen=True)
class Scene:
    """A rectified stereo rig over a road. Angles in degrees, lengths in metres, pixels px."""

    width: int = 640
    height: int = 360
    focal_px: float = 560.0
    baseline_m: float = 0.12
    camera_height_m: float = 1.0
    pitch_deg: float = 35.0
    roll_deg: float = 0.0
    camera_y_m: float = 0.0
    crown_per_m: float = 0.0
    potholes: tuple[PotholeShape, ...] = ()
    texture_seed: int = 7
    supersample: int = 2

    @property
    def calibration(self) -> StereoCalibration:
        return StereoCalibration.from_focal_baseline(self.focal_px, self.baseline_m,
                                                     self.width, self.height)


@dataclass
class StereoSample:
    """A rendered pair with ground truth. Images uint8 HxW; ``disparity`` float32 HxW px of the
    left view (NaN where no road is seen); ``labels`` uint16 HxW, k = pixels of pothole k."""

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray
    labels: np.ndarray
    calibration: StereoCalibration
    potholes: tuple[PotholeShape, ...]
    camera_from_world: np.ndarray = field(repr=False)
    camera_origin_world: np.ndarray = field(repr=False)

    def centroid_cam_m(self, index: int) -> np.ndarray:
        """Centroid (3,) of pothole ``index``'s surface in the left optical frame (m): the
        paraboloid's surface centroid lies at half its depth below the ellipse centre."""
        shape = self.potholes[index]
        world = np.array([shape.x_m, shape.y_m, -shape.depth_m / 2.0])
        return self.camera_from_world @ (world - self.camera_origin_world)


def _axes(scene: Scene) -> np.ndarray:
    """3x3 matrix whose columns are the optical x, y, z axes in world coordinates."""
    pitch, roll = math.radians(scene.pitch_deg), math.radians(scene.roll_deg)
    x = np.array([1.0, 0.0, 0.0])
    y = np.array([0.0, -math.sin(pitch), -math.cos(pitch)])
    z = np.array([0.0, math.cos(pitch), -math.sin(pitch)])
    c, s = math.cos(roll), math.sin(roll)
    return np.stack([c * x - s * y, s * x + c * y, z], axis=1)


def _surface_depth(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """How far the surface lies below Z = 0 at world (x, y): crown plus potholes (m)."""
    depth = scene.crown_per_m * x * x
    for shape in scene.potholes:
        depth = depth + shape.depth_at(x, y)
    return depth


def _cast(scene: Scene, origin: np.ndarray, directions: np.ndarray, steps: int = 48,
          refinements: int = 24) -> np.ndarray:
    """Ray parameter s (= optical depth, directions have optical z = 1) of the first surface
    crossing for each ray (N,); NaN for rays that never reach the road."""
    dz = directions[:, 2]
    s = np.full(directions.shape[0], np.nan)
    down = dz < -1e-9
    max_depth = sum(p.depth_m for p in scene.potholes) + scene.crown_per_m * 1e2
    s_near = -origin[2] / np.where(down, dz, -1.0)
    s_far = (origin[2] + max_depth) / np.where(down, -dz, 1.0)

    def gap(param: np.ndarray, rows: np.ndarray) -> np.ndarray:
        point = origin[None, :] + param[:, None] * directions[rows]
        return point[:, 2] + _surface_depth(scene, point[:, 0], point[:, 1])

    s[down] = s_near[down]
    rows = np.nonzero(down & _near_potholes(scene, origin, directions, s_near, s_far))[0]
    if rows.size == 0:
        return s
    near, far = s_near[rows], s_far[rows]
    low, high = near.copy(), np.full(rows.size, np.nan)
    for k in range(1, steps + 1):
        param = near + (far - near) * (k / steps)
        open_rays = np.isnan(high)
        hit = open_rays & (gap(param, rows) <= 0)
        high[hit] = param[hit]
        low[open_rays & ~hit] = param[open_rays & ~hit]
    crossed = ~np.isnan(high)
    low_c, high_c, rows_c = low[crossed], high[crossed], rows[crossed]
    for _ in range(refinements):
        middle = 0.5 * (low_c + high_c)
        below = gap(middle, rows_c) <= 0
        high_c = np.where(below, middle, high_c)
        low_c = np.where(below, low_c, middle)
    s[rows_c] = 0.5 * (low_c + high_c)
    return s


def _near_potholes(scene: Scene, origin: np.ndarray, directions: np.ndarray,
                   s_near: np.ndarray, s_far: np.ndarray) -> np.ndarray:
    """Rays whose ground track between s_near and s_far passes within a pothole's bounding
    circle (or any ray when the road has a crown)."""
    if scene.crown_per_m != 0.0:
        return np.ones(directions.shape[0], dtype=bool)
    start = origin[None, :2] + s_near[:, None] * directions[:, :2]
    track = (s_far - s_near)[:, None] * directions[:, :2]
    length2 = np.maximum((track ** 2).sum(axis=1), 1e-18)
    near = np.zeros(directions.shape[0], dtype=bool)
    for shape in scene.potholes:
        centre = np.array([shape.x_m, shape.y_m])
        along = np.clip(((centre - start) * track).sum(axis=1) / length2, 0.0, 1.0)
        closest = start + along[:, None] * track
        near |= ((closest - centre) ** 2).sum(axis=1) <= max(shape.a_m, shape.b_m) ** 2 * 1.01
    return near


def _texture(seed: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Multi-scale value noise fixed to the ground (world x, y in m); values in [0, 1]."""
    rng = np.random.default_rng(seed)
    total = np.zeros_like(x)
    weight_sum = 0.0
    for spacing, weight in ((0.004, 0.45), (0.012, 0.3), (0.04, 0.15), (0.15, 0.1)):
        lattice = rng.random((512, 512))
        gx, gy = x / spacing, y / spacing
        ix, iy = np.floor(gx), np.floor(gy)
        fx, fy = gx - ix, gy - iy
        fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
        i0, j0 = ix.astype(np.int64) % 512, iy.astype(np.int64) % 512
        i1, j1 = (i0 + 1) % 512, (j0 + 1) % 512
        value = (lattice[i0, j0] * (1 - fx) * (1 - fy) + lattice[i1, j0] * fx * (1 - fy)
                 + lattice[i0, j1] * (1 - fx) * fy + lattice[i1, j1] * fx * fy)
        total += weight * value
        weight_sum += weight
    return total / weight_sum


def _render_view(scene: Scene, axes: np.ndarray, origin: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image (uint8 HxW), optical depth at pixel centres (HxW, NaN = no road) and world
    points at pixel centres (HxWx3) of one camera."""
    k = scene.supersample
    f, cx, cy = scene.focal_px, (scene.width - 1) / 2.0, (scene.height - 1) / 2.0
    offsets = (np.arange(k) + 0.5) / k - 0.5
    u = (np.arange(scene.width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(scene.height)[:, None] + offsets[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([(uu - cx) / f, (vv - cy) / f, np.ones_like(uu)], axis=-1).reshape(-1, 3)
    directions = rays @ axes.T
    s = _cast(scene, origin, directions)
    points = origin[None, :] + s[:, None] * directions
    hit = np.isfinite(s)
    shade = np.full(s.shape, 0.5)
    texture = _texture(scene.texture_seed, points[hit, 0], points[hit, 1])
    inside = _surface_depth(scene, points[hit, 0], points[hit, 1]) > 1e-6
    shade[hit] = np.where(inside, 0.25 + 0.5 * texture, 0.15 + 0.8 * texture)
    image = shade.reshape(scene.height, k, scene.width, k).mean(axis=(1, 3))
    image8 = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)

    centre_rays = np.stack(np.meshgrid((np.arange(scene.width) - cx) / f,
                                       (np.arange(scene.height) - cy) / f), axis=-1)
    centre_rays = np.concatenate([centre_rays, np.ones(centre_rays.shape[:2] + (1,))], axis=-1)
    centre_dirs = centre_rays.reshape(-1, 3) @ axes.T
    depth = _cast(scene, origin, centre_dirs)
    world = origin[None, :] + depth[:, None] * centre_dirs
    shape = (scene.height, scene.width)
    return image8, depth.reshape(shape), world.reshape(shape + (3,))


def render(scene: Scene) -> StereoSample:
    """Ray cast both views of ``scene``; exact disparity f B / Z and labels for the left."""
    axes = _axes(scene)
    left_origin = np.array([0.0, scene.camera_y_m, scene.camera_height_m])
    right_origin = left_origin + scene.baseline_m * axes[:, 0]
    left, depth, world = _render_view(scene, axes, left_origin)
    right, _, _ = _render_view(scene, axes, right_origin)
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = (scene.focal_px * scene.baseline_m / depth).astype(np.float32)
    labels = np.zeros(depth.shape, dtype=np.uint16)
    finite = np.isfinite(depth)
    for index, shape in enumerate(scene.potholes, start=1):
        inside = finite & (shape.depth_at(world[..., 0], world[..., 1]) > 0)
        labels[inside] = index
    return StereoSample(left, right, disparity, labels, scene.calibration, scene.potholes,
                        camera_from_world=axes.T, camera_origin_world=left_origin)


def demo_scene(width: int = 640, height: int = 360, roll_deg: float = 1.5,
               camera_y_m: float = 0.0, seed: int = 7) -> Scene:
    """A rig like the real pothole data's (0.6 m above the road, pitched 55 deg down, focal
    length 0.67 x width, 0.12 m baseline) over three potholes 5-6 cm deep; the view is the
    same at any image size."""
    return Scene(
        width=width, height=height, focal_px=0.67 * width, camera_height_m=0.6,
        pitch_deg=55.0, roll_deg=roll_deg, camera_y_m=camera_y_m, texture_seed=seed,
        potholes=(
            PotholeShape(-0.20, 0.55, 0.09, 0.07, 0.05, 20.0),
            PotholeShape(0.22, 0.75, 0.11, 0.08, 0.06, -15.0),
            PotholeShape(0.02, 0.33, 0.07, 0.06, 0.05, 0.0),
        ),
    )


DRIVE_POTHOLES = (
    PotholeShape(-0.20, 0.55, 0.09, 0.07, 0.05, 20.0),
    PotholeShape(0.22, 0.80, 0.11, 0.08, 0.06, -15.0),
    PotholeShape(0.00, 1.05, 0.08, 0.06, 0.05, 0.0),
    PotholeShape(-0.18, 1.30, 0.10, 0.07, 0.06, 30.0),
    PotholeShape(0.20, 1.55, 0.09, 0.08, 0.05, -25.0),
)


def drive_scenes(frames: int = 16, width: int = 640, height: int = 360,
                 speed_mps: float = 0.5, rate_hz: float = 10.0,
                 seed: int = 11) -> list[Scene]:
    """The demo rig driving forward at ``speed_mps`` past five potholes 5-6 cm deep, one scene
    per frame at ``rate_hz``; the ground texture moves with the road."""
    base = demo_scene(width, height, seed=seed)
    return [Scene(**{**base.__dict__, "camera_y_m": index * speed_mps / rate_hz,
                     "potholes": DRIVE_POTHOLES})
            for index in range(frames)]


def vehicle_scene(width: int = 640, height: int = 480, pitch_deg: float = 15.0,
                  camera_y_m: float = 0.0, roll_deg: float = 0.0, seed: int = 3) -> Scene:
    """A vehicle rig (1 m above the road, 0.12 m baseline, focal length 1000 px at 1280 px
    wide) over three potholes 6-10 cm deep, 3 to 8 m ahead of the start."""
    return Scene(
        width=width, height=height, focal_px=1000.0 * width / 1280.0, baseline_m=0.12,
        camera_height_m=1.0, pitch_deg=pitch_deg, roll_deg=roll_deg, camera_y_m=camera_y_m,
        texture_seed=seed,
        potholes=(
            PotholeShape(-0.4, 3.0, 0.35, 0.25, 0.06, 10.0),
            PotholeShape(0.8, 5.0, 0.45, 0.3, 0.08, -20.0),
            PotholeShape(-0.3, 8.0, 0.5, 0.4, 0.1, 0.0),
        ),
    )
