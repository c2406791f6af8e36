"""POS / INS calibration of the rig as POS users know it: one lever arm and one boresight.

Lever arm: the POS reference point (GNSS antenna / IMU centre) in the rig frame, l (m), so that

    POS position = rig centre + world_from_rig @ l          (per frame, rotations only)

estimated once over every frame by linear least squares from the estimated rig poses. With the
rotations R_i = world_from_rig of the frames and d_i = POS_i - centre_i, the normal equations are
(sum R_i^T W R_i) l = sum R_i^T W d_i, W the inverse of a diagonal noise variance per world axis
(the vertical scatter of a POS and of a nadir-looking rig differs from the horizontal one). The
frames of a flight group share part of their error (the same ground markers and their survey,
one in-flight mounting), so the residuals are split per world axis into a variance shared by a
group and one of each frame (`variance_components`, estimated from a first unweighted fit), and
the 1-sigma of l is the covariance of the estimate under that model. Treating the frames as
independent would understate it about twofold on the simulated flights.

Observability: l alone is determined by one frame. What needs the attitude to change is telling
a lever arm from a constant world-frame offset (a datum or antenna-height error of the POS): a
rig axis that keeps one world direction in every frame (the heading turns about the vertical, so
a nadir rig's optical axis always points down) takes any world offset along that direction into
its lever-arm component. `attitude_spread` measures this per rig axis; when every axis keeps its
direction (all frames share one attitude) the lever arm is not estimated and one world offset
POS - centre is used instead, with a warning.

Boresight: the small rotation B = imu_from_rig between the rig and the INS whose attitude
frames.csv gives (prior_q*, the INS's rig_from_world): INS attitude_i = B @ rig_from_world_i.
B is the rotation average of INS_i @ R_est_i^T (their small-angle least-squares mean), reported
as a rotation vector in the rig axes with the standard error of the per-frame rotation vectors.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from scipy import optimize

from .geometry import average_rotations, log_so3

log = logging.getLogger(__name__)

ARCMIN_PER_RAD = 180.0 * 60.0 / np.pi
RIG_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class LeverArm:
    """The POS offset fitted over all frames.

    value: (3,) metres, the lever arm in the rig frame (frame 'rig'), or with frame 'world' (the
    degenerate case) a world-frame offset POS - rig centre; covariance: (3, 3) of value;
    n_frames: frames fitted; residual_rms_m: (3,) RMS residual per world axis; fixed_axes: (k, 3)
    unit rig axes that keep one world direction in every frame: along them the lever arm cannot be
    told from a constant POS offset, whatever its sigma says.
    """

    value: np.ndarray
    covariance: np.ndarray
    frame: str
    n_frames: int
    residual_rms_m: np.ndarray
    fixed_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    def pos_offsets(self, world_from_rig: np.ndarray) -> np.ndarray:
        """(n, 3) predicted POS - rig centre of frames with rotations world_from_rig (n, 3, 3)."""
        world_from_rig = np.asarray(world_from_rig, dtype=float).reshape(-1, 3, 3)
        if self.frame == "world":
            return np.broadcast_to(self.value, (len(world_from_rig), 3)).copy()
        return world_from_rig @ self.value

    def position_errors(self, centers, pos, world_from_rig) -> np.ndarray:
        """(n,) |centre + offset - POS| (m) of estimated centres (n, 3), POS positions (n, 3) and
        estimated rotations world_from_rig (n, 3, 3)."""
        predicted = np.asarray(centers, dtype=float) + self.pos_offsets(world_from_rig)
        return np.linalg.norm(predicted - np.asarray(pos, dtype=float), axis=1)


@dataclass(frozen=True)
class Boresight:
    """imu_from_rig as a rotation vector (3,) in radians (rig axes), its covariance (3, 3), the
    frames fitted and the RMS angle (rad) of the per-frame residual rotations."""

    rotvec: np.ndarray
    covariance: np.ndarray
    n_frames: int
    residual_rms_rad: float

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def attitude_spread(world_from_rig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far each rig axis turns between frames: (angles (3,) rad, rig axes (3, 3) as rows,
    world directions (3, 3) as rows), from the SVD of the mean rotation M = mean_i R_i = U S V^T.

    A rig axis V_k that every frame maps to the same world direction U_k has S_k = 1 (angle 0):
    along it a lever arm and a world offset are one and the same. angle_k = arccos(S_k) is the
    RMS-like spread of that axis' world direction. world_from_rig: (n, 3, 3).
    """
    M = np.asarray(world_from_rig, dtype=float).reshape(-1, 3, 3).mean(axis=0)
    U, S, Vt = np.linalg.svd(M)
    return np.arccos(np.clip(S, -1.0, 1.0)), Vt, U.T


