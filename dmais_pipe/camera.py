"""Pinhole cameras with lens distortion: the paper's one radial coefficient (eq. 2-3) or OpenCV's model.

Two models, named in dataset.yaml's camera entry (`model:`):

- `radial1` (the paper's, the default): an undistorted pixel (u, v) with normalized coordinates
  x = (u - cx) / fx, y = (v - cy) / fy is distorted to

      u' = u + d (u - cx) (x^2 + y^2),    v' = v + d (v - cy) (x^2 + y^2),

  i.e. the normalized point (x, y) is scaled by (1 + d r^2). Parameters (fx, fy, cx, cy, d).
- `opencv`: cv2.calibrateCamera's default model, parameters (fx, fy, cx, cy, k1, k2, p1, p2, k3):

      x' = x s + 2 p1 x y + p2 (r^2 + 2 x^2),  y' = y s + p1 (r^2 + 2 y^2) + 2 p2 x y,
      s = 1 + k1 r^2 + k2 r^4 + k3 r^6,        u = fx x' + cx,  v = fy y' + cy.

  With k2 = p1 = p2 = k3 = 0 it is radial1 with d = k1; the Camera field `d` holds k1 in both.

Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0). Camera coordinates:
x right, y down, z forward; x = X_c0 / X_c2, y = X_c1 / X_c2 of a point X_c of the camera frame.

Where the model is invertible: the map (x, y) -> (x', y') is one-to-one inside the disk of
undistorted radius `Camera.max_projectable_radius`, the largest radius within which its Jacobian
determinant stays positive in every direction (radial1: r (1 + d r^2) turns at 1 / sqrt(-3 d) for
d < 0; opencv: found numerically). `Camera.project` returns NaN beyond it, `Camera.undistort*` for
pixels whose undistorted point lies beyond it, and `Camera.folds_in_image` says whether that disk
leaves out part of the image. Then `Camera.one_to_one_region` is the part of the image it covers
(pixels from the principal point, share of the image) and `Camera.fold_reach` how far rays lie
towards the fold (their undistorted radius over the fold's): a calibration is refused only when its observations reach near the fold, an import
when the region is less than half the image (calib.intrinsics.check_plausible, calib.import_intrinsics).

`Camera.project` returns NaN for points the camera does not image; least-squares solvers use
`project_unmasked`, the same formula for every point off the camera plane, so that a trial step
that moves a point behind the camera gives a large residual instead of NaN. Both can return the
Jacobians with respect to the point and to the model's parameters (`Camera.parameter_names`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .errors import DmaisError

_NEWTON_MAX_ITERATIONS = 50
#: The parameters of each model, in the order of the intrinsics Jacobian's columns; the first five
#: are (fx, fy, cx, cy, first radial coefficient) in both.
PARAMETER_NAMES = {
    "radial1": ("fx", "fy", "cx", "cy", "d"),
    "opencv": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"),
}
MODELS = tuple(PARAMETER_NAMES)
#: The Camera fields of the opencv model's parameters after k1 (the field `d`).
LENS_FIELDS = PARAMETER_NAMES["opencv"][5:]
#: The fold search of the opencv model: directions, and radial samples out to this many times the
#: image's normalized half-diagonal (a fold farther out never reaches an imaged point).
_FOLD_DIRECTIONS = 128
_FOLD_SAMPLES = 256
_FOLD_REACH = 8.0
_FOLD_BISECTIONS = 30
#: Undistortion converges to this many pixels (Newton's method; the issue asks for 1e-3 px).
UNDISTORT_TOLERANCE_PX = 1e-9
#: The one-to-one region's edge is traced in this many directions, its share of the image counted on
#: a grid of about this many pixels across the image's longer side.
_REGION_DIRECTIONS = 720
_REGION_GRID = 161


def image_centre(width: int, height: int) -> np.ndarray:
    """(2,) the centre of a width x height image in pixels: ((width - 1) / 2, (height - 1) / 2),
    since the centre of the top-left pixel is (0, 0)."""
    return np.array([(width - 1) / 2.0, (height - 1) / 2.0])


def _as_points(array, width: int, name: str) -> np.ndarray:
    points = np.asarray(array, dtype=float)
    if points.ndim == 1:
        points = points[None, :]
    if points.ndim != 2 or points.shape[1] != width:
        raise DmaisError(f"{name} must have shape (n, {width}), got {np.shape(array)}")
    return points


def project_unmasked(points_cam, camera: "Camera", jacobian: bool = False):
    """Distorted pixels (n, 2) of points (n, 3) in the camera frame, by the camera's model, for any
    point with z != 0.

    Unlike `Camera.project`, points behind the camera or beyond the distortion's fold are projected
    by the same formula (the model's smooth extension, for least-squares solvers). With `jacobian`,
    returns (pixels (n, 2), d pixels / d points_cam (n, 2, 3), d pixels / d parameters (n, 2, P)),
    P = len(camera.parameter_names).
    """
    xy, z = _normalized_from_cam(_as_points(points_cam, 3, "points_cam"))
    return _project_normalized(xy, z, camera, jacobian)


def _normalized_from_cam(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) = (X_c0, X_c1) / X_c2 (n, 2) and the depths X_c2 (n,) of points (n, 3); inf or NaN where z = 0."""
    z = points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return points[:, :2] / z[:, None], z


def _radial_scale(xy: np.ndarray, d: float) -> np.ndarray:
    """(n,) the distortion's scale s = 1 + d r^2 of normalized points (n, 2)."""
    return 1.0 + d * np.sum(xy**2, axis=1)


def _pixels(xy: np.ndarray, s, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(n, 2) pixels u = fx x s + cx, v = fy y s + cy of normalized points xy (n, 2) scaled by s (n,) or 1."""
    return np.column_stack([fx * xy[:, 0] * s + cx, fy * xy[:, 1] * s + cy])


def _distorted_opencv(xy: np.ndarray, k1: float, k2: float, p1: float, p2: float, k3: float,
                      jacobian: bool = False):
    """OpenCV's distorted normalized points (n, 2) of undistorted ones xy (n, 2); with `jacobian`
    also d distorted / d xy (n, 2, 2)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    s = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    distorted = np.column_stack([x * s + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                                 y * s + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y])
    if not jacobian:
        return distorted
    g = 2.0 * k1 + r2 * (4.0 * k2 + 6.0 * k3 * r2)  # d s / d x = g x, d s / d y = g y
    J = np.empty((len(xy), 2, 2))
    J[:, 0, 0] = s + g * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    J[:, 0, 1] = J[:, 1, 0] = g * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    J[:, 1, 1] = s + g * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    return distorted, J


def _determinant(J: np.ndarray) -> np.ndarray:
    """(n,) determinants of 2 x 2 matrices J (n, 2, 2)."""
    return J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]


def _project_normalized(xy, z, camera: "Camera", jacobian: bool):
    """Pixels (n, 2) of undistorted normalized points xy (n, 2) at depths z (n,); with `jacobian` also
    d pixels / d point (n, 2, 3) and d pixels / d parameters (n, 2, P)."""
    if camera.model == "radial1":
        out = _project_radial1(xy, camera.fx, camera.fy, camera.cx, camera.cy, camera.d, jacobian)
    else:
        out = _project_opencv(xy, camera, jacobian)
    if not jacobian:
        return out
    uv, J_xy, J_parameters = out
    J_normalized = np.zeros((len(xy), 2, 3))  # d (x, y) / d point
    J_normalized[:, 0, 0] = J_normalized[:, 1, 1] = 1.0 / z
    J_normalized[:, 0, 2], J_normalized[:, 1, 2] = -xy[:, 0] / z, -xy[:, 1] / z
    return uv, J_xy @ J_normalized, J_parameters


def _project_radial1(xy, fx, fy, cx, cy, d, jacobian: bool):
    """Pixels (n, 2) by eq. 2-3; with `jacobian` also d pixels / d (x, y) (n, 2, 2) and
    d pixels / d (fx, fy, cx, cy, d) (n, 2, 5)."""
    s = _radial_scale(xy, d)
    uv = _pixels(xy, s, fx, fy, cx, cy)
    if not jacobian:
        return uv
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    J_intrinsics = np.zeros((len(xy), 2, 5))
    J_intrinsics[:, 0, 0], J_intrinsics[:, 1, 1] = x * s, y * s
    J_intrinsics[:, 0, 2] = J_intrinsics[:, 1, 3] = 1.0
    J_intrinsics[:, 0, 4], J_intrinsics[:, 1, 4] = fx * x * r2, fy * y * r2
    J_xy = np.empty((len(xy), 2, 2))
    J_xy[:, 0, 0] = fx * (s + 2.0 * d * x * x)
    J_xy[:, 0, 1] = fx * 2.0 * d * x * y
    J_xy[:, 1, 0] = fy * 2.0 * d * x * y
    J_xy[:, 1, 1] = fy * (s + 2.0 * d * y * y)
    return uv, J_xy, J_intrinsics


def _project_opencv(xy, camera: "Camera", jacobian: bool):
    """Pixels (n, 2) by OpenCV's model; with `jacobian` also d pixels / d (x, y) (n, 2, 2) and
    d pixels / d (fx, fy, cx, cy, k1, k2, p1, p2, k3) (n, 2, 9)."""
    f = np.array([camera.fx, camera.fy])
    distorted = _distorted_opencv(xy, *camera.distortion, jacobian)
    if not jacobian:
        return distorted * f + [camera.cx, camera.cy]
    distorted, J_distorted = distorted
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    J = np.zeros((len(xy), 2, 9))
    J[:, 0, 0], J[:, 1, 1] = distorted[:, 0], distorted[:, 1]
    J[:, 0, 2] = J[:, 1, 3] = 1.0
    for column, power in ((4, r2), (5, r2 * r2), (8, r2 * r2 * r2)):  # k1, k2, k3
        J[:, 0, column], J[:, 1, column] = camera.fx * x * power, camera.fy * y * power
    J[:, 0, 6], J[:, 1, 6] = camera.fx * 2.0 * x * y, camera.fy * (r2 + 2.0 * y * y)  # p1
    J[:, 0, 7], J[:, 1, 7] = camera.fx * (r2 + 2.0 * x * x), camera.fy * 2.0 * x * y  # p2
    return distorted * f + [camera.cx, camera.cy], J_distorted * f[None, :, None], J


@dataclass(frozen=True)
class OneToOneRegion:
    """Where a lens model that folds inside its image is one-to-one: the undistorted normalized radius of
    the fold, the smallest distance (distorted pixels) from the principal point to the region's edge,
    and the share of the image's pixels inside it (those outside undistort to NaN)."""

    undistorted_radius: float
    radius_px: float
    image_fraction: float

    def describe(self) -> str:
        return (f"one-to-one within {self.radius_px:.0f} px of the principal point, {self.image_fraction:.1%} of the "
                f"image (undistorted radius {self.undistorted_radius:.3g})")

    def to_dict(self) -> dict:
        return {"undistorted_radius": float(self.undistorted_radius), "radius_px": float(self.radius_px),
                "image_fraction": float(self.image_fraction)}


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one camera: focal lengths and principal point in pixels, the first radial
    coefficient d (k1), image size, the distortion model and, for `opencv`, k2, p1, p2, k3."""

    fx: float
    fy: float
    cx: float
    cy: float
    d: float
    width: int
    height: int
    model: str = "radial1"
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def __post_init__(self):
        if self.model not in PARAMETER_NAMES:
            raise DmaisError(f"camera model {self.model!r} is not one of {', '.join(MODELS)}")
        if self.model == "radial1" and any((self.k2, self.p1, self.p2, self.k3)):
            raise DmaisError("the radial1 model has only d; k2, p1, p2, k3 need model opencv")

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix without skew."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> tuple[float, float, float, float, float]:
        """OpenCV's distortion vector (k1, k2, p1, p2, k3) of this camera (radial1: (d, 0, 0, 0, 0))."""
        return (self.d, self.k2, self.p1, self.p2, self.k3)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The model's parameters, in the order of `parameters` and of the intrinsics Jacobians."""
        return PARAMETER_NAMES[self.model]

    @property
    def parameters(self) -> np.ndarray:
        """(P,) the model's parameters (`parameter_names`)."""
        return np.array([self.fx, self.fy, self.cx, self.cy, *self.distortion][:len(self.parameter_names)],
                        dtype=float)

    def with_parameters(self, parameters) -> "Camera":
        """The camera of the same model and size with parameters (P,) (`parameter_names`' order)."""
        return Camera.from_parameters(self.model, parameters, self.width, self.height)

    @classmethod
    def from_parameters(cls, model: str, parameters, width: int, height: int) -> "Camera":
        """The camera of `model` and size with parameters (P,) in PARAMETER_NAMES[model]'s order."""
        if model not in PARAMETER_NAMES:
            raise DmaisError(f"camera model {model!r} is not one of {', '.join(MODELS)}")
        p = [float(v) for v in parameters]
        if len(p) != len(PARAMETER_NAMES[model]):
            raise DmaisError(f"model {model} has {len(PARAMETER_NAMES[model])} parameters, got {len(p)}")
        return cls(*p[:5], width, height, model, **dict(zip(LENS_FIELDS, p[5:])))

    @property
    def max_projectable_radius(self) -> float:
        """Largest undistorted normalized radius within which the model is one-to-one (inf if it
        never folds): radial1 with d < 0 turns at r = 1 / sqrt(-3 d), beyond which pixels would
        move back towards the centre, so such points are not imaged."""
        if self.model == "radial1":
            return np.inf if self.d >= 0 else 1.0 / np.sqrt(-3.0 * self.d)
        return _opencv_fold_radius(self.distortion, self._half_diagonal())

    @property
    def max_undistortable_radius(self) -> float:
        """Largest distorted normalized radius of the radial1 model that maps back one-to-one (inf
        for d >= 0); the opencv model's region is not a disk: see `undistort_normalized`."""
        if self.model != "radial1":
            raise DmaisError("max_undistortable_radius is the radial1 model's; use max_projectable_radius")
        if self.d >= 0:
            return np.inf
        return 2.0 / 3.0 * self.max_projectable_radius  # r (1 + d r^2) at its turning point

    @property
    def folds_in_image(self) -> bool:
        """Whether the model folds inside the image: some pixel of the image border (sampled every
        few pixels) has no undistorted point within `max_projectable_radius`."""
        n = max(self.width, self.height) // 4 + 2
        us, vs = np.linspace(-0.5, self.width - 0.5, n), np.linspace(-0.5, self.height - 0.5, n)
        border = np.concatenate([np.column_stack([us, np.full(n, -0.5)]),
                                 np.column_stack([us, np.full(n, self.height - 0.5)]),
                                 np.column_stack([np.full(n, -0.5), vs]),
                                 np.column_stack([np.full(n, self.width - 0.5), vs])])
        return bool(np.isnan(self.undistort_normalized(border)).any())

    def one_to_one_region(self) -> OneToOneRegion:
        """The part of the image where the model is one-to-one (the whole image: radius inf, share 1,
        where it does not fold inside it)."""
        limit = self.max_projectable_radius
        if not self.folds_in_image:
            return OneToOneRegion(limit, np.inf, 1.0)
        angle = np.linspace(0.0, 2.0 * np.pi, _REGION_DIRECTIONS, endpoint=False)
        edge = _project_normalized(limit * np.column_stack([np.cos(angle), np.sin(angle)]), None, self, False)
        step = max(self.width, self.height) / (_REGION_GRID - 1)
        us, vs = np.arange(0.0, self.width, step), np.arange(0.0, self.height, step)
        grid = np.column_stack([np.repeat(us, len(vs)), np.tile(vs, len(us))])
        inside = np.isfinite(self.undistort_normalized(grid)).all(axis=1)
        return OneToOneRegion(limit, float(np.hypot(*(edge - [self.cx, self.cy]).T).min()), float(inside.mean()))

    def fold_reach(self, xy) -> np.ndarray:
        """(n,) how far undistorted normalized points xy (n, 2) lie towards the fold: their radius over
        `max_projectable_radius` (1 at the fold, above 1 beyond it; 0 where the model never folds).
        Measured on the rays, not on the pixels: near the fold the polynomial flattens, so a ray 80%
        of the way there already images 93-96% of the way to the fold's pixel."""
        xy = _as_points(xy, 2, "xy")
        return np.hypot(xy[:, 0], xy[:, 1]) / self.max_projectable_radius

    def project(self, points_cam, jacobian: bool = False):
        """Distorted pixels (n, 2) of points (n, 3) in the camera frame.

        NaN for points with z <= 0 and beyond `max_projectable_radius`. With `jacobian`, returns
        (pixels (n, 2), d pixels / d points_cam (n, 2, 3), d pixels / d parameters (n, 2, P)), NaN
        in the rows of points not imaged.
        """
        xy, z = _normalized_from_cam(_as_points(points_cam, 3, "points_cam"))
        hidden = ~(z > 0) | (np.hypot(xy[:, 0], xy[:, 1]) > self.max_projectable_radius)
        xy[hidden] = np.nan
        out = _project_normalized(xy, np.where(hidden, np.nan, z), self, jacobian)
        if jacobian:
            out[1][hidden] = np.nan
            out[2][hidden] = np.nan
        return out

    def distort(self, uv) -> np.ndarray:
        """Distorted pixels (n, 2) from undistorted pixels (n, 2) (eq. 2)."""
        xy = self._normalized_from_pixel(uv)
        return _project_normalized(xy, None, self, False)

    def undistort(self, uv) -> np.ndarray:
        """Undistorted pixels (n, 2) from distorted pixels (n, 2); NaN where not invertible."""
        return _pixels(self.undistort_normalized(uv), 1.0, self.fx, self.fy, self.cx, self.cy)

    def undistort_normalized(self, uv) -> np.ndarray:
        """Undistorted normalized coordinates (n, 2) (x, y) of distorted pixels (n, 2).

        radial1 inverts r_d = r (1 + d r^2) radially by Newton's method; opencv solves the 2-D
        distortion by Newton's method from x = x_d. Pixels whose undistorted point lies beyond
        `max_projectable_radius` (where the model folds back), or where Newton's method does not
        reach `UNDISTORT_TOLERANCE_PX`, come out as NaN.
        """
        xy_d = self._normalized_from_pixel(uv)
        if self.model == "radial1":
            return self._undistort_radial1(xy_d)
        return self._undistort_opencv(xy_d)

    def _undistort_radial1(self, xy_d: np.ndarray) -> np.ndarray:
        r_d = np.hypot(xy_d[:, 0], xy_d[:, 1])
        r = r_d.copy()
        for _ in range(_NEWTON_MAX_ITERATIONS):
            step = (r + self.d * r**3 - r_d) / (1.0 + 3.0 * self.d * r**2)
            r -= step
            if not np.any(np.abs(step) > 1e-15 * (1.0 + r)):
                break
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(r_d > 0, r / r_d, 1.0)
        scale[r_d > self.max_undistortable_radius] = np.nan
        return xy_d * scale[:, None]

    def _undistort_opencv(self, xy_d: np.ndarray) -> np.ndarray:
        xy = xy_d.copy()
        limit = self.max_projectable_radius
        tolerance = UNDISTORT_TOLERANCE_PX / max(self.fx, self.fy)
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            for _ in range(_NEWTON_MAX_ITERATIONS):
                distorted, J = _distorted_opencv(xy, *self.distortion, jacobian=True)
                error = distorted - xy_d
                if np.all(np.abs(error) <= tolerance):
                    break
                step = np.column_stack([J[:, 1, 1] * error[:, 0] - J[:, 0, 1] * error[:, 1],
                                        J[:, 0, 0] * error[:, 1] - J[:, 1, 0] * error[:, 0]]) / _determinant(J)[:, None]
                trial = xy - step
                beyond = np.hypot(trial[:, 0], trial[:, 1]) > limit  # past the fold: half the step
                trial[beyond] = xy[beyond] - 0.5 * step[beyond]
                xy = trial
            error = _distorted_opencv(xy, *self.distortion) - xy_d
            bad = ~np.all(np.abs(error) <= tolerance, axis=1) | ~(np.hypot(xy[:, 0], xy[:, 1]) <= limit)
        xy[bad] = np.nan
        return xy

    def unproject(self, uv) -> np.ndarray:
        """Unit bearing vectors (n, 3) in the camera frame of distorted pixels (n, 2)."""
        xy = self.undistort_normalized(uv)
        rays = np.column_stack([xy, np.ones(len(xy))])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def in_image(self, uv, margin: float = 0.0) -> np.ndarray:
        """(n,) bool: pixels at least `margin` pixels inside the image borders."""
        uv = _as_points(uv, 2, "uv")
        return (
            (uv[:, 0] >= -0.5 + margin)
            & (uv[:, 0] <= self.width - 0.5 - margin)
            & (uv[:, 1] >= -0.5 + margin)
            & (uv[:, 1] <= self.height - 0.5 - margin)
        )

    def to_dict(self) -> dict:
        """fx, fy, cx, cy, d, width, height for radial1 (the paper's files, unchanged); model,
        fx, fy, cx, cy, k1, k2, p1, p2, k3, width, height for opencv."""
        if self.model == "radial1":
            values = {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "d": self.d}
        else:
            values = {"model": self.model, **dict(zip(self.parameter_names, map(float, self.parameters)))}
        return {**{k: (v if k == "model" else float(v)) for k, v in values.items()},
                "width": int(self.width), "height": int(self.height)}

    @classmethod
    def from_dict(cls, data: dict) -> "Camera":
        """The camera of a `to_dict` mapping (no "model": radial1)."""
        model = data.get("model", "radial1")
        names = PARAMETER_NAMES.get(model, ())
        return cls.from_parameters(model, [data[k] for k in names], data["width"], data["height"])

    def _half_diagonal(self) -> float:
        """The image's half-diagonal in normalized units (distortion aside)."""
        return float(np.hypot(max(self.cx + 0.5, self.width - 0.5 - self.cx) / self.fx,
                              max(self.cy + 0.5, self.height - 0.5 - self.cy) / self.fy))

    def _normalized_from_pixel(self, uv) -> np.ndarray:
        uv = _as_points(uv, 2, "uv")
        return np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy])


