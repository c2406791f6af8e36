"""Projection of the paper's camera model (eq. 2-3) with analytic Jacobians, for the solvers in calib/.

Model (same as `dmais_pipe.camera.Camera`, OpenCV pinhole with k1 = d):

    X_c = R X + t,  x = X_c0 / X_c2,  y = X_c1 / X_c2,  s = 1 + d (x^2 + y^2),
    u = fx x s + cx,  v = fy y s + cy.

Rotations are parameterized by a rotation vector phi applied on the left of a fixed reference
rotation, R = exp(phi) R0, so that least-squares solvers work in a chart around R0. The exact
derivative uses the left Jacobian of SO(3) (Barfoot, "State Estimation for Robotics", eq. 7.77):
exp(phi + dphi) ~ exp(J_l(phi) dphi) exp(phi), hence d(R X)/dphi = -[R X]x J_l(phi).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def exp_so3(phi) -> np.ndarray:
    """(3, 3) rotation of a rotation vector (3,)."""
    return Rotation.from_rotvec(np.asarray(phi, dtype=float)).as_matrix()


def left_jacobian(phi) -> np.ndarray:
    """(3, 3) left Jacobian J_l of SO(3) at rotation vector phi (3,)."""
    phi = np.asarray(phi, dtype=float)
    theta = float(np.linalg.norm(phi))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if theta < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (np.eye(3) + (1.0 - np.cos(theta)) / theta**2 * K
            + (theta - np.sin(theta)) / theta**3 * K @ K)


def project(points, R, t, fx, fy, cx, cy, d, jacobian: bool = False):
    """Pixels (n, 2) of world points (n, 3) with cam_from_world (R, t) and intrinsics.

    With `jacobian`, also returns J_cam (n, 2, 3) = d(uv)/d(X_c) and J_intr (n, 2, 5) =
    d(uv)/d(fx, fy, cx, cy, d).
    """
    Xc = points @ np.asarray(R).T + np.asarray(t)
    z = Xc[:, 2]
    x = Xc[:, 0] / z
    y = Xc[:, 1] / z
    r2 = x * x + y * y
    s = 1.0 + d * r2
    uv = np.column_stack([fx * x * s + cx, fy * y * s + cy])
    if not jacobian:
        return uv
    n = len(points)
    J_intr = np.zeros((n, 2, 5))
    J_intr[:, 0, 0] = x * s
    J_intr[:, 1, 1] = y * s
    J_intr[:, 0, 2] = 1.0
    J_intr[:, 1, 3] = 1.0
    J_intr[:, 0, 4] = fx * x * r2
    J_intr[:, 1, 4] = fy * y * r2
    # d(uv)/d(x, y)
    J_xy = np.empty((n, 2, 2))
    J_xy[:, 0, 0] = fx * (s + 2.0 * d * x * x)
    J_xy[:, 0, 1] = fx * 2.0 * d * x * y
    J_xy[:, 1, 0] = fy * 2.0 * d * x * y
    J_xy[:, 1, 1] = fy * (s + 2.0 * d * y * y)
    # d(x, y)/d(X_c)
    J_n = np.zeros((n, 2, 3))
    J_n[:, 0, 0] = 1.0 / z
    J_n[:, 0, 2] = -x / z
    J_n[:, 1, 1] = 1.0 / z
    J_n[:, 1, 2] = -y / z
    return uv, J_xy @ J_n, J_intr


def pose_jacobian(points, R, phi, J_cam) -> np.ndarray:
    """(n, 2, 6) d(uv)/d(phi, t) for R = exp(phi) R0 (R given, already composed) and X_c = R X + t."""
    RX = points @ np.asarray(R).T
    skew = np.zeros((len(points), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = -RX[:, 2], RX[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = RX[:, 2], -RX[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = -RX[:, 1], RX[:, 0]
    dXc_dphi = -skew @ left_jacobian(phi)
    return np.concatenate([J_cam @ dXc_dphi, J_cam], axis=2)
