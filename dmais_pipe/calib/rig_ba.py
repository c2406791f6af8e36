"""Joint refinement of a rig's extrinsics and its placements on fixed control points (paper eq. `min`).

Unknowns: for every camera but the reference, rig_from_cam as a rotation R_c (perturbed on the left,
R_c = exp(phi) R_c0, so phi is a small rotation in the rig frame) and the camera centre c in the
rig frame; for every placement j, rig_from_world as a rotation R_j (exp(psi) R_j0) and the rig
origin C_j in the world. The reference camera is the rig frame (R = I, c = 0). Control points and
intrinsics are constant.

A point X seen by camera c at placement j: X_rig = R_j (X - C_j), X_cam = R_c^T (X_rig - c),
pixel = pi(K_c, d_c, X_cam). Optional soft priors on camera centres in the world (RTK):
C_j + R_j^T c = prior. Residuals are whitened (pixels / pixel_sigma, centres / center_sigma).

Two solvers minimise this same cost:

- `refine_rig` (backend "scipy"): Levenberg-Marquardt (scipy.optimize.least_squares) with an
  analytic dense Jacobian; the problem has 6 (n_cameras - 1) + 6 n_placements unknowns, a few dozen.
- `refine_rig_pycolmap` (backend "pycolmap"): a `pycolmap.Reconstruction` with one `Rig` (reference
  sensor = reference camera), one `Frame` per placement, the control points as constant 3D points
  and constant OPENCV cameras (k1 = d, k2 = p1 = p2 = 0: exactly our model; principal point and
  keypoints both in COLMAP's pixel convention, ours + 0.5, so residuals are unchanged), refined by
  pycolmap's Ceres bundle adjuster; with priors, by its pose-prior bundle adjuster (`pycolmap.PosePrior`,
  covariance center_sigma^2 I). See that function for the adaptations this needs.

Both report the standard deviations from our own Jacobian at their optimum (Gauss-Newton covariance
with the pixels' a posteriori variance of unit weight, `_RigProblem._covariance`), so the numbers are
comparable between backends.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..camera import Camera, project_unmasked
from ..errors import DmaisError
from ..geometry import Rigid3, exp_so3, left_jacobian_so3, skew
from .survey_variance import estimate as estimate_survey_variance
from .survey_variance import inverse_normal, pixel_variance

log = logging.getLogger(__name__)

BACKENDS = ("pycolmap", "scipy")
# Acceptance of pycolmap's solution as the optimum of our cost (measured on the simulator: 1.6e-12 m
# and 1.5e-10; a dropped prior term or moved control points give metres and ~0.4).
MAX_POINT_MOTION_M = 1e-6
MAX_GRADIENT_COSINE = 1e-6
# RANSAC threshold of pycolmap's prior alignment: only the shadow images (exactly on their priors) are inliers
ALIGNMENT_MAX_ERROR_M = 1e-6
COLMAP_PIXEL_OFFSET = 0.5  # COLMAP pixel = ours + 0.5 (see colmap_pixels)
#: scipy's Levenberg-Marquardt stops at this relative step, cost decrease and gradient (xtol, ftol, gtol):
#: a solved quantity is determined to about TOLERANCE x its scale in the problem (a centre: the scene's extent).
TOLERANCE = 1e-12


@dataclass
class ImageBlock:
    """Observations of one image: camera, placement, world points X (n, 3), pixels uv (n, 2), centre
    prior; the points' ids (n,) and survey sigmas per axis (n,) m (0: exact; NaN: not given, estimated
    from the residuals), for the survey's share of the covariance (`RigBAResult.survey_response`)."""

    image: str
    camera: str
    placement: str
    X: np.ndarray
    uv: np.ndarray
    center_prior: np.ndarray | None = None
    point_ids: np.ndarray | None = None
    point_sigma: np.ndarray | None = None


@dataclass
class RigBAResult:
    rig_from_cam: dict[str, Rigid3]
    rig_from_world: dict[str, Rigid3]
    residuals: dict[str, np.ndarray]  # image -> (n, 2) pixel residuals
    rms_px: dict[str, float]  # camera -> RMS reprojection distance
    n_observations: dict[str, int]
    std: dict[str, dict[str, list[float]]]  # camera -> {"rotation_deg": [3], "center_m": [3]}
    prior_residuals_m: dict[str, np.ndarray] = field(default_factory=dict)
    sigma0: float = float("nan")  # the pixels' a posteriori standard deviation of unit weight
    backend: str = "scipy"
    #: the non-reference cameras' parameters "<camera>.rx|ry|rz|vx|vy|vz" (rig-frame rotation of
    #: rig_from_cam, R = exp(r) R_estimate, and the centre v in the rig), the order of the two below
    camera_parameters: list[str] = field(default_factory=list)
    #: (6 C', 6 C') their covariance with the intrinsics held at their values (the std above)
    camera_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    #: (6 C', n) their change per unit change of each camera's intrinsics (the optimum's first-order
    #: response), to carry the intrinsics' errors into them; n = len(intrinsics_parameters),
    #: "<camera>.<name>" of every camera's model parameters (Camera.parameter_names), intrinsics_cameras' order
    intrinsics_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    intrinsics_cameras: list[str] = field(default_factory=list)
    intrinsics_parameters: list[str] = field(default_factory=list)
    #: the surveyed control points (P,) (the blocks' points with a survey sigma) and (6 C', 3 P) the
    #: cameras' parameters' change per one-sigma survey error of each along x, y, z (the optimum's
    #: response: the control points are held fixed, so their errors are not in camera_covariance)
    survey_points: list[str] = field(default_factory=list)
    survey_response: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    #: the survey sigma (m) of the points whose sigma the dataset does not give, estimated from the
    #: adjustment's residuals (`survey_variance`; their response made with it), their ids, and the number
    #: of observations of them; None, [] and 0 where every point's sigma is given (or exact)
    survey_sigma_m: float | None = None
    survey_estimated_points: list[str] = field(default_factory=list)
    survey_estimated_observations: int = 0


