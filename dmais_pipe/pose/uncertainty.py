"""1-sigma uncertainty of solved rig poses, for many frames at once, from the error model.

error_model.py gives each component's covariance of a frame's (omega, delta_t) (refine.py's
parameters about the frame's point centroid, R <- exp(omega) R). Its outputs here: the rig
centre c = -R^T t moves by dc = -R^T([t]x omega + delta_t) (`cramer_rao_bound`), so cov(c) =
G cov G^T, G = -R^T [[t]x, I]; the ZYX Euler angles a of world_from_rig = R^T move by
da = -E(a)^-1 omega (`geometry.euler_zyx_rates`: world_from_rig exp(-omega) is a body-frame
perturbation), so cov(a) = E^-1 cov_omega E^-T. The sigmas are the square roots of the sums over
the components; frames whose normal matrix is singular get NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from ..geometry import euler_zyx_from_rotation, euler_zyx_rates, skew
from .error_model import ErrorModel, Geometry, frame_covariances

ARCMIN_PER_RAD = 60.0 * 180.0 / np.pi


@dataclass(frozen=True)
class PoseUncertainty:
    """Per frame (F of them): attitude (F, 3) heading, pitch, roll in degrees (ZYX Euler angles of
    world_from_rig, heading in [0, 360)); sigma_position (F, 3) m along the world x, y, z;
    sigma_attitude (F, 3) arc-min of heading, pitch, roll; noise_px (F,) the model's per-axis pixel
    noise; variance_position {component: (F, 3)} m^2 and variance_attitude {component: (F, 3)}
    arcmin^2, each component's share (the sigmas' squares are their sums); covariance (F, 6, 6) the
    linearised total of (omega, delta_t); pose_covariance (F, 6, 6) that of (omega, the rig centre in
    the world axes), which geo.ned_sigmas turns to north-east-down."""

    attitude: np.ndarray
    sigma_position: np.ndarray
    sigma_attitude: np.ndarray
    noise_px: np.ndarray
    variance_position: dict[str, np.ndarray]
    variance_attitude: dict[str, np.ndarray]
    covariance: np.ndarray | None = None
    pose_covariance: np.ndarray | None = None

    def with_totals(self, rows: np.ndarray, position: np.ndarray, attitude: np.ndarray) -> "PoseUncertainty":
        """This uncertainty with the frames `rows` (k,) given the total variances position (k, 3) m^2 and
        attitude (k, 3) arcmin^2 (`nonlinear.bootstrap_variances`; NaN: kept as is): their sigmas, and
        each component's variances scaled to sum to them (the linear model's shares)."""
        factors = []
        for linear, given in ((self.sigma_position ** 2, position), (self.sigma_attitude ** 2, attitude)):
            factor = np.ones_like(linear)
            known = np.isfinite(given) & (linear[rows] > 0)
            factor[rows] = np.where(known, given / np.where(known, linear[rows], 1.0), 1.0)
            factors.append(factor)
        scaled = [{name: v * factor for name, v in parts.items()}
                  for parts, factor in ((self.variance_position, factors[0]), (self.variance_attitude, factors[1]))]
        return replace(self, sigma_position=self.sigma_position * np.sqrt(factors[0]),
                       sigma_attitude=self.sigma_attitude * np.sqrt(factors[1]),
                       variance_position=scaled[0], variance_attitude=scaled[1])


def concatenated(parts: list[PoseUncertainty]) -> PoseUncertainty:
    """One PoseUncertainty of the frames of `parts` (of the same model's components), in their order."""
    if len(parts) == 1:
        return parts[0]

    def joined(values: list):
        if values[0] is None:
            return None
        if isinstance(values[0], dict):
            return {name: np.concatenate([v[name] for v in values]) for name in values[0]}
        return np.concatenate(values)

    return PoseUncertainty(**{f.name: joined([getattr(p, f.name) for p in parts]) for f in fields(PoseUncertainty)})


def heading_pitch_roll(R) -> np.ndarray:
    """(F, 3) heading, pitch, roll in degrees of rig_from_world rotations R (F, 3, 3): world_from_rig
    = R^T = Rz(heading) Ry(pitch) Rx(roll), heading in [0, 360), pitch in [-90, 90], roll in (-180, 180]."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    angles = np.degrees(euler_zyx_from_rotation(np.swapaxes(R, -1, -2)))
    angles[:, 0] %= 360.0
    return angles


def pose_uncertainty(geometry: Geometry, model: ErrorModel, R, t) -> PoseUncertainty:
    """The uncertainty of F poses R (F, 3, 3), t (F, 3) (rig_from_world) solved from the
    observations of `geometry` (`error_model.linearised_solve`) under the error `model`."""
    R, t = np.asarray(R, dtype=float).reshape(-1, 3, 3), np.asarray(t, dtype=float).reshape(-1, 3)
    attitude = heading_pitch_roll(R)
    G = -np.swapaxes(R, 1, 2) @ np.concatenate([skew(geometry.t_centred), np.broadcast_to(np.eye(3), R.shape)],
                                               axis=2)
    E_inverse = np.linalg.inv(euler_zyx_rates(np.radians(attitude)))
    position, angles = {}, {}
    covariances = frame_covariances(geometry, model)
    total = sum(covariances.values())
    J = np.zeros((len(R), 6, 6))  # (omega, delta_t) -> (omega, centre)
    J[:, :3, :3], J[:, 3:, :] = np.eye(3), G
    for name, covariance in covariances.items():
        position[name] = _variances(G @ covariance @ np.swapaxes(G, 1, 2))
        angles[name] = _variances(E_inverse @ covariance[:, :3, :3] @ np.swapaxes(E_inverse, 1, 2)) * ARCMIN_PER_RAD**2
    return PoseUncertainty(attitude=attitude, sigma_position=np.sqrt(sum(position.values())),
                           sigma_attitude=np.sqrt(sum(angles.values())),
                           noise_px=np.full(len(R), model.sigma["pixel"]),
                           variance_position=position, variance_attitude=angles,
                           covariance=total, pose_covariance=J @ total @ np.swapaxes(J, 1, 2))


def _variances(covariance) -> np.ndarray:
    """(F, 3) the diagonals of covariances (F, 3, 3), clipped at 0 (NaN where not finite)."""
    return np.clip(np.diagonal(covariance, axis1=1, axis2=2), 0.0, None)
