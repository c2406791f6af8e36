"""1-sigma uncertainty of solved rig poses from the solve's covariance, for many frames at once.

Model: every observation used by a frame's solve has independent Gaussian pixel noise of sigma
per axis. Linearised about the solved pose with refine.py's Jacobian J_i (2, 6) of the angular
residual r_i of observation i (parameters (omega, delta_t) about the frame's point centroid,
R <- exp(omega) R), a pixel error is about focal_i r_i (focal_i the camera's pixels per radian on
its axis; the paper's distortion changes it by < 3% at the image corners). The solve minimises
sum_i w_i ||r_i||^2, with w_i = ||p_i||^2 for the paper's eq. objfun (||[f]x p||^2 = ||p||^2 sin^2
of the ray angle, p_i = R M_i + t - v_i) and w_i = 1 for a pose refined on the angular residuals
(`refine_pose`). The first-order covariance of that estimator (the sandwich form) is

    A = sum_i w_i J_i^T J_i,   B = sum_i w_i^2 / focal_i^2 J_i^T J_i,   cov = sigma^2 A^-1 B A^-1,

which for the maximum-likelihood weights w_i = focal_i^2 is sigma^2 times the inverse
Gauss-Newton normal matrix of the pixel residuals. sigma^2 = sum_i ||e_i||^2 / (2n - 6) from the
frame's own pixel residuals e_i (n used observations) when 2n - 6 >= MIN_DEGREES_OF_FREEDOM;
otherwise the estimate pooled over the other frames of the call, and without any, the calibrated
noise given (rig.json's per-camera RMS reprojection distance over sqrt 2).

Outputs: the rig centre c = -R^T t moves by dc = -R^T([t]x omega + delta_t) (`cramer_rao_bound`),
so cov(c) = G cov G^T, G = -R^T [[t]x, I]; the ZYX Euler angles a of world_from_rig = R^T move by
da = -E(a)^-1 omega (`geometry.euler_zyx_rates`: world_from_rig exp(-omega) is a body-frame
perturbation), so cov(a) = E^-1 cov_omega E^-T. Frames whose normal matrix is singular get NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import euler_zyx_from_rotation, euler_zyx_rates, skew
from .refine import _jacobian, inverse_normal_matrices, tangent_bases

#: Frames per block of `pose_uncertainty` (~60 MB of Jacobians at 40 observations a frame).
BLOCK_FRAMES = 1024
#: Fewest residual degrees of freedom (2n - 6) for a frame's own noise estimate (n >= 5 points).
MIN_DEGREES_OF_FREEDOM = 4
ARCMIN_PER_RAD = 60.0 * 180.0 / np.pi


@dataclass(frozen=True)
class PoseUncertainty:
    """Per frame (F of them): attitude (F, 3) heading, pitch, roll in degrees (ZYX Euler angles of
    world_from_rig, heading in [0, 360)); sigma_position (F, 3) m along the world x, y, z;
    sigma_attitude (F, 3) arc-min of heading, pitch, roll; noise_px (F,) the per-axis pixel noise
    used; own_noise (F,) whether it came from the frame's own residuals."""

    attitude: np.ndarray
    sigma_position: np.ndarray
    sigma_attitude: np.ndarray
    noise_px: np.ndarray
    own_noise: np.ndarray


def heading_pitch_roll(R) -> np.ndarray:
    """(F, 3) heading, pitch, roll in degrees of rig_from_world rotations R (F, 3, 3): world_from_rig
    = R^T = Rz(heading) Ry(pitch) Rx(roll), heading in [0, 360), pitch in [-90, 90], roll in (-180, 180]."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    angles = np.degrees(euler_zyx_from_rotation(np.swapaxes(R, -1, -2)))
    angles[:, 0] %= 360.0
    return angles


def frame_noise_px(residuals_px, frame_index, n_frames: int, calibrated_px: float = np.nan
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis pixel noise sigma (F,) of each frame and whether it is the frame's own estimate.

    residuals_px: (N, 2) observed minus projected pixels of the used observations; frame_index
    (N,) their frame in [0, n_frames). sum ||e||^2 / (2n - 6) where 2n - 6 >= MIN_DEGREES_OF_FREEDOM,
    else pooled over those frames, else calibrated_px (module docstring).
    """
    squares = np.bincount(frame_index, np.sum(np.square(residuals_px), axis=1), minlength=n_frames)
    dof = 2.0 * np.bincount(frame_index, minlength=n_frames) - 6.0
    own = dof >= MIN_DEGREES_OF_FREEDOM
    sigma = np.full(n_frames, np.nan)
    sigma[own] = np.sqrt(squares[own] / dof[own])
    pooled = np.sqrt(squares[own].sum() / dof[own].sum()) if own.any() else float(calibrated_px)
    sigma[~own] = pooled
    return sigma, own