def _camera_sigmas(cameras, pixel_sigma: float | dict[str, float]) -> dict[str, float]:
    return {c: float(pixel_sigma[c]) if isinstance(pixel_sigma, dict) else float(pixel_sigma) for c in cameras}


class _RigProblem:
    """The whitened cost of eq. `min` in a chart around given poses; x0 (n_params,) encodes those poses.

    Parameter layout: 6 per non-reference camera (phi, c), then 6 per placement (psi, C_j).
    """

    def __init__(self, cameras: dict[str, Camera], reference: str, blocks: list[ImageBlock],
                 rig_from_cam: dict[str, Rigid3], rig_from_world: dict[str, Rigid3],
                 pixel_sigma: float | dict[str, float], center_sigma: float, use_priors: bool):
        self.cameras, self.reference, self.blocks = cameras, reference, blocks
        self.names = sorted({b.camera for b in blocks} - {reference})
        self.placements = sorted({b.placement for b in blocks})
        missing = ([c for c in self.names if c not in rig_from_cam]
                   + [p for p in self.placements if p not in rig_from_world])
        if missing:
            raise DmaisError(f"rig bundle adjustment: no initial value for {', '.join(missing)}")
        self.cam_index = {c: 6 * k for k, c in enumerate(self.names)}
        offset = 6 * len(self.names)
        self.pl_index = {p: offset + 6 * k for k, p in enumerate(self.placements)}
        self.n_params = offset + 6 * len(self.placements)
        self.Rc0 = {c: rig_from_cam[c].R for c in self.names}
        self.Rj0 = {p: rig_from_world[p].R for p in self.placements}
        self.x0 = np.zeros(self.n_params)
        for c in self.names:
            self.x0[self.cam_index[c] + 3: self.cam_index[c] + 6] = rig_from_cam[c].t
        for p in self.placements:
            self.x0[self.pl_index[p] + 3: self.pl_index[p] + 6] = rig_from_world[p].center
        self.sig = _camera_sigmas(cameras, pixel_sigma)
        self.center_sigma, self.use_priors = center_sigma, use_priors
        self.with_prior = [use_priors and b.center_prior is not None and bool(np.all(np.isfinite(b.center_prior)))
                           for b in blocks]
        self.rows, start = [], 0
        for b, prior in zip(blocks, self.with_prior):
            n_rows = 2 * len(b.X) + (3 if prior else 0)
            self.rows.append((start, n_rows))
            start += n_rows
        self.n_res = start
        if self.n_res < self.n_params:
            raise DmaisError(f"rig bundle adjustment: {self.n_res} residuals for {self.n_params} unknowns")

    def camera_params(self, p: np.ndarray, c: str):
        """(phi (3,), R_c (3, 3) rig_from_cam rotation, c (3,) centre in the rig)."""
        if c == self.reference:
            return np.zeros(3), np.eye(3), np.zeros(3)
        k = self.cam_index[c]
        return p[k:k + 3], exp_so3(p[k:k + 3]) @ self.Rc0[c], p[k + 3:k + 6]

    def placement_params(self, p: np.ndarray, j: str):
        """(psi (3,), R_j (3, 3) rig_from_world rotation, C_j (3,) rig origin in the world)."""
        k = self.pl_index[j]
        return p[k:k + 3], exp_so3(p[k:k + 3]) @ self.Rj0[j], p[k + 3:k + 6]

    def poses(self, p: np.ndarray) -> tuple[dict[str, Rigid3], dict[str, Rigid3]]:
        """rig_from_cam (every camera, reference = identity) and rig_from_world (every placement) at p."""
        rig_from_cam = {self.reference: Rigid3.identity()}
        for c in self.names:
            _, Rc, cc = self.camera_params(p, c)
            rig_from_cam[c] = Rigid3(Rc, cc)
        rig_from_world = {}
        for j in self.placements:
            _, Rj, Cj = self.placement_params(p, j)
            rig_from_world[j] = Rigid3(Rj, -Rj @ Cj)
        return rig_from_cam, rig_from_world

    def evaluate(self, p: np.ndarray, jacobian: bool):
        """Whitened residuals (n_res,) and, with `jacobian`, J (n_res, n_params)."""
        r = np.empty(self.n_res)
        J = np.zeros((self.n_res, self.n_params)) if jacobian else None
        for b, prior, (r0, nr) in zip(self.blocks, self.with_prior, self.rows):
            cam = self.cameras[b.camera]
            s = self.sig[b.camera]
            phi, Rc, c = self.camera_params(p, b.camera)
            psi, Rj, Cj = self.placement_params(p, b.placement)
            X_rig = (b.X - Cj) @ Rj.T
            v = X_rig - c
            X_cam = v @ Rc  # rows of Rc^T v
            n2 = 2 * len(b.X)
            out = project_unmasked(X_cam, cam, jacobian=jacobian)
            uv = out[0] if jacobian else out
            r[r0:r0 + n2] = (uv - b.uv).ravel() / s
            if prior:
                r[r0 + n2:r0 + nr] = (Cj + Rj.T @ c - b.center_prior) / self.center_sigma
            if not jacobian:
                continue
            J_cam = out[1] / s  # (n, 2, 3) d(pixel)/d(X_cam)
            RcT = Rc.T
            # placement: dX_rig/dpsi = -[X_rig]x J_l(psi), dX_rig/dC = -R_j; dX_cam/dX_rig = R_c^T
            dXr_dpsi = -skew(X_rig) @ left_jacobian_so3(psi)
            kj = self.pl_index[b.placement]
            J[r0:r0 + n2, kj:kj + 3] = (J_cam @ RcT @ dXr_dpsi).reshape(-1, 3)
            J[r0:r0 + n2, kj + 3:kj + 6] = (J_cam @ (RcT @ -Rj)).reshape(-1, 3)
            if b.camera != self.reference:
                # dX_cam/dphi = R_c^T [v]x J_l(phi), dX_cam/dc = -R_c^T
                kc = self.cam_index[b.camera]
                J[r0:r0 + n2, kc:kc + 3] = (J_cam @ (RcT @ skew(v)) @ left_jacobian_so3(phi)).reshape(-1, 3)
                J[r0:r0 + n2, kc + 3:kc + 6] = (J_cam @ -RcT).reshape(-1, 3)
            if prior:
                rr = slice(r0 + n2, r0 + nr)
                J[rr, kj:kj + 3] = Rj.T @ skew(c) @ left_jacobian_so3(psi) / self.center_sigma
                J[rr, kj + 3:kj + 6] = np.eye(3) / self.center_sigma
                if b.camera != self.reference:
                    J[rr, kc + 3:kc + 6] = Rj.T / self.center_sigma
        return (r, J) if jacobian else r

    def gradient_cosine(self, p: np.ndarray) -> float:
        """max_k |J_k . r| / (|J_k| |r|): 0 at a stationary point of the cost, scale-free."""
        r, J = self.evaluate(p, True)
        norms = np.linalg.norm(J, axis=0) * max(np.linalg.norm(r), 1e-300)
        return float(np.max(np.abs(J.T @ r) / np.where(norms > 0, norms, 1.0)))

    def solve(self, p0: np.ndarray, max_nfev: int) -> np.ndarray:
        """Levenberg-Marquardt from p0 (n_params,); returns the optimum (n_params,)."""
        sol = least_squares(lambda p: self.evaluate(p, False), p0, jac=lambda p: self.evaluate(p, True)[1],
                            method="lm", x_scale="jac", xtol=TOLERANCE, ftol=TOLERANCE, gtol=TOLERANCE,
                            max_nfev=max_nfev)
        return sol.x

    def recentred(self, p: np.ndarray) -> "_RigProblem":
        """The same problem in the chart around the poses at p (its x0 encodes them with zero rotation vectors)."""
        rig_from_cam, rig_from_world = self.poses(p)
        return _RigProblem(self.cameras, self.reference, self.blocks, rig_from_cam, rig_from_world, self.sig,
                           self.center_sigma, self.use_priors)

    def result(self, p: np.ndarray, backend: str) -> RigBAResult:
        """Poses, residuals, RMS and standard deviations (from J at p) as a RigBAResult.

        Call it on a recentred problem (p = x0) so that rotation deviations are small rotations about the estimate.
        """
        r, J = self.evaluate(p, True)
        inverse = inverse_normal(J)
        survey_points, survey_sigma, unit = self.survey_jacobian(p)
        J_intrinsics = self.intrinsics_jacobian(p)
        survey_sigma, estimated = self._survey_sigmas(J, r, inverse, survey_points, survey_sigma, unit)
        sigma0_sq, cov = self._covariance(J, r, inverse, np.hstack([unit, J_intrinsics]))
        std_all = np.sqrt(np.clip(np.diag(cov), 0, None))
        camera_rows = np.arange(6 * len(self.names))  # the cameras' parameters come first
        sensitivity = -inverse @ J.T @ J_intrinsics
        survey_response = -inverse @ J.T @ (unit * np.repeat(survey_sigma, 3))
        std = {self.reference: {"rotation_deg": [0.0, 0.0, 0.0], "center_m": [0.0, 0.0, 0.0]}}
        for c in self.names:
            k = self.cam_index[c]
            std[c] = {"rotation_deg": np.degrees(std_all[k:k + 3]).tolist(), "center_m": std_all[k + 3:k + 6].tolist()}
        out_cam, out_pl = self.poses(p)
        residuals, prior_res = {}, {}
        per_camera: dict[str, list[np.ndarray]] = {}
        for b, prior, (r0, nr) in zip(self.blocks, self.with_prior, self.rows):
            n2 = 2 * len(b.X)
            res = (r[r0:r0 + n2] * self.sig[b.camera]).reshape(-1, 2)
            residuals[b.image] = res
            per_camera.setdefault(b.camera, []).append(res)
            if prior:
                prior_res[b.image] = r[r0 + n2:r0 + nr] * self.center_sigma
        rms = {c: float(np.sqrt(np.mean(np.sum(np.vstack(v) ** 2, axis=1)))) for c, v in per_camera.items()}
        n_obs = {c: int(sum(len(x) for x in v)) for c, v in per_camera.items()}
        return RigBAResult(rig_from_cam=out_cam, rig_from_world=out_pl, residuals=residuals, rms_px=rms,
                           n_observations=n_obs, std=std, prior_residuals_m=prior_res,
                           sigma0=float(np.sqrt(sigma0_sq)), backend=backend,
                           camera_parameters=[f"{c}.{k}" for c in self.names
                                              for k in ("rx", "ry", "rz", "vx", "vy", "vz")],
                           camera_covariance=cov[np.ix_(camera_rows, camera_rows)],
                           intrinsics_sensitivity=sensitivity[camera_rows], intrinsics_cameras=list(self.cameras),
                           intrinsics_parameters=[f"{c}.{k}" for c, cam in self.cameras.items()
                                                  for k in cam.parameter_names],
                           survey_points=survey_points, survey_response=survey_response[camera_rows],
                           **estimated)

    def pixel_rows(self) -> np.ndarray:
        """(n_res,) bool: the residuals that are pixels (not the camera-centre priors)."""
        rows = np.zeros(self.n_res, dtype=bool)
        for b, (r0, _) in zip(self.blocks, self.rows):
            rows[r0:r0 + 2 * len(b.X)] = True
        return rows

    def _covariance(self, J: np.ndarray, r: np.ndarray, inverse: np.ndarray, nuisance: np.ndarray
                    ) -> tuple[float, np.ndarray]:
        """The pixel rows' variance of unit weight and the parameters' covariance (n_params, n_params).

        The variance is the pixel noise's alone (`survey_variance.pixel_variance`: the residuals outside
        the span of the survey's and the intrinsics' effects, `nuisance` (n_res, q), which are the same
        in every placement and are carried into the calibration covariance by the survey response and
        the intrinsics sensitivity; counted as noise too, they made the rig's pixel share ~5.5 times
        its error along the flight's x and y (24 simulated calibrations)). The priors keep their sigma:
        cov = N^-1 (s^2 J_pixel^T J_pixel + J_prior^T J_prior) N^-1. Where no pixel dimension lies
        outside that span, s^2 is the residuals' r.r / dof, the whole covariance scaled by it."""
        pixel = self.pixel_rows()
        variance = pixel_variance(J, r, nuisance, pixel)
        if not np.isfinite(variance):
            variance = float(r @ r) / max(self.n_res - self.n_params, 1)
            return variance, inverse * variance
        weighted = variance * (J[pixel].T @ J[pixel]) + J[~pixel].T @ J[~pixel]
        return variance, inverse @ weighted @ inverse

    @staticmethod
    def _survey_sigmas(J: np.ndarray, r: np.ndarray, inverse: np.ndarray, points: list[str],
                       survey_sigma: np.ndarray, unit: np.ndarray) -> tuple[np.ndarray, dict]:
        """The survey points' (P,) sigmas and RigBAResult's survey_sigma_m, survey_estimated_points and
        survey_estimated_observations: the points' sigma not given (NaN) estimated from the residuals
        (`survey_variance.estimate`), the survey's share carried by the response."""
        unknown = np.isnan(survey_sigma)
        if not unknown.any():
            return survey_sigma, {}
        columns = np.repeat(unknown, 3)
        given = unit[:, ~columns] * np.repeat(survey_sigma[~unknown], 3)
        found = estimate_survey_variance(J, r, unit[:, columns], given, inverse)
        observations = int(np.count_nonzero(np.any(unit[:, columns] != 0, axis=1))) // 2
        ids = [point for point, free in zip(points, unknown) if free]
        return (np.where(unknown, found.survey_sigma, survey_sigma),
                {"survey_sigma_m": found.survey_sigma, "survey_estimated_points": ids,
                 "survey_estimated_observations": observations})

    def intrinsics_jacobian(self, p: np.ndarray) -> np.ndarray:
        """(n_res, n) the whitened residuals' derivatives with respect to every camera's model
        parameters (Camera.parameter_names), the cameras in self.cameras' order."""
        sizes = [len(cam.parameter_names) for cam in self.cameras.values()]
        start = dict(zip(self.cameras, np.cumsum([0] + sizes)))
        J = np.zeros((self.n_res, sum(sizes)))
        for b, (r0, _) in zip(self.blocks, self.rows):
            cam = self.cameras[b.camera]
            _, Rc, c = self.camera_params(p, b.camera)
            _, Rj, Cj = self.placement_params(p, b.placement)
            X_cam = ((b.X - Cj) @ Rj.T - c) @ Rc
            J_intrinsics = project_unmasked(X_cam, cam, jacobian=True)[2]
            k, size = start[b.camera], J_intrinsics.shape[2]
            J[r0:r0 + 2 * len(b.X), k:k + size] = J_intrinsics.reshape(-1, size) / self.sig[b.camera]
        return J

    def survey_jacobian(self, p: np.ndarray) -> tuple[list[str], np.ndarray, np.ndarray]:
        """The control points not taken as exact (P,) (the blocks' points with a survey sigma above 0, or
        NaN: not given), their sigmas (P,) and (n_res, 3 P) the whitened residuals' change per metre of
        error of each point's coordinates along x, y, z (the same point in every image that sees it)."""
        given = [(b, r0) for b, (r0, _) in zip(self.blocks, self.rows)
                 if b.point_ids is not None and b.point_sigma is not None]
        sigma_of = {str(i): float(sigma) for b, _ in given for i, sigma in zip(b.point_ids, b.point_sigma)
                    if not sigma <= 0}
        ids = sorted(sigma_of)
        column = {point: 3 * k for k, point in enumerate(ids)}
        J = np.zeros((self.n_res, 3 * len(ids)))
        for b, r0 in given:
            cam = self.cameras[b.camera]
            _, Rc, c = self.camera_params(p, b.camera)
            _, Rj, Cj = self.placement_params(p, b.placement)
            X_cam = ((b.X - Cj) @ Rj.T - c) @ Rc
            J_cam = project_unmasked(X_cam, cam, jacobian=True)[1]
            d_point = J_cam @ (Rc.T @ Rj) / self.sig[b.camera]  # (n, 2, 3): X_cam = R_c^T R_j (X - C_j) - ...
            for row, point in enumerate(b.point_ids):
                k = column.get(str(point))
                if k is not None:
                    J[r0 + 2 * row:r0 + 2 * row + 2, k:k + 3] = d_point[row]
        return ids, np.array([sigma_of[point] for point in ids]), J


