"""Localization of one image in the world from 2D-3D correspondences, with or without a centre prior.

Paper, section "Extrinsic Calibration", "Image Visual Localization": with a narrow field of view
PnP constrains the camera position poorly, so the camera centre measured by RTK is used:

1. rotation with the centre held at the prior: the bearings b_k of the undistorted observations
   (camera frame) and the unit vectors w_k from the centre to the control points (world frame)
   satisfy b_k = R w_k; R is the orthogonal Procrustes (Kabsch / Wahba) solution. This is what a
   DLT with known position reduces to once the translation is eliminated.
2. refinement of the full pose on the reprojection error, with the centre tied to the prior by a
   soft constraint weighted by the prior's sigma (pixel residuals / pixel_sigma, centre residuals /
   center_sigma, i.e. a whitened least-squares problem).

Without a prior, the pose comes from PnP (`calib.intrinsics.estimate_pose`).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ..camera import Camera, project_unmasked
from ..errors import DmaisError
from ..geometry import Rigid3, exp_so3, left_jacobian_so3, pose_jacobian, skew
from .intrinsics import estimate_pose

MIN_POINTS = 3
DEFAULT_CENTER_SIGMA_M = 0.02
DEFAULT_PIXEL_SIGMA_PX = 0.3


def kabsch_rotation(a: np.ndarray, b: np.ndarray, weights=None) -> np.ndarray:
    """(3, 3) rotation R minimising sum w_k |a_k - R b_k|^2 for vectors a, b (n, 3) (Wahba's problem)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=float)
    H = (a * w[:, None]).T @ b
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_with_known_center(camera: Camera, X: np.ndarray, uv: np.ndarray, center: np.ndarray) -> Rigid3:
    """cam_from_world with its centre at `center` (3,) and the rotation fitted to bearings (Kabsch).

    X: (n, 3) world points, uv: (n, 2) distorted pixels, n >= 2 non-parallel directions.
    """
    X = np.asarray(X, dtype=float)
    center = np.asarray(center, dtype=float).reshape(3)
    bearings = camera.unproject(uv)
    ok = np.isfinite(bearings).all(axis=1)
    if ok.sum() < 2:
        raise DmaisError(f"rotation with known centre needs 2 or more undistortable points, got {int(ok.sum())}")
    directions = X[ok] - center
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    R = kabsch_rotation(bearings[ok], directions)
    return Rigid3(R, -R @ center)


def refine_pose_with_center_prior(camera: Camera, X: np.ndarray, uv: np.ndarray, pose: Rigid3,
                                  center_prior: np.ndarray, center_sigma: float = DEFAULT_CENTER_SIGMA_M,
                                  pixel_sigma: float = DEFAULT_PIXEL_SIGMA_PX) -> tuple[Rigid3, np.ndarray]:
    """LM over cam_from_world (rotation + centre) on reprojection error plus a soft centre prior.

    Cost: sum |pi(X_k) - uv_k|^2 / pixel_sigma^2 + |C - center_prior|^2 / center_sigma^2.
    Returns (cam_from_world, pixel residuals (n, 2)).
    """
    X = np.asarray(X, dtype=float)
    uv = np.asarray(uv, dtype=float)
    prior = np.asarray(center_prior, dtype=float).reshape(3)
    R0 = pose.R
    n = len(X)

    def unpack(p):
        R = exp_so3(p[:3]) @ R0
        return R, -R @ p[3:]

    def fun(p):
        R, t = unpack(p)
        r_pix = (project_unmasked(X @ R.T + t, camera) - uv).ravel() / pixel_sigma
        return np.concatenate([r_pix, (p[3:] - prior) / center_sigma])

    def jac(p):
        R, t = unpack(p)
        _, J_cam, _ = project_unmasked(X @ R.T + t, camera, jacobian=True)
        J_pose = pose_jacobian(X, R, p[:3], J_cam)  # d/d(phi, t) with t free
        # t = -R C: dt/dphi = [R C]x J_l (from d(R C) = -[R C]x J_l dphi), dt/dC = -R
        dt_dphi = skew(R @ p[3:]) @ left_jacobian_so3(p[:3])
        J = np.empty((2 * n + 3, 6))
        J[:2 * n, :3] = (J_pose[:, :, :3] + J_pose[:, :, 3:] @ dt_dphi).reshape(-1, 3)
        J[:2 * n, 3:] = (J_pose[:, :, 3:] @ -R).reshape(-1, 3)
        J[:2 * n] /= pixel_sigma
        J[2 * n:] = 0.0
        J[2 * n:, 3:] = np.eye(3) / center_sigma
        return J

    sol = least_squares(fun, np.concatenate([np.zeros(3), pose.center]), jac=jac, method="lm",
                        x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100)
    R, t = unpack(sol.x)
    return Rigid3(R, t), (sol.fun[:2 * n] * pixel_sigma).reshape(-1, 2)


def localize_image(camera: Camera, X: np.ndarray, uv: np.ndarray, center_prior=None, *,
                   center_sigma: float = DEFAULT_CENTER_SIGMA_M,
                   pixel_sigma: float = DEFAULT_PIXEL_SIGMA_PX) -> tuple[Rigid3, np.ndarray]:
    """cam_from_world of one image and its pixel residuals (n, 2).

    With `center_prior` (3,) (e.g. RTK): rotation with the centre held at the prior, then the pose
    refined with a soft centre prior. Without (None or NaN): PnP (`estimate_pose`).
    """
    X = np.asarray(X, dtype=float).reshape(-1, 3)
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if len(X) != len(uv):
        raise DmaisError(f"localization: {len(X)} points for {len(uv)} pixels")
    has_prior = center_prior is not None and np.all(np.isfinite(center_prior))
    if not has_prior:
        if len(X) < 4:
            raise DmaisError(f"localization without a centre prior needs 4 or more points, got {len(X)}")
        return estimate_pose(camera, X, uv)
    if len(X) < MIN_POINTS:
        raise DmaisError(f"localization needs {MIN_POINTS} or more points, got {len(X)}")
    initial = rotation_with_known_center(camera, X, uv, center_prior)
    return refine_pose_with_center_prior(camera, X, uv, initial, center_prior, center_sigma, pixel_sigma)