def pose_uncertainty(origins, directions, points, focal_px, frame_index, R, t, noise_px,
                     own_noise=None, object_space: bool = True) -> PoseUncertainty:
    """The uncertainty of F poses solved from their used observations (module docstring), in blocks
    of BLOCK_FRAMES frames to bound the memory of the per-observation Jacobians.

    origins, directions, points: (N, 3) the used observations' rays (rig frame) and world points,
    grouped by frame; focal_px (N,) their cameras' focal lengths; frame_index (N,) their frame in
    [0, F), ascending, every frame with one at least; R (F, 3, 3), t (F, 3) rig_from_world;
    noise_px (F,) per-axis pixel sigma (`frame_noise_px`). object_space: the poses minimise the
    paper's eq. objfun (True) or the angular residuals (refined, False).
    """
    R, t = np.asarray(R, dtype=float).reshape(-1, 3, 3), np.asarray(t, dtype=float).reshape(-1, 3)
    noise_px = np.asarray(noise_px, dtype=float)
    own = np.ones(len(R), bool) if own_noise is None else np.asarray(own_noise, bool)
    firsts = range(0, max(len(R), 1), BLOCK_FRAMES)
    bounds = np.searchsorted(frame_index, [*firsts, len(R)])
    attitude = heading_pitch_roll(R)
    blocks = [_block_covariances(origins[a:b], directions[a:b], points[a:b], focal_px[a:b], frame_index[a:b] - first,
                                 R[first:first + BLOCK_FRAMES], t[first:first + BLOCK_FRAMES],
                                 attitude[first:first + BLOCK_FRAMES], object_space)
              for first, a, b in zip(firsts, bounds[:-1], bounds[1:])]
    position, angles = (np.concatenate(parts) for parts in zip(*blocks))
    return PoseUncertainty(attitude=attitude, sigma_position=noise_px[:, None] * _sigmas(position),
                           sigma_attitude=noise_px[:, None] * _sigmas(angles) * ARCMIN_PER_RAD, noise_px=noise_px,
                           own_noise=own)


def _block_covariances(origins, directions, points, focal_px, frame_index, R, t, attitude, object_space: bool
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Covariances (F, 3, 3) of the rig centre and of (heading, pitch, roll) for unit pixel noise, of
    one block of frames (arguments as `pose_uncertainty`'s, frame_index from 0; attitude (F, 3) the
    frames' `heading_pitch_roll` in degrees)."""
    n_frames = len(R)
    counts = np.maximum(np.bincount(frame_index, minlength=n_frames), 1)
    centroid = np.stack([np.bincount(frame_index, points[:, k], minlength=n_frames) for k in range(3)], axis=1)
    centroid = centroid.astype(float).reshape(-1, 3) / counts[:, None]
    t_centred = t + np.einsum("fij,fj->fi", R, centroid)  # about the centroid, as refine_pose
    R_rows = R[frame_index]
    _, J = _jacobian(origins, tangent_bases(directions / np.linalg.norm(directions, axis=1)[:, None]),
                     points - centroid[frame_index], R_rows, t_centred[frame_index])
    if object_space:
        p = np.einsum("nij,nj->ni", R_rows, points) + t[frame_index] - origins
        weight = np.sum(p * p, axis=1)
        weight /= np.bincount(frame_index, weight, minlength=n_frames)[frame_index] / counts[frame_index]
    else:
        weight = np.ones(len(points))
    A, B = _frame_sums(J, [np.repeat(weight, 2), np.repeat(weight**2 / np.asarray(focal_px, dtype=float) ** 2, 2)],
                       frame_index, n_frames)
    A_inverse = inverse_normal_matrices(A)
    covariance = A_inverse @ B @ A_inverse
    G = -np.swapaxes(R, 1, 2) @ np.concatenate([skew(t_centred), np.broadcast_to(np.eye(3), R.shape)], axis=2)
    E_inverse = np.linalg.inv(euler_zyx_rates(np.radians(attitude)))
    return (G @ covariance @ np.swapaxes(G, 1, 2),
            E_inverse @ covariance[:, :3, :3] @ np.swapaxes(E_inverse, 1, 2))


def _frame_sums(J, weights, frame_index, n_frames: int) -> list[np.ndarray]:
    """For each weight vector (2N,) of `weights`, (F, 6, 6) the sums over each frame's rows of
    weight J^T J; J (2N, 6) two rows per observation, frame_index (N,) ascending, every frame present."""
    upper = np.triu_indices(6)
    products = J[:, upper[0]] * J[:, upper[1]]  # (2N, 21) the distinct entries of each row's J^T J
    starts = 2 * np.searchsorted(frame_index, np.arange(n_frames))
    sums = []
    for weight in weights:
        entries = np.add.reduceat(products * weight[:, None], starts, axis=0) if n_frames else np.zeros((0, 21))
        out = np.empty((n_frames, 6, 6))
        out[:, upper[0], upper[1]] = entries
        out[:, upper[1], upper[0]] = entries
        sums.append(out)
    return sums


def _sigmas(covariance) -> np.ndarray:
    """(F, 3) square roots of the diagonals of covariances (F, 3, 3) (NaN where not finite)."""
    return np.sqrt(np.clip(np.diagonal(covariance, axis1=1, axis2=2), 0.0, None))