def refine_rig(cameras: dict[str, Camera], reference: str, blocks: list[ImageBlock],
               rig_from_cam: dict[str, Rigid3], rig_from_world: dict[str, Rigid3], *,
               pixel_sigma: float | dict[str, float] = 0.3, center_sigma: float = 0.02,
               use_priors: bool = True, max_nfev: int = 200) -> RigBAResult:
    """Levenberg-Marquardt over extrinsics (reference fixed) and placement poses (eq. `min`).

    rig_from_cam: initial value for every camera of `blocks` (the reference's is ignored: identity);
    rig_from_world: initial value for every placement of `blocks`. `pixel_sigma` (per camera or one
    value) and `center_sigma` weight the reprojection and prior terms.
    """
    problem = _RigProblem(cameras, reference, blocks, rig_from_cam, rig_from_world, pixel_sigma, center_sigma,
                          use_priors)
    return _solved_by_scipy(problem, max_nfev)


def _solved_by_scipy(problem: _RigProblem, max_nfev: int) -> RigBAResult:
    at_optimum = problem.recentred(problem.solve(problem.x0, max_nfev))
    return at_optimum.result(at_optimum.x0, "scipy")


# ------------------------------------------------------------------------------ pycolmap backend


def colmap_rigid(T: Rigid3):
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(T.R), T.t)


