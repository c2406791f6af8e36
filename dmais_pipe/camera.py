"""Pinhole camera with one radial distortion coefficient, exactly the paper's eq. 2-3.

An undistorted pixel (u, v) with normalized coordinates x = (u - cx) / fx, y = (v - cy) / fy is
distorted to

    u' = u + d (u - cx) (x^2 + y^2),    v' = v + d (v - cy) (x^2 + y^2),

i.e. the normalized point (x, y) is scaled by (1 + d r^2). Pixel coordinates follow OpenCV: the
centre of the top-left pixel is (0, 0). Camera coordinates: x right, y down, z forward.

For a point X_c of the camera frame (OpenCV's pinhole with k1 = d):

    x = X_c0 / X_c2,  y = X_c1 / X_c2,  s = 1 + d (x^2 + y^2),  u = fx x s + cx,  v = fy y s + cy.

`Camera.project` returns NaN for points the camera does not image; least-squares solvers use
`project_unmasked`, the same formula for every point off the camera plane, so that a trial step
that moves a point behind the camera gives a large residual instead of NaN. Both can return the
Jacobians with respect to the point and to the intrinsics (fx, fy, cx, cy, d).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .errors import DmaisError

_NEWTON_MAX_ITERATIONS = 50


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


def project_unmasked(points_cam, fx: float, fy: float, cx: float, cy: float, d: float, jacobian: bool = False):
    """Distorted pixels (n, 2) of points (n, 3) in the camera frame, by eq. 2-3 for any point with z != 0.

    Unlike `Camera.project`, points behind the camera or beyond the distortion's fold are projected
    by the same formula (the model's smooth extension, for least-squares solvers). With `jacobian`,
    returns (pixels (n, 2), d pixels / d points_cam (n, 2, 3), d pixels / d (fx, fy, cx, cy, d) (n, 2, 5)).
    """
    xy, z = _normalized_from_cam(_as_points(points_cam, 3, "points_cam"))
    return _project_normalized(xy, z, fx, fy, cx, cy, d, jacobian)


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


def _project_normalized(xy, z, fx, fy, cx, cy, d, jacobian: bool):
    """Pixels (n, 2) of undistorted normalized points xy (n, 2) at depths z (n,); with `jacobian` also
    d pixels / d point (n, 2, 3) and d pixels / d (fx, fy, cx, cy, d) (n, 2, 5)."""
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
    J_xy = np.empty((len(xy), 2, 2))  # d pixels / d (x, y)
    J_xy[:, 0, 0] = fx * (s + 2.0 * d * x * x)
    J_xy[:, 0, 1] = fx * 2.0 * d * x * y
    J_xy[:, 1, 0] = fy * 2.0 * d * x * y
    J_xy[:, 1, 1] = fy * (s + 2.0 * d * y * y)
    J_normalized = np.zeros((len(xy), 2, 3))  # d (x, y) / d point
    J_normalized[:, 0, 0] = J_normalized[:, 1, 1] = 1.0 / z
    J_normalized[:, 0, 2], J_normalized[:, 1, 2] = -x / z, -y / z
    return uv, J_xy @ J_normalized, J_intrinsics


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one camera: focal lengths and principal point in pixels, distortion d, size."""

    fx: float
    fy: float
    cx: float
    cy: float
    d: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix without skew."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def max_undistortable_radius(self) -> float:
        """Largest distorted normalized radius the model maps back one-to-one (inf for d >= 0)."""
        if self.d >= 0:
            return np.inf
        return 2.0 / 3.0 * self.max_projectable_radius  # r (1 + d r^2) at its turning point

    @property
    def max_projectable_radius(self) -> float:
        """Largest undistorted normalized radius before the model folds back (inf for d >= 0).

        For d < 0, r (1 + d r^2) peaks at r = 1 / sqrt(-3 d); beyond it pixels would move back
        towards the centre, so such points are not imaged.
        """
        return np.inf if self.d >= 0 else 1.0 / np.sqrt(-3.0 * self.d)

    def project(self, points_cam, jacobian: bool = False):
        """Distorted pixels (n, 2) of points (n, 3) in the camera frame.

        NaN for points with z <= 0 and, for d < 0, beyond `max_projectable_radius`. With `jacobian`,
        returns (pixels (n, 2), d pixels / d points_cam (n, 2, 3), d pixels / d (fx, fy, cx, cy, d)
        (n, 2, 5)), NaN in the rows of points not imaged.
        """
        xy, z = _normalized_from_cam(_as_points(points_cam, 3, "points_cam"))
        hidden = ~(z > 0) | (np.hypot(xy[:, 0], xy[:, 1]) > self.max_projectable_radius)
        xy[hidden] = np.nan
        out = _project_normalized(xy, np.where(hidden, np.nan, z), self.fx, self.fy, self.cx, self.cy, self.d,
                                      jacobian)
        if jacobian:
            out[1][hidden] = np.nan
            out[2][hidden] = np.nan
        return out

    def distort(self, uv) -> np.ndarray:
        """Distorted pixels (n, 2) from undistorted pixels (n, 2) (eq. 2)."""
        xy = self._normalized_from_pixel(uv)
        return _pixels(xy, _radial_scale(xy, self.d), self.fx, self.fy, self.cx, self.cy)

    def undistort(self, uv) -> np.ndarray:
        """Undistorted pixels (n, 2) from distorted pixels (n, 2); NaN where not invertible."""
        return _pixels(self.undistort_normalized(uv), 1.0, self.fx, self.fy, self.cx, self.cy)

    def undistort_normalized(self, uv) -> np.ndarray:
        """Undistorted normalized coordinates (n, 2) (x, y) of distorted pixels (n, 2).

        Inverts r_d = r (1 + d r^2) radially by Newton's method; for d < 0 points beyond the radius
        where the model folds back (see `max_undistortable_radius`) come out as NaN.
        """
        xy_d = self._normalized_from_pixel(uv)
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
        return {k: (int(v) if k in ("width", "height") else float(v)) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict) -> "Camera":
        return cls(**{k: data[k] for k in ("fx", "fy", "cx", "cy", "d", "width", "height")})

    def _normalized_from_pixel(self, uv) -> np.ndarray:
        uv = _as_points(uv, 2, "uv")
        return np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy])
