"""PnPf: camera pose and one focal length from 2D-3D correspondences, principal point known, d = 0.

The paper initializes its intrinsic calibration with Nakano's PnPf solver (Nakano 2016, "A
versatile approach for solving PnP, PnPf, and PnPfr problems", ECCV), a Groebner-basis method.
We solve the same problem with a different, non-minimal and linear-then-iterative method that is
simple to make stable at f ~ 45000 px and a 5 deg field of view:

1. Normalization (Hartley & Zisserman, "Multiple View Geometry", 2nd ed., sec. 4.4.4 and 7.1):
   pixels relative to the known principal point, divided by their RMS radius (the principal point
   stays at the origin, so the constraint "principal point = 0" keeps its linear form); 3D points
   centred and whitened along their principal axes (non-isotropic scaling, sec. 4.4.4), which
   also tells coplanar from non-coplanar configurations.
2. Linear initialization.
   * Non-coplanar, n >= 6: the DLT for P (H&Z algorithm 7.1). With the principal point at 0 and
     square pixels, P = lambda diag(f, f, 1) [R | t]; f is read from the row norms of P[:, :3]
     (rows 1-2 have norm lambda f, row 3 norm lambda), R is the closest rotation to the
     de-scaled rows (SVD), t the de-scaled last column.
   * Coplanar, n >= 4: the plane-to-image homography H = lambda diag(f, f, 1) [r1 r2 t]
     (H&Z alg. 4.2) and Zhang's two constraints on the image of the absolute conic
     (Zhang 2000, "A flexible new technique for camera calibration", eq. 3-4) with the known
     principal point and square pixels, omega = diag(w, w, 1), w = 1/f^2:
         w (h11 h12 + h21 h22) + h31 h32 = 0,
         w (h11^2 + h21^2 - h12^2 - h22^2) + h31^2 - h32^2 = 0,
     solved for w in the least-squares sense; then [r1 r2 t] = K^-1 H / lambda (Zhang sec. 3.1).
   Nearly planar point sets (thin along one axis) are tried both ways and the better one kept.
3. Levenberg-Marquardt polish of the reprojection error over (R, t, f) (7 unknowns, analytic
   Jacobian, scipy.optimize.least_squares), in the normalized coordinates of step 1.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ..errors import DmaisError
from ..camera import Camera, project_unmasked
from ..geometry import Rigid3, exp_so3, pose_jacobian

MIN_POINTS_3D = 6
MIN_POINTS_PLANAR = 4
_PLANAR_RATIO = 1e-3  # smallest / largest spread of the 3D points below which they are coplanar
_THIN_RATIO = 0.1  # below this, also try the planar solver and keep the better result
_COLLINEAR_RATIO = 1e-6


def _check_inputs(points_world, uv, principal_point):
    X = np.asarray(points_world, dtype=float)
    m = np.asarray(uv, dtype=float)
    c = np.asarray(principal_point, dtype=float).reshape(-1)
    if X.ndim != 2 or X.shape[1] != 3:
        raise DmaisError(f"PnPf: points_world must have shape (n, 3), got {X.shape}")
    if m.ndim != 2 or m.shape[1] != 2 or len(m) != len(X):
        raise DmaisError(f"PnPf: uv must have shape ({len(X)}, 2), got {m.shape}")
    if c.shape != (2,) or not np.all(np.isfinite(c)):
        raise DmaisError(f"PnPf: principal_point must be 2 finite numbers, got {principal_point!r}")
    bad = ~(np.isfinite(X).all(axis=1) & np.isfinite(m).all(axis=1))
    if bad.any():
        raise DmaisError(f"PnPf: non-finite input in correspondence(s) {np.flatnonzero(bad).tolist()}")
    if len(X) < MIN_POINTS_PLANAR:
        raise DmaisError(f"PnPf: {len(X)} correspondences, needs at least {MIN_POINTS_PLANAR} coplanar "
                         f"or {MIN_POINTS_3D} non-coplanar points")
    return X, m, c


def _projective_dlt(points_h: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(3, k) matrix P with x ~ P p for homogeneous points p (n, k) and pixels x (n, 2).

    Two rows per correspondence of the homogeneous DLT (Hartley & Zisserman alg. 4.1 / 7.1);
    the solution is the right singular vector of the smallest singular value.
    """
    n, k = points_h.shape
    A = np.zeros((2 * n, 3 * k))
    A[0::2, 0:k] = points_h
    A[0::2, 2 * k:] = -x[:, :1] * points_h
    A[1::2, k:2 * k] = points_h
    A[1::2, 2 * k:] = -x[:, 1:] * points_h
    return np.linalg.svd(A)[2][-1].reshape(3, k)