def _rigid(T) -> Rigid3:
    """Our Rigid3 from a pycolmap.Rigid3d."""
    return Rigid3(T.rotation.matrix(), T.translation)


@dataclass
class _ColmapScene:
    """A pycolmap.Reconstruction of the rig problem and the ids needed to read it back."""

    reconstruction: object
    camera_ids: dict[str, int]  # camera name -> camera id (= sensor id)
    frame_ids: dict[str, int]  # placement -> frame id
    image_ids: list[int]  # per block
    points: np.ndarray  # (m, 3) unique control points
    point_ids: list[int]  # (m,) their 3D point ids
    shadow_camera_id: int  # the unit pinhole camera of the shadow images
    shadow_image_ids: list[int]  # per block, its shadow image (see _build_scene)
    shadow_frame_ids: list[int]  # per block, the shadow image's frame (constant pose)
    shadow_centres: np.ndarray  # (n_blocks, 3) the shadow images' (= the blocks' initial) camera centres


def colmap_pixels(uv: np.ndarray) -> np.ndarray:
    """Our pixel coordinates (n, 2) in COLMAP's convention (n, 2).

    We follow OpenCV (the centre of the top-left pixel is (0, 0)); COLMAP puts the image's top-left
    corner at (0, 0), so that pixel's centre is at (0.5, 0.5).
    """
    return np.asarray(uv, dtype=float) + COLMAP_PIXEL_OFFSET


