"""Rotations (Cayley, quaternion, ZYX Euler, SO(3) exp/log and Jacobians), rigid transforms and error metrics.

Conventions: quaternions are (w, x, y, z); angles are radians; a `Rigid3` named `a_from_b` maps
points of frame b to frame a: x_a = R @ x_b + t.

Least-squares solvers perturb a rotation on the left of a fixed reference, R = exp(phi) R0, so
they work in a chart around R0. The exact derivative uses the left Jacobian of SO(3) (Barfoot,
"State Estimation for Robotics", eq. 7.77): exp(phi + dphi) ~ exp(J_l(phi) dphi) exp(phi), hence
d(R X)/dphi = -[R X]x J_l(phi) (`pose_jacobian`).

`exp_so3` and `rotation_from_quat` (every flight image's prior and windows, every frame of the pose
stage) are scipy's `Rotation.from_rotvec(...).as_matrix()` and `Rotation.from_quat(...,
scalar_first=True).as_matrix()` to the last bit, computed here in the same order of operations
(`_matrix_of_quat`), so that a marker job does not import scipy.spatial (~0.1-0.2 CPU s; issue 40,
per-job overhead); tests/test_geometry.py compares them with scipy's. The other conversions import
scipy's Rotation where they are called.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import GeometryError

#: Below this angle (rad) `exp_so3` takes sin(angle / 2) / angle from its Taylor series (as scipy does).
_SMALL_ANGLE = 1e-3


def skew(v) -> np.ndarray:
    """Cross-product matrices [v]x (3, 3) or (n, 3, 3) of vectors (3,) or (n, 3): skew(a) @ b == cross(a, b)."""
    v = np.asarray(v, dtype=float)
    if v.ndim not in (1, 2) or v.shape[-1] != 3:
        raise GeometryError(f"skew needs vectors of shape (3,) or (n, 3), got {v.shape}")
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def exp_so3(phi) -> np.ndarray:
    """Rotations (3, 3) or (n, 3, 3) of rotation vectors phi (3,) or (n, 3) (angle |phi| about phi / |phi|):
    the quaternion (sin(angle / 2) / angle * phi, cos(angle / 2)), its factor from the Taylor series
    0.5 - angle^2 / 48 + angle^4 / 3840 below 1e-3 rad, as a matrix (scipy's bits, module docstring)."""
    phi = np.asarray(phi, dtype=float)
    if phi.ndim not in (1, 2) or phi.shape[-1] != 3:
        raise ValueError(f"Expected `rot_vec` to have shape (3,) or (N, 3), got {phi.shape}")
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    angle = np.sqrt(x * x + y * y + z * z)
    small = angle <= _SMALL_ANGLE
    squared = angle * angle
    series = 0.5 - squared / 48 + squared * squared / 3840
    scale = np.where(small, series, np.sin(angle / 2) / np.where(small, 1.0, angle))
    return _matrix_of_quat(scale * x, scale * y, scale * z, np.cos(angle / 2))


def log_so3(R) -> np.ndarray:
    """Rotation vectors (3,) or (n, 3), angle in [0, pi], of rotations (3, 3) or (n, 3, 3); exp_so3's inverse."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def left_jacobian_so3(phi) -> np.ndarray:
    """(..., 3, 3) left Jacobians J_l of SO(3) at rotation vectors phi (..., 3), e.g. (3,) or (n, 3):
    exp(phi + dphi) ~ exp(J_l dphi) exp(phi).

    J_l = I + (1 - cos theta) / theta^2 [phi]x + (theta - sin theta) / theta^3 [phi]x^2, theta = |phi|;
    its Taylor series to second order below theta = 1e-6.
    """
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi.reshape(-1, 3)).reshape(phi.shape + (3,))
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    first = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    second = np.where(small, 1.0 / 6.0, (safe - np.sin(safe)) / safe**3)
    return np.eye(3) + first * K + second * (K @ K)


def pose_jacobian(points, R, phi, J_point) -> np.ndarray:
    """(n, k, 6) d f / d(phi, t) of a function f of X_c = R X + t, with R = exp(phi) R0.

    points: (n, 3) X; R: (3, 3) the rotation already composed, exp(phi) R0; phi: (3,);
    J_point: (n, k, 3) d f / d X_c at X_c (e.g. `camera.project_unmasked`'s pixel Jacobian, k = 2).
    By the chain rule with d X_c / dphi = -[R X]x J_l(phi) and d X_c / dt = I.
    """
    dXc_dphi = -skew(np.asarray(points, dtype=float) @ np.asarray(R).T) @ left_jacobian_so3(phi)
    return np.concatenate([J_point @ dXc_dphi, J_point], axis=2)


def rotation_from_cayley(q) -> np.ndarray:
    """Rotation matrices (3, 3) or (n, 3, 3) from Cayley parameters (3,) or (n, 3).

    The paper's formula: R = ((1 - q.q) I + 2 q q^T + 2 [q]x) / (1 + q.q).
    """
    q = np.asarray(q, dtype=float)
    qs = np.atleast_2d(q)
    qx, qy, qz = qs[:, 0], qs[:, 1], qs[:, 2]
    qq = qx**2 + qy**2 + qz**2
    R = np.empty((len(qs), 3, 3))
    R[:, 0, 0] = 1 + qx**2 - qy**2 - qz**2
    R[:, 0, 1] = 2 * qx * qy - 2 * qz
    R[:, 0, 2] = 2 * qy + 2 * qx * qz
    R[:, 1, 0] = 2 * qx * qy + 2 * qz
    R[:, 1, 1] = 1 - qx**2 + qy**2 - qz**2
    R[:, 1, 2] = 2 * qy * qz - 2 * qx
    R[:, 2, 0] = 2 * qx * qz - 2 * qy
    R[:, 2, 1] = 2 * qx + 2 * qy * qz
    R[:, 2, 2] = 1 - qx**2 - qy**2 + qz**2
    R /= (1 + qq)[:, None, None]
    return R[0] if q.ndim == 1 else R


def cayley_from_rotation(R, min_denominator: float = 1e-12) -> np.ndarray:
    """Cayley parameters (3,) or (n, 3) of rotations (3, 3) or (n, 3, 3).

    q = (R32 - R23, R13 - R31, R21 - R12) / (1 + trace R) = tan(angle / 2) * axis. Rotations by
    180 degrees have no Cayley parameters and raise GeometryError.
    """
    R = np.asarray(R, dtype=float)
    Rs = R.reshape(-1, 3, 3)
    denominator = 1.0 + np.trace(Rs, axis1=1, axis2=2)
    if np.any(denominator < min_denominator):
        raise GeometryError("a rotation by 180 degrees has no Cayley parameters")
    q = np.stack(
        [Rs[:, 2, 1] - Rs[:, 1, 2], Rs[:, 0, 2] - Rs[:, 2, 0], Rs[:, 1, 0] - Rs[:, 0, 1]], axis=1
    ) / denominator[:, None]
    return q[0] if R.ndim == 2 else q


def rotation_from_quat(q) -> np.ndarray:
    """Rotation matrices (3, 3) or (n, 3, 3) from quaternions (w, x, y, z), (4,) or (n, 4), each divided
    by its norm first (scipy's bits, module docstring); a zero or non-finite norm raises ValueError."""
    q = np.asarray(q, dtype=float)
    if q.ndim not in (1, 2) or q.shape[-1] != 4:
        raise ValueError(f"Expected `quat` to have shape (4,) or (N, 4), got {q.shape}")
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    if np.any(np.isnan(norm) | (norm == 0)):
        raise ValueError("Found zero norm quaternions in `quat`.")
    return _matrix_of_quat(x / norm, y / norm, z / norm, w / norm)


def _matrix_of_quat(x, y, z, w) -> np.ndarray:
    """(..., 3, 3) rotation matrices of the quaternions' parts x, y, z, w (...), each entry formed in
    the order scipy's `Rotation.as_matrix` forms it."""
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    R = np.empty(np.shape(x) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = 2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = 2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2
    return R


def quat_from_rotation(R) -> np.ndarray:
    """Unit quaternions (w, x, y, z) with w >= 0, (4,) or (n, 4), of rotations (3, 3) or (n, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat(canonical=True, scalar_first=True)


def euler_zyx_from_rotation(R) -> np.ndarray:
    """Intrinsic ZYX Euler angles (z, y, x) in radians, R = Rz(z) Ry(y) Rx(x), as the paper's tables."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_euler("ZYX")


def rotation_from_euler_zyx(angles) -> np.ndarray:
    """R = Rz(z) Ry(y) Rx(x) from angles (z, y, x) in radians, (3,) or (n, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("ZYX", np.asarray(angles, dtype=float)).as_matrix()


def euler_zyx_rates(angles) -> np.ndarray:
    """E (3, 3) or (n, 3, 3) of ZYX Euler angles (z, y, x) (3,) or (n, 3) in radians: the rotation
    vector of a small right (body-frame) perturbation, R(angles + d) ~ R(angles) exp(E @ d).

    From R^T dR = Rx^T Ry^T [e_z]x Ry Rx dz + Rx^T [e_y]x Rx dy + [e_x]x dx: the columns of E are
    Rx^T Ry^T e_z = (-sin y, sin x cos y, cos x cos y), Rx^T e_y = (0, cos x, -sin x) and e_x.
    Singular at y = +-90 degrees (gimbal lock).
    """
    angles = np.asarray(angles, dtype=float)
    y, x = angles[..., 1], angles[..., 2]
    E = np.zeros(angles.shape[:-1] + (3, 3))
    E[..., 0, 0], E[..., 1, 0], E[..., 2, 0] = -np.sin(y), np.sin(x) * np.cos(y), np.cos(x) * np.cos(y)
    E[..., 1, 1], E[..., 2, 1] = np.cos(x), -np.sin(x)
    E[..., 0, 2] = 1.0
    return E


def rotation_angle(R) -> np.ndarray:
    """Rotation angle in radians, in [0, pi], of rotations (3, 3) or (n, 3, 3)."""
    cos = (np.trace(np.asarray(R, dtype=float), axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def rotation_error(R_estimate, R_reference) -> np.ndarray:
    """Angle (rad) of R_estimate @ R_reference^T, accurate also for tiny angles."""
    delta = np.asarray(R_estimate) @ np.swapaxes(np.asarray(R_reference), -1, -2)
    return np.linalg.norm(log_so3(delta), axis=-1)


def translation_error(t_estimate, t_reference) -> np.ndarray:
    """Euclidean distance between translations (3,) or (n, 3)."""
    return np.linalg.norm(np.asarray(t_estimate) - np.asarray(t_reference), axis=-1)


def average_rotations(rotations, weights=None) -> np.ndarray:
    """Markley's quaternion average (3, 3) of rotations (n, 3, 3), via scipy's Rotation.mean."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(rotations, dtype=float)).mean(weights=weights).as_matrix()


@dataclass(frozen=True)
class Rigid3:
    """Rigid transform x_a = R @ x_b + t; name instances `a_from_b`."""

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "R", np.asarray(self.R, dtype=float).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=float).reshape(3))

    @classmethod
    def identity(cls) -> "Rigid3":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_quat(cls, q, t) -> "Rigid3":
        return cls(rotation_from_quat(q), t)

    @property
    def quat(self) -> np.ndarray:
        """(w, x, y, z) of R, w >= 0."""
        return quat_from_rotation(self.R)

    @property
    def center(self) -> np.ndarray:
        """Origin of frame a expressed in frame b: -R^T t (a camera's centre for cam_from_world)."""
        return -self.R.T @ self.t

    def apply(self, points) -> np.ndarray:
        """Points (n, 3) or (3,) of frame b mapped to frame a."""
        points = np.asarray(points, dtype=float)
        return points @ self.R.T + self.t

    def inverse(self) -> "Rigid3":
        return Rigid3(self.R.T, -self.R.T @ self.t)

    def __mul__(self, other: "Rigid3") -> "Rigid3":
        """Composition: a_from_b * b_from_c = a_from_c."""
        return Rigid3(self.R @ other.R, self.R @ other.t + self.t)

    def to_dict(self) -> dict:
        """{'R': row-major 3x3 list, 't': 3-list}, as in rig.json."""
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> "Rigid3":
        return cls(np.array(data["R"], dtype=float), np.array(data["t"], dtype=float))
