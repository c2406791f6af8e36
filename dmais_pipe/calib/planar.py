"""The focal length a flat calibration field's views determine: the start of the intrinsics on a board.

The paper starts its calibration with PnPf per image, which needs a 3-D field: on a flat one a
view's focal length is determined only through its perspective, and a view nearly parallel to the
image plane has none (PnPf then returns anything, and their mean is refused). Here every view's
plane-to-image homography H (OpenCV's normalized DLT, cv2.findHomography) enters Zhang's two
constraints on the image of the absolute conic (Zhang 2000, "A flexible new technique for camera
calibration", eq. 3-4), with the principal point at the image centre and square pixels as the
paper's priors, omega = diag(w, w, 1), w = 1 / f^2 (cv2.initCameraMatrix2D solves the same with
fx, fy apart):

    w (h11 h12 + h21 h22) + h31 h32 = 0,
    w (h11^2 + h21^2 - h12^2 - h22^2) + h31^2 - h32^2 = 0,

h_ij of H in pixels relative to the principal point, scaled by a common length and each H to unit
norm of its first two columns. Both coefficients of w are proportional to the view's perspective
(the square of its tilt's sine for a small tilt), so the least-squares w weights each view by that
share: a fronto-parallel view's rows are zero and weigh nothing, and no view is refused. Only
when the views together leave f undetermined (all nearly parallel to the image plane) is the
camera refused, naming their tilts.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import DmaisError

log = logging.getLogger(__name__)

#: Points whose smallest spread is below this fraction of their largest lie on a plane (as
#: calib.pnpf's coplanar test).
PLANAR_THICKNESS = 1e-3
#: The start's focal length must be determined to this relative standard deviation by the views'
#: constraints (the LM after it converges from much farther; a worse one means no perspective).
MAX_RELATIVE_SPREAD = 0.25
#: A view below this share of the views' mean weight is named as weighted out in the log.
WEIGHTED_OUT = 0.05


@dataclass
class PlanarStart:
    """The focal length of a flat field's views and what each view contributed.

    focal_px: the start's f (px); relative_std: its relative standard deviation from the
    constraints' scatter; weight: image -> its share of the constraints' information (sums to 1);
    tilt_deg: image -> the angle between the field's plane and the image plane at that f (exact for
    a pinhole camera; a strong distortion, which no homography follows, bends it by degrees, and f
    by up to ~20% on a k1 = -0.37 lens: the LM after the start takes both out)."""

    focal_px: float
    relative_std: float
    weight: dict[str, float]
    tilt_deg: dict[str, float]


def plane_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(centre (3,), in-plane axes (2, 3)) of points (n, 3) that lie on a plane, None otherwise
    (thicker than PLANAR_THICKNESS of their extent, or fewer than 4 distinct points)."""
    points = np.unique(np.asarray(points, dtype=float), axis=0)
    if len(points) < 4:
        return None
    centre = points.mean(axis=0)
    _, spread, axes = np.linalg.svd(points - centre, full_matrices=False)
    if spread[0] <= 0 or spread[1] < PLANAR_THICKNESS * spread[0] or spread[2] >= PLANAR_THICKNESS * spread[0]:
        return None
    return centre, axes[:2]