def opencv_params(camera: Camera, sigma: float = 1.0) -> tuple[str, list[float]]:
    """The COLMAP model and parameters exactly equal to `camera`: OPENCV (fx, fy, cx, cy, k1, k2, p1,
    p2; radial1 is k1 = d, the rest 0) or, for an opencv camera with k3 != 0, FULL_OPENCV (the same
    then k3, k4 = k5 = k6 = 0); in COLMAP's pixel convention (cx, cy shifted by `colmap_pixels`), with
    the pixel-valued ones divided by sigma."""
    cx, cy = colmap_pixels([camera.cx, camera.cy])
    k1, k2, p1, p2, k3 = camera.distortion
    params = [camera.fx / sigma, camera.fy / sigma, cx / sigma, cy / sigma, k1, k2, p1, p2]
    return ("OPENCV", params) if k3 == 0 else ("FULL_OPENCV", params + [k3, 0.0, 0.0, 0.0])


def colmap_camera(camera: Camera, camera_id: int, sigma: float = 1.0):
    """The COLMAP camera equal to `camera` (`opencv_params`; principal point + 0.5 px) with pixels
    scaled by 1 / sigma, so that residuals are whitened (sigma 1: the camera itself)."""
    import pycolmap

    model, params = opencv_params(camera, sigma)
    return pycolmap.Camera(camera_id=camera_id, model=model, width=max(1, round(camera.width / sigma)),
                           height=max(1, round(camera.height / sigma)), params=params)