@functools.lru_cache(maxsize=256)
def _opencv_fold_radius(distortion: tuple[float, ...], half_diagonal: float) -> float:
    """The largest undistorted radius within which OpenCV's distortion (k1, k2, p1, p2, k3) keeps a
    positive Jacobian determinant in every direction, searched out to _FOLD_REACH image
    half-diagonals (inf if it does not fold there): a grid of _FOLD_DIRECTIONS x _FOLD_SAMPLES,
    then bisection between each direction's last positive and first non-positive sample."""
    if not any(distortion):
        return np.inf
    angle = np.linspace(0.0, 2.0 * np.pi, _FOLD_DIRECTIONS, endpoint=False)
    direction = np.column_stack([np.cos(angle), np.sin(angle)])
    radius = np.linspace(0.0, _FOLD_REACH * max(half_diagonal, 1e-6), _FOLD_SAMPLES + 1)[1:]

    def folded(r: np.ndarray, towards: np.ndarray) -> np.ndarray:
        """(m,) whether the determinant is <= 0 at radii r (m,) along unit directions (m, 2)."""
        return _determinant(_distorted_opencv(r[:, None] * towards, *distortion, jacobian=True)[1]) <= 0

    grid = folded(np.tile(radius, len(angle)), np.repeat(direction, len(radius), axis=0)).reshape(len(angle), -1)
    hit = grid.any(axis=1)
    if not hit.any():
        return np.inf
    first = grid[hit].argmax(axis=1)
    if (first == 0).any():
        return 0.0
    good, bad, towards = radius[first - 1], radius[first], direction[hit]
    for _ in range(_FOLD_BISECTIONS):
        middle = 0.5 * (good + bad)
        fold = folded(middle, towards)
        good, bad = np.where(fold, good, middle), np.where(fold, middle, bad)
    return float(good.min())