def _dlt(Xw: np.ndarray, x: np.ndarray):
    """Homogeneous DLT: (3, 4) P with x ~ P [Xw; 1] for whitened points Xw (n, 3) and pixels x (n, 2)."""
    return _projective_dlt(np.column_stack([Xw, np.ones(len(Xw))]), x)


def _homography(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(3, 3) H with x ~ H [a; 1] for plane points a (n, 2) and pixels x (n, 2)."""
    return _projective_dlt(np.column_stack([a, np.ones(len(a))]), x)


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def _init_3d(Xc: np.ndarray, W: np.ndarray, x: np.ndarray):
    """(R, t, f) for centred points Xc (n, 3); W (3, 3) whitens them; x normalized pixels."""
    P = _dlt(Xc @ W.T, x)
    P = np.column_stack([P[:, :3] @ W, P[:, 3]])  # back to the centred frame
    A = P[:, :3]
    scale = np.linalg.norm(A[2])
    if scale == 0:
        return None
    P = P / scale
    if np.median(Xc @ P[2, :3] + P[2, 3]) < 0:  # points must be in front of the camera
        P = -P
    f = 0.5 * (np.linalg.norm(P[0, :3]) + np.linalg.norm(P[1, :3]))
    if not np.isfinite(f) or f <= 0:
        return None
    Kinv = np.diag([1.0 / f, 1.0 / f, 1.0])
    R = _nearest_rotation(Kinv @ P[:, :3])
    t = Kinv @ P[:, 3]
    return R, t, f


def _init_planar(Xc: np.ndarray, Vt: np.ndarray, sigma: np.ndarray, x: np.ndarray):
    """(R, t, f) for coplanar centred points; rows of Vt are the principal axes, sigma their spreads."""
    a = (Xc @ Vt[:2].T) / sigma[:2]
    H = _homography(a, x) @ np.diag([1.0 / sigma[0], 1.0 / sigma[1], 1.0])  # isotropic plane coords
    H /= np.linalg.norm(H)
    h1, h2 = H[:, 0], H[:, 1]
    coeff = np.array([h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2])
    const = np.array([h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2])
    denom = coeff @ coeff
    if denom <= 0:
        return None
    w = -(coeff @ const) / denom
    if not np.isfinite(w) or w <= 0:
        return None
    f = 1.0 / np.sqrt(w)
    M = np.diag([1.0 / f, 1.0 / f, 1.0]) @ H
    lam = 0.5 * (np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1]))
    M /= lam
    if M[2, 2] < 0:  # the centroid (plane origin) must be in front of the camera
        M = -M
    r1, r2 = M[:, 0], M[:, 1]
    R_plane = _nearest_rotation(np.column_stack([r1, r2, np.cross(r1, r2)]))
    V = np.vstack([Vt[0], Vt[1], np.cross(Vt[0], Vt[1])]).T  # plane axes, right-handed
    return R_plane @ V.T, M[:, 2], f


def _residuals_and_jacobian(Xs, x, R0):
    def fun(p):
        R = exp_so3(p[:3]) @ R0
        f = np.exp(p[6])
        return (project_unmasked(Xs @ R.T + p[3:6], Camera(f, f, 0.0, 0.0, 0.0, 0, 0)) - x).ravel()

    def jac(p):
        R = exp_so3(p[:3]) @ R0
        f = np.exp(p[6])
        _, J_cam, J_intr = project_unmasked(Xs @ R.T + p[3:6], Camera(f, f, 0.0, 0.0, 0.0, 0, 0), jacobian=True)
        J_pose = pose_jacobian(Xs, R, p[:3], J_cam)
        J_f = (J_intr[:, :, 0] + J_intr[:, :, 1]) * f  # d/d(log f)
        return np.concatenate([J_pose, J_f[:, :, None]], axis=2).reshape(-1, 7)

    return fun, jac


def _polish(Xs, x, R0, t0, f0):
    """LM over (rotation vector around R0, t, log f); returns (R, t, f, rms) in the scaled frame."""
    fun, jac = _residuals_and_jacobian(Xs, x, R0)
    p0 = np.concatenate([np.zeros(3), t0, [np.log(f0)]])
    try:
        sol = least_squares(fun, p0, jac=jac, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=200)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(sol.x)):
        return None
    R = exp_so3(sol.x[:3]) @ R0
    t = sol.x[3:6]
    depth = Xs @ R[2] + t[2]
    if np.any(depth <= 0):
        return None
    return R, t, float(np.exp(sol.x[6])), float(np.sqrt(np.mean(sol.fun**2)))


def solve_pnpf(points_world, uv, principal_point) -> tuple[Rigid3, float]:
    """Pose and focal length (px) of a camera with known principal point, square pixels and d = 0.

    points_world: (n, 3) world points; uv: (n, 2) pixels; principal_point: (2,) pixels.
    Needs n >= 6 non-coplanar or n >= 4 coplanar points. Returns (cam_from_world, focal).
    Raises DmaisError for too few, non-finite or degenerate (collinear, fronto-parallel planar) input.
    """
    X, m, c = _check_inputs(points_world, uv, principal_point)
    n = len(X)
    # Image normalization: relative to the principal point, RMS radius sqrt(2).
    x = m - c
    img_scale = np.sqrt(np.mean(np.sum(x**2, axis=1)) / 2.0)
    if img_scale <= 0:
        raise DmaisError("PnPf: all image points coincide with the principal point")
    x = x / img_scale
    # Object normalization: centre, principal axes.
    centre = X.mean(axis=0)
    Xc = X - centre
    _, sing, Vt = np.linalg.svd(Xc, full_matrices=False)
    spread = sing / np.sqrt(n)
    if spread[0] <= 0 or spread[1] / spread[0] < _COLLINEAR_RATIO:
        raise DmaisError("PnPf: the 3D points are collinear (or coincide); pose and focal are not determined")
    ratio = spread[2] / spread[0]
    candidates = []
    if ratio >= _PLANAR_RATIO:
        if n < MIN_POINTS_3D:
            raise DmaisError(f"PnPf: {n} non-coplanar points, needs at least {MIN_POINTS_3D}")
        W = np.diag(1.0 / spread) @ Vt
        candidates.append(_init_3d(Xc, W, x))
    if ratio < _THIN_RATIO:
        candidates.append(_init_planar(Xc, Vt, spread, x))
    iso = np.sqrt(np.mean(np.sum(Xc**2, axis=1)))  # isotropic scale for the polish
    Xs = Xc / iso
    best = None
    for init in candidates:
        if init is None:
            continue
        R0, t0, f0 = init
        result = _polish(Xs, x, R0, t0 / iso, f0)
        if result is not None and (best is None or result[3] < best[3]):
            best = result
    if best is None:
        kind = "coplanar" if ratio < _PLANAR_RATIO else "3D"
        raise DmaisError(f"PnPf: degenerate {kind} configuration of {n} points (e.g. a plane parallel to the "
                         "image plane, or all points behind the camera): the focal length is not determined")
    R, t_s, f_n, _ = best
    focal = f_n * img_scale
    # Undo the object normalization: R (X - centre) / iso + t_s  ~  R X + (iso t_s - R centre)
    t = iso * t_s - R @ centre
    return Rigid3(R, t), float(focal)