def fit_lever_arm(centers, pos, world_from_rig, min_spread_rad: float, groups=None) -> LeverArm:
    """The lever arm l of POS = centre + R l over all frames (weighted linear least squares).

    centers, pos: (n, 3) estimated rig centres and POS positions; world_from_rig: (n, 3, 3) the
    estimated rotations; groups: (n,) labels of frames that share errors (flight groups: the same
    ground markers and in-flight mounting), None for independent frames. When every rig axis turns
    by less than min_spread_rad (attitude_spread), the frames share one attitude and a world offset
    POS - centre is fitted instead (warning).
    """
    R = np.asarray(world_from_rig, dtype=float).reshape(-1, 3, 3)
    d = np.asarray(pos, dtype=float) - np.asarray(centers, dtype=float)
    groups = np.zeros(len(d), dtype=int) if groups is None else np.unique(np.asarray(groups).astype(str),
                                                                         return_inverse=True)[1]
    angles, axes, directions = attitude_spread(R)
    if angles.max() < min_spread_rad:
        log.warning("lever arm: the %d frames share one attitude (every rig axis turns by at most %.2f deg, "
                    "below %.2f deg): a rig-frame lever arm cannot be told from a world offset, so eps_pos "
                    "removes one world offset POS - estimate instead", len(R), np.degrees(angles.max()),
                    np.degrees(min_spread_rad))
        return _fit_offset(d, np.broadcast_to(np.eye(3), R.shape), groups, "world")
    fixed = angles < min_spread_rad
    for angle, axis, direction in zip(angles[fixed], axes[fixed], directions[fixed]):
        log.warning("lever arm: rig axis (%.3f, %.3f, %.3f) keeps world direction (%.3f, %.3f, %.3f) within "
                    "%.2f deg in every frame; along it the lever arm also holds any constant POS offset "
                    "(e.g. a height bias), which no sigma accounts for", *axis, *direction, np.degrees(angle))
    return replace(_fit_offset(d, R, groups, "rig"), fixed_axes=np.asarray(axes)[fixed].reshape(-1, 3))


def _fit_offset(d: np.ndarray, A: np.ndarray, groups: np.ndarray, frame: str) -> LeverArm:
    """Least squares of d_i = A_i x (d: (n, 3), A: (n, 3, 3)) weighted per world axis, with the
    error of a frame the sum of a part shared by its group and its own part, both with a variance
    per world axis (`variance_components`); the weights 1 / (shared + own) come from an unweighted
    first fit. Covariance of x: N^-1 M N^-1 with N = sum A_i^T W A_i and M the covariance of
    sum A_i^T W e_i under that error model (N^-1 when nothing is shared); NaN with one frame.
    groups: (n,) ints."""
    weights = np.ones(3)
    for _ in range(2):
        N = np.einsum("nji,j,njk->ik", A, weights, A)
        x = np.linalg.solve(N, np.einsum("nji,j,nj->i", A, weights, d))
        residuals = d - A @ x
        if len(d) < 2:
            return LeverArm(x, np.full((3, 3), np.nan), frame, len(d), np.abs(residuals[0]))
        own, shared = variance_components(residuals, A, weights, groups)
        weights = 1.0 / np.maximum(own + shared, 1e-12)
    N_inv = np.linalg.inv(np.einsum("nji,j,njk->ik", A, weights, A))
    WA = A * weights[None, :, None]
    M = np.einsum("nji,j,njk->ik", WA, own, WA)
    for g in np.unique(groups):
        S = WA[groups == g].sum(axis=0)
        M += S.T @ (shared[:, None] * S)
    return LeverArm(x, N_inv @ M @ N_inv, frame, len(d), np.sqrt(np.mean(residuals**2, axis=0)))


def variance_components(residuals, A, weights, groups) -> tuple[np.ndarray, np.ndarray]:
    """Per world axis k, the variances of the two parts of a frame's error e_i = b_g(i) + u_i:
    own (u, independent per frame) and shared (b, one per group), from the residuals of the
    weighted fit d_i = A_i x.

    Moment estimates (Henderson's method, Searle, Casella & McCulloch, "Variance Components",
    ch. 5): the sums of squares Q_total,k = sum_i r_ik^2 and Q_between,k = sum_g m_g rbar_gk^2 are
    set to their expectations under the model, tr(P (I - H) K_c (I - H)^T) per component c with H
    the fit's hat matrix, so the degrees of freedom the fit takes from the group means are
    accounted for; solved with non-negative least squares. With fewer than two groups, or no group
    of two frames, nothing is shared. residuals: (n, 3); A: (n, 3, 3); weights: (3,); groups: (n,)
    ints 0..G-1. Returns own (3,), shared (3,).
    """
    residuals = np.asarray(residuals, dtype=float)
    n = len(residuals)
    sizes = np.bincount(groups)
    separable = len(sizes) >= 2 and n > len(sizes)
    # A component or statistic is (world axis k, M): it touches axis k of every frame i through row
    # i of M (None: the identity, one column per frame), so its matrix over the 3n stacked residuals
    # is M on axis k (e.g. Q_between,k = |M^T r_k|^2).
    in_group = np.eye(len(sizes))[groups]
    owns = [(k, None) for k in range(3)]
    shares = [(k, in_group) for k in range(3)] if separable else []
    means = [(k, in_group / np.sqrt(sizes)) for k in range(3)] if separable else []
    N_inv = np.linalg.inv(np.einsum("nji,j,njk->ik", A, weights, A))
    statistics = owns + means
    Q = np.array([np.sum(_transposed_times(M, residuals[:, k]) ** 2) for k, M in statistics])
    T = np.array([[_residual_moment(P, L, A, weights, N_inv) for L in owns + shares] for P in statistics])
    theta = optimize.nnls(T, Q)[0]
    return theta[:3], theta[3:] if separable else np.zeros(3)