def add_colmap_rig(rec, cameras: dict[str, Camera], names: list[str], rig_from_cam: dict[str, Rigid3],
                   sig: dict[str, float] | None = None) -> dict[str, int]:
    """Cameras (ids 1, 2, ... in the order of `names`, pixels scaled by 1 / sig[c], default 1) and
    rig 1 (reference sensor names[0]); returns camera name -> camera id."""
    import pycolmap

    camera_ids = {c: k + 1 for k, c in enumerate(names)}
    for c, cid in camera_ids.items():
        rec.add_camera(colmap_camera(cameras[c], cid, sig[c] if sig else 1.0))
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(rec.cameras[camera_ids[names[0]]].sensor_id)
    for c in names[1:]:
        rig.add_sensor(rec.cameras[camera_ids[c]].sensor_id, colmap_rigid(rig_from_cam[c].inverse()))
    rec.add_rig(rig)
    return camera_ids


def add_colmap_frame(rec, frame_id: int, rig_id: int, rig_from_world: Rigid3, images: list) -> None:
    import pycolmap

    frame = pycolmap.Frame(frame_id=frame_id, rig_id=rig_id)
    frame.rig_from_world = colmap_rigid(rig_from_world)
    for image in images:
        image.frame_id = frame_id
        frame.add_data_id(image.data_id)
    rec.add_frame(frame)
    for image in images:
        rec.add_image(image)
    rec.register_frame(frame_id)