def planar_start(views: dict[str, tuple[np.ndarray, np.ndarray]], principal: np.ndarray, name: str) -> PlanarStart:
    """The focal length of the views {image: (points (n, 3) on one plane, pixels (n, 2))} of a flat
    field with the principal point `principal` (2,) (see the module docstring).

    Raises DmaisError naming the camera and each view's tilt when the views leave f undetermined.
    """
    frame = plane_frame(np.vstack([X for X, _ in views.values()]))
    if frame is None:
        raise DmaisError(f"camera {name}: the planar start needs control points on one plane")
    scale = np.sqrt(np.mean([np.mean(np.sum((uv - principal) ** 2, axis=1)) for _, uv in views.values()]))
    homographies = {image: _normalized_homography(X, uv, frame, principal, scale)
                    for image, (X, uv) in views.items()}
    homographies = {image: H for image, H in homographies.items() if H is not None}
    rows = {image: _conic_rows(H) for image, H in homographies.items()}
    coefficients = np.concatenate([c for c, _ in rows.values()])
    constants = np.concatenate([k for _, k in rows.values()])
    information = float(coefficients @ coefficients)
    w = -float(coefficients @ constants) / information if information > 0 else np.nan
    residual = coefficients * w + constants
    spread = np.sqrt(residual @ residual / max(len(residual) - 1, 1) / information) if information > 0 else np.inf
    relative_std = 0.5 * spread / w if w > 0 else np.inf  # f = scale / sqrt(w)
    focal = scale / np.sqrt(w) if w > 0 else np.nan
    tilt = {image: _tilt_deg(H, focal / scale) if np.isfinite(focal) else np.nan
            for image, H in homographies.items()}
    if not relative_std <= MAX_RELATIVE_SPREAD:
        determined = f"only to {relative_std:.0%}" if np.isfinite(relative_std) else "not at all"
        raise DmaisError(f"camera {name}: the {len(homographies)} views of its flat calibration field do not determine "
                         f"the focal length (their perspective fixes it {determined}: every view nearly parallel "
                         f"to the image plane: {', '.join(homographies)}); views tilted by 15 deg or more give it")
    weight = {image: float(c @ c) / information for image, (c, _) in rows.items()}
    _log_weighted_out(name, weight, tilt)
    return PlanarStart(float(focal), float(relative_std), weight, tilt)


def _normalized_homography(X: np.ndarray, uv: np.ndarray, frame, principal: np.ndarray,
                           scale: float) -> np.ndarray | None:
    """(3, 3) H from plane coordinates to pixels relative to `principal` divided by `scale`, its
    first two columns of unit Frobenius norm; None where OpenCV finds none."""
    centre, axes = frame
    plane = ((X - centre) @ axes.T).astype(np.float64)
    H, _ = cv2.findHomography(plane, uv.astype(np.float64), 0)
    if H is None or not np.all(np.isfinite(H)):
        return None
    H = np.diag([1.0 / scale, 1.0 / scale, 1.0]) @ np.array([[1.0, 0.0, -principal[0]],
                                                              [0.0, 1.0, -principal[1]], [0.0, 0.0, 1.0]]) @ H
    return H / np.linalg.norm(H[:, :2])


def _conic_rows(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zhang's two constraints of one homography H (3, 3) as coefficients of w (2,) and constants (2,)."""
    h1, h2 = H[:, 0], H[:, 1]
    coefficients = np.array([h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2])
    constants = np.array([h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2])
    return coefficients, constants


def _tilt_deg(H: np.ndarray, normalized_focal: float) -> float:
    """The angle (deg) between the field's plane and the image plane of the view of H (3, 3) at the
    focal length `normalized_focal` (in the homography's scaled pixels)."""
    M = np.diag([1.0 / normalized_focal, 1.0 / normalized_focal, 1.0]) @ H
    normal = np.cross(M[:, 0], M[:, 1])
    return float(np.degrees(np.arccos(min(abs(normal[2]) / np.linalg.norm(normal), 1.0))))


def _log_weighted_out(name: str, weight: dict[str, float], tilt: dict[str, float]) -> None:
    """Log the views whose perspective carries (next to) nothing of the focal length."""
    mean = 1.0 / len(weight)
    out = [image for image, share in weight.items() if share < WEIGHTED_OUT * mean]
    if out:
        log.info("camera %s: %d of %d views of the flat field nearly parallel to the image plane weigh next to "
                 "nothing in the focal length's start: %s", name, len(out), len(weight),
                 ", ".join(f"{image} ({tilt[image]:.1f} deg)" for image in out))
