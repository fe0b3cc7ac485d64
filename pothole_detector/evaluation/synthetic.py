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

import cv2
import numpy as np

from ..calibration import CameraModel, StereoCalibration, StereoCamera


def _ellipse_frame(shape: "PotholeShape | BumpShape | Paint", x: np.ndarray,
                   y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (x, y) m in the frame of a shape's rotated ellipse: the coordinates along
    its semi-axes (a, b), in units of them (inside where p^2 + q^2 < 1)."""
    c, s = math.cos(math.radians(shape.angle_deg)), math.sin(math.radians(shape.angle_deg))
    dx, dy = x - shape.x_m, y - shape.y_m
    return (c * dx + s * dy) / shape.a_m, (-s * dx + c * dy) / shape.b_m


@dataclass(frozen=True)
class PotholeShape:
    """An elliptic pothole: depth(r) = depth_m (1 - r^n) inside the ellipse of semi-axes
    (a, b) m centred at (x, y) m on the road, rotated by ``angle_deg``; n = ``wall_power``
    (2: a paraboloid bowl, larger: steeper walls and a flatter floor)."""

    x_m: float
    y_m: float
    a_m: float
    b_m: float
    depth_m: float
    angle_deg: float = 0.0
    wall_power: float = 2.0

    @property
    def area_m2(self) -> float:
        return math.pi * self.a_m * self.b_m

    @property
    def mean_depth_m(self) -> float:
        return self.depth_m * self.wall_power / (self.wall_power + 2.0)

    @property
    def volume_m3(self) -> float:
        return self.area_m2 * self.mean_depth_m

    def depth_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Depth below the road surface (m, >= 0) at world points (x, y) m."""
        p, q = _ellipse_frame(self, x, y)
        r2 = p ** 2 + q ** 2
        wall = r2 if self.wall_power == 2.0 else r2 ** (0.5 * self.wall_power)
        return np.where(r2 < 1.0, self.depth_m * (1.0 - wall), 0.0)


@dataclass(frozen=True)
class BumpShape:
    """A raised shape on the road (distractor): ``profile`` dome (paraboloid cap), disc (a flat
    manhole cover with a 1 cm chamfer) or ridge (a speed bump: cos^2 across ``b_m``, flat along
    ``a_m``), ``height_m`` above the road, semi-axes (a, b) m, rotated by ``angle_deg``."""

    x_m: float
    y_m: float
    a_m: float
    b_m: float
    height_m: float
    profile: str = "dome"
    angle_deg: float = 0.0

    def depth_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Depth below the road surface (m, <= 0 on the bump) at world points (x, y) m."""
        p, q = _ellipse_frame(self, x, y)
        if self.profile == "ridge":
            shape = np.where((np.abs(p) < 1.0) & (np.abs(q) < 1.0),
                             np.cos(0.5 * np.pi * q) ** 2, 0.0)
        elif self.profile == "disc":
            r = np.sqrt(p * p + q * q)
            edge = 0.01 / min(self.a_m, self.b_m)
            shape = np.clip((1.0 - r) / edge, 0.0, 1.0)
        else:
            shape = np.maximum(1.0 - (p * p + q * q), 0.0)
        return -self.height_m * shape


@dataclass(frozen=True)
class Paint:
    """A change of the road's brightness without relief, fixed to the ground (distractor): an
    ellipse (stain, patch, shadow: ``shade`` multiplies the texture's brightness) or, with
    ``kind`` line, a band of half-width ``b_m`` and half-length ``a_m`` (lane marking: bright;
    crack: dark and thin), rotated by ``angle_deg``."""

    x_m: float
    y_m: float
    a_m: float
    b_m: float
    shade: float
    kind: str = "ellipse"
    angle_deg: float = 0.0

    def mask(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Where the paint lies, at world points (x, y) m."""
        p, q = _ellipse_frame(self, x, y)
        if self.kind == "line":
            return (np.abs(p) < 1.0) & (np.abs(q) < 1.0)
        return p * p + q * q < 1.0


@dataclass(frozen=True)
class Scene:
    """A rectified stereo rig over a road. Angles in degrees, lengths in metres, pixels px.

    The road's base surface is Z = -crown x^2 - y^2 / (2 R) with R =
    ``grade_radius_m`` (> 0 a crest, < 0 a sag, 0 flat); ``potholes`` are what detection must
    find, ``relief`` (bumps, shallow dips) and ``paint`` are distractors that it must not.
    ``noise_grey``: sigma of the Gaussian sensor noise (grey levels); ``right_gain``: the right
    camera's gain relative to the left."""

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
    grade_radius_m: float = 0.0
    relief: tuple[PotholeShape | BumpShape, ...] = ()
    paint: tuple[Paint, ...] = ()
    noise_grey: float = 0.0
    right_gain: float = 1.0

    def features(self) -> tuple[PotholeShape | BumpShape, ...]:
        """Every shape that moves the surface: the potholes, then the distractors' relief."""
        return self.potholes + self.relief

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
        """Centroid (3,) of pothole ``index``'s surface in the left optical frame (m): it lies
        at the mean depth below the ellipse centre."""
        shape = self.potholes[index]
        world = np.array([shape.x_m, shape.y_m, -shape.mean_depth_m])
        return self.camera_from_world @ (world - self.camera_origin_world)


def _axes(scene: Scene) -> np.ndarray:
    """3x3 matrix whose columns are the optical x, y, z axes in world coordinates."""
    pitch, roll = math.radians(scene.pitch_deg), math.radians(scene.roll_deg)
    x = np.array([1.0, 0.0, 0.0])
    y = np.array([0.0, -math.sin(pitch), -math.cos(pitch)])
    z = np.array([0.0, math.cos(pitch), -math.sin(pitch)])
    c, s = math.cos(roll), math.sin(roll)
    return np.stack([c * x - s * y, s * x + c * y, z], axis=1)


def _grade(scene: Scene) -> float:
    """The base surface's curvature along the road: 1 / (2 R) (1/m), 0 for a flat grade."""
    return 0.5 / scene.grade_radius_m if scene.grade_radius_m else 0.0


def _surface_depth(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """How far the surface lies below Z = 0 at world (x, y): crown, grade, potholes, relief
    (m, negative above)."""
    depth = scene.crown_per_m * x * x
    if scene.grade_radius_m:
        depth = depth + _grade(scene) * y * y
    for shape in scene.features():
        depth = depth + shape.depth_at(x, y)
    return depth


def _base_hit(scene: Scene, origin: np.ndarray, directions: np.ndarray,
              offset: float) -> np.ndarray:
    """Ray parameter of the first crossing of the base surface raised by ``offset`` m
    (Z = offset - crown x^2 - grade y^2): the smallest positive root of a quadratic; NaN where
    the ray never meets it."""
    crown, grade = scene.crown_per_m, _grade(scene)
    dx, dy, dz = directions[:, 0], directions[:, 1], directions[:, 2]
    a = crown * dx * dx + grade * dy * dy
    b = dz + 2.0 * (crown * origin[0] * dx + grade * origin[1] * dy)
    c = origin[2] + crown * origin[0] ** 2 + grade * origin[1] ** 2 - offset
    with np.errstate(divide="ignore", invalid="ignore"):
        linear = np.where(b < -1e-9, -c / b, np.nan)
        if crown == 0.0 and grade == 0.0:
            return linear
        root = np.sqrt(b * b - 4.0 * a * c)
        roots = np.stack([(-b - root) / (2.0 * a), (-b + root) / (2.0 * a)])
        roots = np.where(roots > 0, roots, np.inf).min(axis=0)
        quadratic = np.where(np.isfinite(roots), roots, np.nan)
    return np.where(np.abs(a) > 1e-15, quadratic, linear)


def _cast(scene: Scene, origin: np.ndarray, directions: np.ndarray, steps: int = 48,
          refinements: int = 24) -> np.ndarray:
    """Ray parameter s (= optical depth, directions have optical z = 1) of the first surface
    crossing for each ray (N,); NaN for rays that never reach the road."""
    features = scene.features()
    max_height = sum(shape.height_m for shape in features if isinstance(shape, BumpShape))
    max_below = sum(shape.depth_m for shape in features if isinstance(shape, PotholeShape))
    s_near = _base_hit(scene, origin, directions, max_height)
    s = _base_hit(scene, origin, directions, 0.0) if max_height else s_near.copy()
    far = _base_hit(scene, origin, directions, -max_below)
    s_far = np.where(np.isfinite(far), far, s_near + 1e3)

    def gap(param: np.ndarray, rows: np.ndarray) -> np.ndarray:
        point = origin[None, :] + param[:, None] * directions[rows]
        return point[:, 2] + _surface_depth(scene, point[:, 0], point[:, 1])

    down = np.isfinite(s_near)
    rows = np.nonzero(down & _near_features(scene, origin, directions, s_near, s_far))[0]
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


def _near_features(scene: Scene, origin: np.ndarray, directions: np.ndarray,
                   s_near: np.ndarray, s_far: np.ndarray) -> np.ndarray:
    """Rays whose ground track between s_near and s_far passes within a pothole's or a bump's
    bounding circle."""
    start = origin[None, :2] + s_near[:, None] * directions[:, :2]
    track = (s_far - s_near)[:, None] * directions[:, :2]
    length2 = np.maximum((track ** 2).sum(axis=1), 1e-18)
    near = np.zeros(directions.shape[0], dtype=bool)
    for shape in scene.features():
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


def _pothole_depth(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Depth below the base surface (m) of the potholes alone at world (x, y)."""
    depth = scene.crown_per_m * x * x
    for shape in scene.potholes:
        depth = depth + shape.depth_at(x, y)
    return depth


def _render_view(scene: Scene, axes: np.ndarray, origin: np.ndarray, gain: float = 1.0,
                 noise_stream: int = 0, lens: CameraModel | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image (uint8 HxW), optical depth at pixel centres (HxW, NaN = no road) and world
    points at pixel centres (HxWx3) of one camera, whose gain is ``gain`` and whose sensor
    noise is drawn from stream ``noise_stream``. With ``lens`` the image is the raw one of that
    calibrated camera (its rectified frame the scene's camera): each sample's ray goes where
    the lens model sends its raw pixel; depth and world points stay the rectified view's."""
    k = scene.supersample
    f, cx, cy = scene.focal_px, (scene.width - 1) / 2.0, (scene.height - 1) / 2.0
    offsets = (np.arange(k) + 0.5) / k - 0.5
    u = (np.arange(scene.width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(scene.height)[:, None] + offsets[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    if lens is not None:
        uu, vv = _rectified_position(lens, uu, vv)
    rays = np.stack([(uu - cx) / f, (vv - cy) / f, np.ones_like(uu)], axis=-1).reshape(-1, 3)
    directions = rays @ axes.T
    s = _cast(scene, origin, directions)
    points = origin[None, :] + s[:, None] * directions
    hit = np.isfinite(s)
    shade = np.full(s.shape, 0.5)
    x, y = points[hit, 0], points[hit, 1]
    texture = _texture(scene.texture_seed, x, y)
    inside = _pothole_depth(scene, x, y) > 1e-6
    shade[hit] = np.where(inside, 0.25 + 0.5 * texture, 0.15 + 0.8 * texture)
    for paint in scene.paint:
        shade[hit] = np.where(paint.mask(x, y), shade[hit] * paint.shade, shade[hit])
    image = shade.reshape(scene.height, k, scene.width, k).mean(axis=(1, 3))
    if gain != 1.0:
        image = image * gain
    if scene.noise_grey > 0.0:
        noise = np.random.default_rng([scene.texture_seed, noise_stream])
        image = image + noise.normal(0.0, scene.noise_grey / 255.0, image.shape)
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
    right, _, _ = _render_view(scene, axes, right_origin, scene.right_gain, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = (scene.focal_px * scene.baseline_m / depth).astype(np.float32)
    labels = np.zeros(depth.shape, dtype=np.uint16)
    finite = np.isfinite(depth)
    for index, shape in enumerate(scene.potholes, start=1):
        inside = finite & (shape.depth_at(world[..., 0], world[..., 1]) > 0)
        labels[inside] = index
    return StereoSample(left, right, disparity, labels, scene.calibration, scene.potholes,
                        camera_from_world=axes.T, camera_origin_world=left_origin)


def _rectified_position(lens: CameraModel, u: np.ndarray, v: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Where raw pixels (u, v) of ``lens`` lie in its rectified frame (P's), by OpenCV's
    undistortion of its model (the inverse of the rectification maps)."""
    points = np.stack([u.ravel(), v.ravel()], axis=-1)[:, None, :].astype(np.float64)
    k = np.asarray(lens.k, dtype=np.float64).reshape(3, 3)
    r = np.asarray(lens.r, dtype=np.float64).reshape(3, 3)
    p = np.asarray(lens.p, dtype=np.float64).reshape(3, 4)
    d = np.asarray(lens.d, dtype=np.float64)
    if lens.distortion_model == "equidistant":
        found = cv2.fisheye.undistortPoints(points, k, d[:4], R=r, P=p)
    else:
        found = cv2.undistortPoints(points, k, d, R=r, P=p)
    return found[:, 0, 0].reshape(u.shape), found[:, 0, 1].reshape(v.shape)


LENS_DISTORTION = {
    "plumb_bob": (-0.28, 0.07, 0.0008, -0.0005, 0.0),
    "rational_polynomial": (0.35, -0.04, 0.0006, -0.0004, 0.0, 0.62, -0.02, 0.0),
    "equidistant": (-0.03, 0.012, -0.004, 0.0008),
}


def raw_camera(calibration: StereoCalibration, width: int, height: int,
               model: str = "plumb_bob", seed: int = 0) -> StereoCamera:
    """A calibrated stereo camera whose rectification gives ``calibration``'s rectified pair
    (its P matrices) for ``width`` x ``height`` images: per view a lens of distortion
    ``model`` (coefficients LENS_DISTORTION), a focal length 15 % longer than the rectified
    one, the principal point a few pixels off and a rotation R of about a degree (drawn from
    ``seed``)."""
    rng = np.random.default_rng(seed)
    f, cx, cy = calibration.f, calibration.cx, calibration.cy
    models = []
    for side in (0, 1):
        rotation, _ = cv2.Rodrigues(rng.normal(0.0, math.radians(0.6), 3))
        k = (1.15 * f, 0.0, cx + rng.uniform(-6, 6), 0.0, 1.15 * f, cy + rng.uniform(-6, 6),
             0.0, 0.0, 1.0)
        tx = -f * calibration.baseline if side else 0.0
        p = (f, 0.0, cx, tx, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0)
        models.append(CameraModel(width, height, model, LENS_DISTORTION[model], k,
                                  tuple(rotation.ravel()), p))
    return StereoCamera(models[0], models[1])


def render_raw(scene: Scene, camera: StereoCamera) -> tuple[np.ndarray, np.ndarray]:
    """The raw left and right images (uint8 HxW) that ``camera`` (raw_camera of the scene's
    calibration) takes of ``scene``: rectified by the camera's calibration they are the views
    :func:`render` gives, and its ground truth holds for them."""
    axes = _axes(scene)
    left_origin = np.array([0.0, scene.camera_y_m, scene.camera_height_m])
    right_origin = left_origin + scene.baseline_m * axes[:, 0]
    left, _, _ = _render_view(scene, axes, left_origin, lens=camera.left)
    right, _, _ = _render_view(scene, axes, right_origin, scene.right_gain, 1, camera.right)
    return left, right


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


SURVEY_POTHOLES = (
    PotholeShape(-0.18, 0.60, 0.09, 0.07, 0.080, 20.0, 4.0),
    PotholeShape(0.20, 1.00, 0.10, 0.08, 0.015, -15.0, 6.0),
    PotholeShape(-0.05, 1.45, 0.09, 0.07, 0.036, 0.0, 4.0),
    PotholeShape(0.18, 1.90, 0.10, 0.08, 0.085, 30.0, 4.0),
    PotholeShape(-0.20, 2.35, 0.09, 0.08, 0.015, -25.0, 6.0),
    PotholeShape(0.10, 2.80, 0.10, 0.07, 0.038, 10.0, 4.0),
)


def survey_drive(frames: int = 48, width: int = 640, height: int = 360,
                 speed_mps: float = 0.5, rate_hz: float = 10.0, seed: int = 13) -> list[Scene]:
    """The demo rig driving 2.4 m (48 frames at 10 Hz) past six potholes, 1.5-8.5 cm deep (two
    of each severity class, away from its bounds), every one in view for a dozen frames or more."""
    base = demo_scene(width, height, seed=seed)
    return [Scene(**{**base.__dict__, "camera_y_m": index * speed_mps / rate_hz,
                     "potholes": SURVEY_POTHOLES})
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