def _unique_points(blocks: list[ImageBlock]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Distinct control points (m, 3) and, per block, the index of each observation's point."""
    points, index = np.unique(np.vstack([b.X for b in blocks]), axis=0, return_inverse=True)
    index = index.ravel()
    return points, np.split(index, np.cumsum([len(b.X) for b in blocks])[:-1])


def _build_scene(cameras: dict[str, Camera], reference: str, blocks: list[ImageBlock],
                 rig_from_cam: dict[str, Rigid3], rig_from_world: dict[str, Rigid3],
                 sig: dict[str, float]) -> _ColmapScene:
    """Reconstruction with rig 1 (the cameras), one frame per placement, one image per block, plus shadows.

    Every block also gets a "shadow" image: rig 2, a unit pinhole camera at the block's initial pose,
    held constant, observing the block's points at their exact projections. Its observations are
    constant zero-residual terms that change nothing, but they give every control point the two
    observations COLMAP requires, and their centres anchor the pose-prior alignment (`_solve_colmap`).
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    names = [reference] + sorted({b.camera for b in blocks} - {reference})
    camera_ids = add_colmap_rig(rec, cameras, names, rig_from_cam, sig)
    frame_ids = {j: k + 1 for k, j in enumerate(sorted({b.placement for b in blocks}))}
    image_ids = list(range(1, len(blocks) + 1))
    for j, fid in frame_ids.items():
        images = [pycolmap.Image(name=b.image, keypoints=colmap_pixels(b.uv) / sig[b.camera],
                                 camera_id=camera_ids[b.camera], image_id=image_id)
                  for b, image_id in zip(blocks, image_ids) if b.placement == j]
        add_colmap_frame(rec, fid, 1, rig_from_world[j], images)

    points, block_points = _unique_points(blocks)
    tracks = [pycolmap.Track() for _ in points]
    for image_id, idx in zip(image_ids, block_points):
        for n, i in enumerate(idx):
            tracks[i].add_element(image_id, n)
    shadow_camera_id = len(names) + 1
    shadow_image_ids = list(range(len(blocks) + 1, 2 * len(blocks) + 1))
    shadow_frame_ids = list(range(len(frame_ids) + 1, len(frame_ids) + len(blocks) + 1))
    centres = _add_shadows(rec, blocks, block_points, points, tracks, rig_from_cam, rig_from_world,
                           shadow_image_ids, shadow_frame_ids, shadow_camera_id)
    point_ids = [rec.add_point3D(x, track) for x, track in zip(points, tracks)]
    return _ColmapScene(rec, camera_ids, frame_ids, image_ids, points, point_ids, shadow_camera_id,
                        shadow_image_ids, shadow_frame_ids, centres)


def _add_shadows(rec, blocks, block_points, points, tracks, rig_from_cam, rig_from_world, image_ids, frame_ids,
                 camera_id: int) -> np.ndarray:
    """The shadow image of every block (see `_build_scene`), appended to `tracks`; returns their centres (n, 3)."""
    import pycolmap

    rec.add_camera(pycolmap.Camera(camera_id=camera_id, model="PINHOLE", width=1, height=1,
                                   params=[1.0, 1.0, 0.0, 0.0]))
    rig = pycolmap.Rig(rig_id=2)
    rig.add_ref_sensor(rec.cameras[camera_id].sensor_id)
    rec.add_rig(rig)
    centres = []
    for b, idx, image_id, frame_id in zip(blocks, block_points, image_ids, frame_ids):
        cam_from_world = rig_from_cam[b.camera].inverse() * rig_from_world[b.placement]
        X_cam = cam_from_world.apply(points[idx])
        image = pycolmap.Image(name=f"shadow of {b.image}", keypoints=X_cam[:, :2] / X_cam[:, 2:],
                               camera_id=camera_id, image_id=image_id)
        add_colmap_frame(rec, frame_id, 2, cam_from_world, [image])
        for q, i in enumerate(idx):
            tracks[i].add_element(image_id, q)
        centres.append(cam_from_world.center)
    return np.array(centres)


def _ba_options(max_iterations: int):
    import pycolmap

    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_focal_length = False
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.refine_points3D = False
    solver = options.ceres.solver_options
    solver.max_num_iterations = max_iterations
    solver.function_tolerance = 1e-16
    solver.gradient_tolerance = 1e-16
    solver.parameter_tolerance = 1e-16
    solver.num_threads = 1
    return options


def _ba_config(scene: _ColmapScene):
    import pycolmap

    config = pycolmap.BundleAdjustmentConfig()
    for image_id in scene.image_ids + scene.shadow_image_ids:
        config.add_image(image_id)
    for frame_id in scene.shadow_frame_ids:
        config.set_constant_rig_from_world_pose(frame_id)
    for point_id in scene.point_ids:
        config.add_constant_point(point_id)
    for camera_id in [*scene.camera_ids.values(), scene.shadow_camera_id]:
        config.set_constant_cam_intrinsics(camera_id)
    return config


def _pose_priors(scene: _ColmapScene, blocks: list[ImageBlock], with_prior: list[bool], center_sigma: float):
    """pycolmap.PosePrior per block with a prior, and one at every shadow image's exact centre (none without priors)."""
    import pycolmap

    def prior(image_id: int, position) -> object:
        return pycolmap.PosePrior(position=np.asarray(position, dtype=float),
                                  position_covariance=center_sigma**2 * np.eye(3),
                                  coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
                                  corr_data_id=scene.reconstruction.images[image_id].data_id)

    priors = [prior(image_id, b.center_prior) for b, image_id, used in zip(blocks, scene.image_ids, with_prior)
              if used]
    if priors:
        priors += [prior(image_id, c) for image_id, c in zip(scene.shadow_image_ids, scene.shadow_centres)]
    return priors


def _solve_colmap(scene: _ColmapScene, blocks, with_prior, center_sigma: float, max_iterations: int):
    """Run pycolmap's bundle adjuster on the scene in place; returns the solver summary.

    With priors, `create_pose_prior_bundle_adjuster` first moves the whole reconstruction, constant
    control points included, by a similarity aligning the image centres to their priors (RANSAC).
    The shadow images sit exactly at their priors and every real image misses its prior by far more
    than ALIGNMENT_MAX_ERROR_M, so the inliers are the shadows and the similarity is the identity.
    """
    import pycolmap

    options, config = _ba_options(max_iterations), _ba_config(scene)
    priors = _pose_priors(scene, blocks, with_prior, center_sigma)
    if not priors:
        adjuster = pycolmap.create_default_bundle_adjuster(options, config, scene.reconstruction)
    else:
        prior_options = pycolmap.PosePriorBundleAdjustmentOptions()
        prior_options.prior_position_fallback_stddev = center_sigma
        prior_options.alignment_ransac.max_error = ALIGNMENT_MAX_ERROR_M
        prior_options.alignment_ransac.random_seed = 0
        adjuster = pycolmap.create_pose_prior_bundle_adjuster(options, prior_options, config, priors,
                                                              scene.reconstruction)
    return adjuster.solve()


def _read_poses(scene: _ColmapScene, reference: str) -> tuple[dict[str, Rigid3], dict[str, Rigid3]]:
    rec = scene.reconstruction
    rig = rec.rigs[1]
    rig_from_cam = {reference: Rigid3.identity()}
    for c, cid in scene.camera_ids.items():
        if c != reference:
            rig_from_cam[c] = _rigid(rig.sensor_from_rig(rec.cameras[cid].sensor_id)).inverse()
    rig_from_world = {j: _rigid(rec.frames[fid].rig_from_world) for j, fid in scene.frame_ids.items()}
    return rig_from_cam, rig_from_world


def _points_moved(scene: _ColmapScene) -> float:
    """Largest displacement (m) of the constant control points during the adjustment."""
    rec = scene.reconstruction
    moved = [np.linalg.norm(rec.points3D[k].xyz - x) for k, x in zip(scene.point_ids, scene.points)]
    return float(max(moved))


def _colmap_optimum(problem: _RigProblem, max_nfev: int) -> tuple[dict[str, Rigid3], dict[str, Rigid3], float]:
    """pycolmap's optimum from problem.x0: rig_from_cam, rig_from_world and how far the control points moved (m)."""
    start_cam, start_world = problem.poses(problem.x0)
    scene = _build_scene(problem.cameras, problem.reference, problem.blocks, start_cam, start_world, problem.sig)
    summary = _solve_colmap(scene, problem.blocks, problem.with_prior, problem.center_sigma, max_nfev)
    log.debug("rig BA (pycolmap): %s", summary.termination_type)
    return (*_read_poses(scene, problem.reference), _points_moved(scene))


def refine_rig_pycolmap(cameras: dict[str, Camera], reference: str, blocks: list[ImageBlock],
                        rig_from_cam: dict[str, Rigid3], rig_from_world: dict[str, Rigid3], *,
                        pixel_sigma: float | dict[str, float] = 0.3, center_sigma: float = 0.02,
                        use_priors: bool = True, max_nfev: int = 200) -> RigBAResult:
    """`refine_rig` (same inputs and result) solved by pycolmap's rig bundle adjuster.

    Reference camera = the rig's reference sensor, placements = frames, control points constant,
    intrinsics constant, sensor_from_rig and rig_from_world refined. Two adaptations make COLMAP's
    cost exactly ours:

    - Per-camera pixel weights: COLMAP weighs all reprojection residuals alike, so each camera's
      pixels (intrinsics and observations) are scaled by 1 / pixel_sigma (the residual becomes
      pixel / sigma; the normalized coordinates and d are unchanged).
    - Camera-centre priors go through `create_pose_prior_bundle_adjuster`, which first moves the whole
      reconstruction, constant control points included, by the similarity aligning the image centres
      to the priors (with the rig turned in place the centres span a few decimetres, so that
      similarity is far from the identity: 5 % scale and 4 deg on the simulator). Constant shadow
      images lying exactly on priors of their own make that alignment the identity (`_solve_colmap`),
      so the control points stay put and the solve starts from our initial poses.

    The result is checked against our own cost (control points unmoved, gradient ~ 0). If a check
    fails, or a placement holds two images of one camera (a COLMAP frame cannot), the problem is
    solved by `refine_rig` instead, with a warning, and the result's `backend` is "scipy".
    Standard deviations come from our analytic Jacobian at the optimum (`_RigProblem.result`), not
    from pycolmap's covariance estimator (it expects variable 3D points, the Schur structure).
    """
    problem = _RigProblem(cameras, reference, blocks, rig_from_cam, rig_from_world, pixel_sigma, center_sigma,
                          use_priors)
    if len({(b.placement, b.camera) for b in blocks}) < len(blocks):
        log.warning("rig bundle adjustment: a placement holds several images of one camera, which a COLMAP frame "
                    "cannot; using scipy")
        return _solved_by_scipy(problem, max_nfev)
    cams, world, moved = _colmap_optimum(problem, max_nfev)
    at_optimum = _RigProblem(cameras, reference, blocks, cams, world, pixel_sigma, center_sigma, use_priors)
    cosine = at_optimum.gradient_cosine(at_optimum.x0)
    log.debug("rig BA (pycolmap): control points moved %.2e m, gradient cosine %.2e", moved, cosine)
    if moved > MAX_POINT_MOTION_M or cosine > MAX_GRADIENT_COSINE:
        log.warning("rig bundle adjustment: pycolmap's solution is not the optimum of our cost (control points "
                    "moved %.2e m, gradient cosine %.2e); solving with scipy instead", moved, cosine)
        return _solved_by_scipy(problem, max_nfev)
    return at_optimum.result(at_optimum.x0, "pycolmap")


def refine(backend: str, *args, **kwargs) -> RigBAResult:
    """`refine_rig` or `refine_rig_pycolmap` by backend name ("scipy" or "pycolmap")."""
    if backend == "scipy":
        return refine_rig(*args, **kwargs)
    if backend == "pycolmap":
        return refine_rig_pycolmap(*args, **kwargs)
    raise DmaisError(f"rig bundle adjustment: unknown backend {backend!r}; use one of {', '.join(BACKENDS)}")
