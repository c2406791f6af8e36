"""Joint refinement of a rig's extrinsics and its placements on fixed control points (paper eq. `min`).

Unknowns: for every camera but the reference, rig_from_cam as a rotation R_c (perturbed on the left,
R_c = exp(phi) R_c0, so phi is a small rotation in the rig frame) and the camera centre c in the
rig frame; for every placement j, rig_from_world as a rotation R_j (exp(psi) R_j0) and the rig
origin C_j in the world. The reference camera is the rig frame (R = I, c = 0). Control points and
intrinsics are constant.

A point X seen by camera c at placement j: X_rig = R_j (X - C_j), X_cam = R_c^T (X_rig - c),
pixel = pi(K_c, d_c, X_cam). Optional soft priors on camera centres in the world (RTK):
C_j + R_j^T c = prior. Residuals are whitened (pixels / pixel_sigma, centres / center_sigma) and the
problem is solved by Levenberg-Marquardt (scipy.optimize.least_squares, analytic dense Jacobian:
the problem has 6 (n_cameras - 1) + 6 n_placements unknowns, a few dozen).

Backend note: pycolmap's rig bundle adjuster was not used; this scipy formulation holds exactly the
paper's cost plus the prior term and gives the covariance of the extrinsics directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..camera import Camera
from ..errors import DmaisError
from ..geometry import Rigid3
from ._projection import exp_so3, left_jacobian, project


@dataclass
class ImageBlock:
    """Observations of one image: camera, placement, world points X (n, 3), pixels uv (n, 2), centre prior."""

    image: str
    camera: str
    placement: str
    X: np.ndarray
    uv: np.ndarray
    center_prior: np.ndarray | None = None


@dataclass
class RigBAResult:
    rig_from_cam: dict[str, Rigid3]
    rig_from_world: dict[str, Rigid3]
    residuals: dict[str, np.ndarray]  # image -> (n, 2) pixel residuals
    rms_px: dict[str, float]  # camera -> RMS reprojection distance
    n_observations: dict[str, int]
    std: dict[str, dict[str, list[float]]]  # camera -> {"rotation_deg": [3], "center_m": [3]}
    prior_residuals_m: dict[str, np.ndarray] = field(default_factory=dict)
    sigma0: float = float("nan")  # a posteriori standard deviation of unit weight


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _skews(v: np.ndarray) -> np.ndarray:
    """(n, 3, 3) cross-product matrices of vectors (n, 3)."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def refine_rig(cameras: dict[str, Camera], reference: str, blocks: list[ImageBlock],
               rig_from_cam: dict[str, Rigid3], rig_from_world: dict[str, Rigid3], *,
               pixel_sigma: float | dict[str, float] = 0.3, center_sigma: float = 0.02,
               use_priors: bool = True, max_nfev: int = 200) -> RigBAResult:
    """Levenberg-Marquardt over extrinsics (reference fixed) and placement poses (eq. `min`).

    rig_from_cam: initial value for every camera of `blocks` (the reference's is ignored: identity);
    rig_from_world: initial value for every placement of `blocks`. `pixel_sigma` (per camera or one
    value) and `center_sigma` weight the reprojection and prior terms.
    """
    names = sorted({b.camera for b in blocks} - {reference})
    placements = sorted({b.placement for b in blocks})
    missing = [c for c in names if c not in rig_from_cam] + [p for p in placements if p not in rig_from_world]
    if missing:
        raise DmaisError(f"rig bundle adjustment: no initial value for {', '.join(missing)}")
    cam_index = {c: 6 * k for k, c in enumerate(names)}
    offset = 6 * len(names)
    pl_index = {p: offset + 6 * k for k, p in enumerate(placements)}
    n_params = offset + 6 * len(placements)
    Rc0 = {c: rig_from_cam[c].R for c in names}
    Rj0 = {p: rig_from_world[p].R for p in placements}
    x0 = np.zeros(n_params)
    for c in names:
        x0[cam_index[c] + 3: cam_index[c] + 6] = rig_from_cam[c].t
    for p in placements:
        x0[pl_index[p] + 3: pl_index[p] + 6] = rig_from_world[p].center
    sig = {c: float(pixel_sigma[c]) if isinstance(pixel_sigma, dict) else float(pixel_sigma) for c in cameras}
    with_prior = [use_priors and b.center_prior is not None and np.all(np.isfinite(b.center_prior)) for b in blocks]
    rows, start = [], 0
    for b, prior in zip(blocks, with_prior):
        n_rows = 2 * len(b.X) + (3 if prior else 0)
        rows.append((start, n_rows))
        start += n_rows
    n_res = start
    if n_res < n_params:
        raise DmaisError(f"rig bundle adjustment: {n_res} residuals for {n_params} unknowns")

    def camera_params(p, c):
        if c == reference:
            return np.zeros(3), np.eye(3), np.zeros(3)
        k = cam_index[c]
        return p[k:k + 3], exp_so3(p[k:k + 3]) @ Rc0[c], p[k + 3:k + 6]

    def placement_params(p, j):
        k = pl_index[j]
        return p[k:k + 3], exp_so3(p[k:k + 3]) @ Rj0[j], p[k + 3:k + 6]

    def evaluate(p, jacobian: bool):
        r = np.empty(n_res)
        J = np.zeros((n_res, n_params)) if jacobian else None
        for b, prior, (r0, nr) in zip(blocks, with_prior, rows):
            cam = cameras[b.camera]
            s = sig[b.camera]
            phi, Rc, c = camera_params(p, b.camera)
            psi, Rj, Cj = placement_params(p, b.placement)
            X_rig = (b.X - Cj) @ Rj.T
            v = X_rig - c
            X_cam = v @ Rc  # rows of Rc^T v
            n2 = 2 * len(b.X)
            out = project(X_cam, np.eye(3), np.zeros(3), cam.fx, cam.fy, cam.cx, cam.cy, cam.d, jacobian=jacobian)
            uv = out[0] if jacobian else out
            r[r0:r0 + n2] = (uv - b.uv).ravel() / s
            if prior:
                r[r0 + n2:r0 + nr] = (Cj + Rj.T @ c - b.center_prior) / center_sigma
            if not jacobian:
                continue
            J_cam = out[1] / s  # (n, 2, 3) d(pixel)/d(X_cam)
            RcT = Rc.T
            # placement: dX_rig/dpsi = -[X_rig]x J_l(psi), dX_rig/dC = -R_j; dX_cam/dX_rig = R_c^T
            dXr_dpsi = -_skews(X_rig) @ left_jacobian(psi)
            kj = pl_index[b.placement]
            J[r0:r0 + n2, kj:kj + 3] = (J_cam @ RcT @ dXr_dpsi).reshape(-1, 3)
            J[r0:r0 + n2, kj + 3:kj + 6] = (J_cam @ (RcT @ -Rj)).reshape(-1, 3)
            if b.camera != reference:
                # dX_cam/dphi = R_c^T [v]x J_l(phi), dX_cam/dc = -R_c^T
                kc = cam_index[b.camera]
                J[r0:r0 + n2, kc:kc + 3] = (J_cam @ (RcT @ _skews(v)) @ left_jacobian(phi)).reshape(-1, 3)
                J[r0:r0 + n2, kc + 3:kc + 6] = (J_cam @ -RcT).reshape(-1, 3)
            if prior:
                rr = slice(r0 + n2, r0 + nr)
                J[rr, kj:kj + 3] = Rj.T @ _skew(c) @ left_jacobian(psi) / center_sigma
                J[rr, kj + 3:kj + 6] = np.eye(3) / center_sigma
                if b.camera != reference:
                    J[rr, kc + 3:kc + 6] = Rj.T / center_sigma
        return (r, J) if jacobian else r

    sol = least_squares(lambda p: evaluate(p, False), x0, jac=lambda p: evaluate(p, True)[1], method="lm",
                        x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=max_nfev)
    p = sol.x
    r, J = evaluate(p, True)
    dof = max(n_res - n_params, 1)
    sigma0_sq = float(r @ r) / dof
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    Js = J / scale
    cov = np.linalg.pinv(Js.T @ Js) / np.outer(scale, scale) * sigma0_sq
    std_all = np.sqrt(np.clip(np.diag(cov), 0, None))

    out_cam = {reference: Rigid3.identity()}
    std = {reference: {"rotation_deg": [0.0, 0.0, 0.0], "center_m": [0.0, 0.0, 0.0]}}
    for c in names:
        _, Rc, cc = camera_params(p, c)
        out_cam[c] = Rigid3(Rc, cc)
        k = cam_index[c]
        std[c] = {"rotation_deg": np.degrees(std_all[k:k + 3]).tolist(), "center_m": std_all[k + 3:k + 6].tolist()}
    out_pl = {}
    for j in placements:
        _, Rj, Cj = placement_params(p, j)
        out_pl[j] = Rigid3(Rj, -Rj @ Cj)
    residuals, prior_res = {}, {}
    per_camera: dict[str, list[np.ndarray]] = {}
    for b, prior, (r0, nr) in zip(blocks, with_prior, rows):
        n2 = 2 * len(b.X)
        res = (r[r0:r0 + n2] * sig[b.camera]).reshape(-1, 2)
        residuals[b.image] = res
        per_camera.setdefault(b.camera, []).append(res)
        if prior:
            prior_res[b.image] = r[r0 + n2:r0 + nr] * center_sigma
    rms = {c: float(np.sqrt(np.mean(np.sum(np.vstack(v) ** 2, axis=1)))) for c, v in per_camera.items()}
    n_obs = {c: int(sum(len(x) for x in v)) for c, v in per_camera.items()}
    return RigBAResult(rig_from_cam=out_cam, rig_from_world=out_pl, residuals=residuals, rms_px=rms,
                       n_observations=n_obs, std=std, prior_residuals_m=prior_res, sigma0=float(np.sqrt(sigma0_sq)))