def _residual_moment(P: tuple[int, np.ndarray], L: tuple[int, np.ndarray], A: np.ndarray, weights: np.ndarray,
                     N_inv: np.ndarray) -> float:
    """|P^T (I - H) L|_F^2 over the stacked residuals, H = A N_inv A^T W the fit's hat matrix: the
    expected |P^T r|^2 per unit of a variance component with covariance L L^T. P, L: (axis, (n, a)
    map) as in variance_components; A: (n, 3, 3); weights: (3,)."""
    (k, Mp), (kl, Ml) = P, L
    U = _transposed_times(Mp, A[:, k, :])  # (a, 3)
    V = _transposed_times(Ml, weights[kl] * A[:, kl, :]) @ N_inv.T  # (b, 3): the transpose of N_inv A^T W M
    moment = np.trace((U.T @ U) @ (V.T @ V))
    if k != kl:
        return float(moment)
    if Mp is None and Ml is None:  # S = P^T L = I_n, without forming it
        return float(len(A) - 2.0 * np.sum(U * V) + moment)
    S = Ml if Mp is None else (Mp.T if Ml is None else Mp.T @ Ml)
    return float(np.sum(S**2) - 2.0 * np.sum(S * (U @ V.T)) + moment)


def _transposed_times(M: np.ndarray | None, X: np.ndarray) -> np.ndarray:
    """M^T X, with M None standing for the identity."""
    return X if M is None else M.T @ X


def fit_boresight(rig_from_world_est, rig_from_world_ins) -> Boresight:
    """imu_from_rig B of INS_i = B @ R_i over all frames: the rotation average of INS_i R_i^T.

    rig_from_world_est: (n, 3, 3) the estimated attitudes; rig_from_world_ins: (n, 3, 3) the INS's.
    The covariance is that of the mean of the per-frame rotation vectors about B (NaN with one frame).
    """
    est = np.asarray(rig_from_world_est, dtype=float).reshape(-1, 3, 3)
    ins = np.asarray(rig_from_world_ins, dtype=float).reshape(-1, 3, 3)
    per_frame = ins @ np.swapaxes(est, -1, -2)
    B = average_rotations(per_frame)
    residuals = log_so3(per_frame @ B.T).reshape(-1, 3)
    n = len(per_frame)
    covariance = np.cov(residuals.T, ddof=1) / n if n > 1 else np.full((3, 3), np.nan)
    return Boresight(log_so3(B), covariance, n, float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))))


def calibration_table(lever: LeverArm, boresight: Boresight | None = None, truth: dict | None = None
                      ) -> pd.DataFrame:
    """tables/lever_arm.csv: parameter, value, sigma, unit, note [, truth], one row per parameter.

    Parameters: lever_x/y/z (m, rig frame) or, in the degenerate case, world_offset_x/y/z (m, world
    frame, POS - estimate); boresight_x/y/z (arc-min, the rotation vector of imu_from_rig in rig
    axes). truth: parameter -> the simulator's value (the lever arm, the boresight), optional.
    """
    prefix = "lever" if lever.frame == "rig" else "world_offset"
    rows = [(f"{prefix}_{a}", v, s, "m") for a, v, s in zip(RIG_AXES, lever.value, lever.sigma)]
    if boresight is not None:
        rows += [(f"boresight_{a}", v * ARCMIN_PER_RAD, s * ARCMIN_PER_RAD, "arcmin")
                 for a, v, s in zip(RIG_AXES, boresight.rotvec, boresight.sigma)]
    table = pd.DataFrame(rows, columns=["parameter", "value", "sigma", "unit"])
    table["note"] = ""
    for axis in lever.fixed_axes:  # a lever-arm component mostly along an axis that never turned
        for k in np.flatnonzero(np.abs(axis) > 0.5):
            table.loc[k, "note"] = ("not separable from a constant POS offset: this rig axis keeps one world "
                                    "direction in every frame")
    if truth:
        table["truth"] = table["parameter"].map(truth).astype(float)
    return table
