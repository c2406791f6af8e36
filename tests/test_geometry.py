"""Tests of rotations (Cayley, quaternion, ZYX Euler, SO(3) exp/log/Jacobians), error metrics, averaging and Rigid3."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from dmais_pipe.errors import DmaisError, GeometryError
from dmais_pipe.geometry import (
    Rigid3,
    average_rotations,
    cayley_from_rotation,
    euler_zyx_from_rotation,
    exp_so3,
    left_jacobian_so3,
    log_so3,
    pose_jacobian,
    quat_from_rotation,
    rotation_angle,
    rotation_error,
    rotation_from_cayley,
    rotation_from_euler_zyx,
    rotation_from_quat,
    skew,
    translation_error,
)


def random_rotations(n: int, seed: int) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_matrix()


def paper_cayley_matrix(qx: float, qy: float, qz: float) -> np.ndarray:
    """The paper's Cayley rotation matrix, written out literally."""
    return np.array([
        [1 + qx**2 - qy**2 - qz**2, 2 * qx * qy - 2 * qz, 2 * qy + 2 * qx * qz],
        [2 * qx * qy + 2 * qz, 1 - qx**2 + qy**2 - qz**2, 2 * qy * qz - 2 * qx],
        [2 * qx * qz - 2 * qy, 2 * qx + 2 * qy * qz, 1 - qx**2 - qy**2 + qz**2],
    ]) / (1 + qx**2 + qy**2 + qz**2)


def Rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def Ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def Rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def assert_rotation(R: np.ndarray, atol: float = 1e-12) -> None:
    R = np.asarray(R).reshape(-1, 3, 3)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=atol)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=atol)


# ------------------------------------------------------------------------------------- skew


def test_skew_is_cross_product_matrix():
    rng = np.random.default_rng(0)
    for _ in range(10):
        a, b = rng.normal(size=3), rng.normal(size=3)
        np.testing.assert_allclose(skew(a) @ b, np.cross(a, b), atol=1e-15)
        np.testing.assert_array_equal(skew(a), -skew(a).T)


def test_skew_is_vectorised_over_rows():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
    S = skew(a)
    assert S.shape == (7, 3, 3)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", S, b), np.cross(a, b), atol=1e-15)
    for k in range(7):
        np.testing.assert_array_equal(S[k], skew(a[k]))
    assert skew(np.zeros((0, 3))).shape == (0, 3, 3)


@pytest.mark.parametrize("shape", [(2,), (4,), (3, 2), (2, 3, 3)])
def test_skew_rejects_other_shapes(shape):
    with pytest.raises(GeometryError):
        skew(np.ones(shape))


# ------------------------------------------------------------------------------- SO(3) exp and log

# Rotation angles from 0 through tiny (series territory) and moderate to pi and just below it.
ANGLES = [0.0, 1e-12, 1e-8, 1e-6, 1e-3, 0.5, 2.0, np.pi - 1e-3, np.pi - 1e-7, np.pi - 1e-10]


def rotvecs_at(angles, seed: int) -> np.ndarray:
    """(len(angles), 3) rotation vectors of the given lengths about random axes."""
    axes = np.random.default_rng(seed).normal(size=(len(angles), 3))
    return axes / np.linalg.norm(axes, axis=1, keepdims=True) * np.asarray(angles)[:, None]


def rodrigues(axis, angle) -> np.ndarray:
    """cos a I + sin a [k]x + (1 - cos a) k k^T for a unit axis k, written out."""
    k = np.asarray(axis, dtype=float)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.cos(angle) * np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * np.outer(k, k)


def test_exp_so3_is_the_matrix_exponential_of_skew():
    phis = rotvecs_at(ANGLES, seed=3)
    R = exp_so3(phis)
    assert R.shape == (len(ANGLES), 3, 3)
    for phi, Rk in zip(phis, R):
        np.testing.assert_allclose(Rk, expm(skew(phi)), rtol=0, atol=1e-14)
        np.testing.assert_array_equal(exp_so3(phi), Rk)
    assert_rotation(R)


@pytest.mark.parametrize("angle", ANGLES + [np.pi])
def test_exp_so3_is_rodrigues(angle):
    axis = np.array([2.0, -1.0, 0.5]) / np.linalg.norm([2.0, -1.0, 0.5])
    np.testing.assert_allclose(exp_so3(angle * axis), rodrigues(axis, angle), rtol=0, atol=1e-15)


@pytest.mark.parametrize("angle", ANGLES)
def test_log_so3_inverts_rodrigues(angle):
    """log of an angle-axis rotation built without scipy gives its rotation vector back; near 0 the
    vector keeps its relative accuracy, near pi its direction."""
    axis = np.array([-0.3, 0.4, 0.2]) / np.linalg.norm([-0.3, 0.4, 0.2])
    phi = log_so3(rodrigues(axis, angle))
    assert phi.shape == (3,)
    # Near pi the matrix fixes the angle to ~sqrt(eps) only: |R - R'| ~ (pi - a) da for nearby angles.
    atol = 1e-15 if angle < 3.0 else 2e-8
    np.testing.assert_allclose(phi, angle * axis, rtol=1e-9, atol=atol)


def test_log_so3_at_pi_gives_an_axis_of_the_rotation():
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    phi = log_so3(rodrigues(axis, np.pi))
    assert np.linalg.norm(phi) == pytest.approx(np.pi, abs=1e-12)
    assert abs(phi @ axis) == pytest.approx(np.pi, abs=1e-12)  # +-axis: both are the same rotation
    np.testing.assert_allclose(exp_so3(phi), rodrigues(axis, np.pi), atol=1e-14)


def test_log_so3_is_vectorised_and_matches_scipy_rotvec():
    phis = rotvecs_at(ANGLES, seed=4)
    R = np.array([rodrigues(p / max(np.linalg.norm(p), 1e-300), np.linalg.norm(p)) for p in phis])
    logs = log_so3(R)
    assert logs.shape == (len(ANGLES), 3)
    np.testing.assert_allclose(logs, Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(exp_so3(logs), R, rtol=0, atol=1e-14)


# ------------------------------------------------------------------------------- Jacobians


def numeric_left_jacobian(phi, h: float = 1e-6) -> np.ndarray:
    """Central differences of log(exp(phi + h e_k) exp(phi)^T) / h: the definition of J_l."""
    R = exp_so3(phi)
    columns = [(log_so3(exp_so3(phi + h * e) @ R.T) - log_so3(exp_so3(phi - h * e) @ R.T)) / (2.0 * h)
               for e in np.eye(3)]
    return np.column_stack(columns)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 5e-7, 1e-3, 0.4, 1.5, 2.8])
def test_left_jacobian_so3_is_the_derivative_of_exp(angle):
    """Both branches (the series below 1e-6 and the closed form) against finite differences."""
    phi = rotvecs_at([angle], seed=5)[0]
    np.testing.assert_allclose(left_jacobian_so3(phi), numeric_left_jacobian(phi), rtol=0, atol=1e-8)


def test_left_jacobian_so3_fixes_phi_and_is_continuous_at_the_series_switch():
    phi = np.array([0.3, -0.9, 1.1])
    np.testing.assert_allclose(left_jacobian_so3(phi) @ phi, phi, atol=1e-15)  # J_l(phi) phi = phi
    axis = np.array([1.0, 1.0, -1.0]) / np.sqrt(3.0)
    below, above = left_jacobian_so3((1e-6 - 1e-15) * axis), left_jacobian_so3((1e-6 + 1e-15) * axis)
    # the closed form's 1 - cos(theta) keeps only ~eps / theta^2 = 1e-4 of relative accuracy at the
    # switch: 5e-11 on the 0.5 [phi]x term (dropping that term would differ by 5e-7)
    np.testing.assert_allclose(below, above, rtol=0, atol=1e-10)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 0.02, 2.0])
def test_pose_jacobian_is_the_derivative_of_the_transformed_points(angle):
    """With J_point = I the chain rule gives d(exp(phi) R0 X + t)/d(phi, t): compared with central differences."""
    rng = np.random.default_rng(6)
    X, R0, t = rng.normal(0.0, 10.0, (5, 3)), random_rotations(1, seed=7)[0], rng.normal(size=3)
    phi = rotvecs_at([angle], seed=8)[0]

    def transformed(p):
        return X @ (exp_so3(p[:3]) @ R0).T + p[3:]

    p0, h = np.concatenate([phi, t]), 1e-6
    numeric = np.stack([(transformed(p0 + h * e) - transformed(p0 - h * e)) / (2.0 * h) for e in np.eye(6)], axis=2)
    J = pose_jacobian(X, exp_so3(phi) @ R0, phi, np.broadcast_to(np.eye(3), (5, 3, 3)))
    assert J.shape == (5, 3, 6)
    np.testing.assert_allclose(J, numeric, rtol=0, atol=1e-7)


# The removed calib/_projection.py's outputs (commit c2e85e5), captured before it went.
PROJECTION_REFERENCE = Path(__file__).parent / "data" / "projection_reference.npz"


def test_exp_and_left_jacobian_equal_the_removed_projection_module():
    ref = np.load(PROJECTION_REFERENCE)
    for phi, R, J in zip(ref["phis"], ref["exp_so3"], ref["left_jacobian"]):
        np.testing.assert_allclose(exp_so3(phi), R, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(left_jacobian_so3(phi), J, rtol=1e-12, atol=1e-15)


# ------------------------------------------------------------------------------------- Cayley

CAYLEY_SAMPLES = [
    (0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.0, -0.7, 0.0), (0.0, 0.0, 2.5),
    (0.1, -0.2, 0.3), (-1.5, 0.8, 0.05), (10.0, -20.0, 5.0), (1e-9, 2e-9, -3e-9),
]


@pytest.mark.parametrize("q", CAYLEY_SAMPLES)
def test_rotation_from_cayley_is_paper_matrix(q):
    np.testing.assert_allclose(rotation_from_cayley(np.array(q)), paper_cayley_matrix(*q), rtol=0, atol=1e-15)


@pytest.mark.parametrize("q", CAYLEY_SAMPLES)
def test_rotation_from_cayley_matches_scipy_rotvec(q):
    """Cayley q = tan(theta / 2) * axis, i.e. the rotation vector 2 atan(|q|) q / |q|."""
    q = np.array(q)
    norm = np.linalg.norm(q)
    rotvec = np.zeros(3) if norm == 0 else 2.0 * np.arctan(norm) * q / norm
    R = rotation_from_cayley(q)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rotvec).as_matrix(), rtol=0, atol=1e-14)
    assert_rotation(R)


def test_cayley_is_the_cayley_transform_of_skew():
    """R = (I + [q]x)(I - [q]x)^-1, the classical Cayley transform."""
    rng = np.random.default_rng(1)
    for q in rng.normal(size=(20, 3)):
        expected = (np.eye(3) + skew(q)) @ np.linalg.inv(np.eye(3) - skew(q))
        np.testing.assert_allclose(rotation_from_cayley(q), expected, atol=1e-13)


def test_cayley_from_rotation_inverts_rotation_from_cayley():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(200, 3)) * rng.choice([1e-6, 0.1, 1.0, 10.0], size=(200, 1))
    R = rotation_from_cayley(q)
    np.testing.assert_allclose(cayley_from_rotation(R), q, rtol=1e-9, atol=1e-15)
    # and the other way round, for random rotations (none near 180 degrees)
    R = random_rotations(200, 3)
    R = R[rotation_angle(R) < np.radians(170)]
    np.testing.assert_allclose(rotation_from_cayley(cayley_from_rotation(R)), R, atol=1e-13)


def test_cayley_from_rotation_is_tan_half_angle_axis():
    rotvec = np.array([0.2, -0.5, 0.9])
    angle = np.linalg.norm(rotvec)
    q = cayley_from_rotation(Rotation.from_rotvec(rotvec).as_matrix())
    np.testing.assert_allclose(q, np.tan(angle / 2) * rotvec / angle, rtol=1e-12)


def test_cayley_vectorized_shapes():
    rng = np.random.default_rng(4)
    q = rng.normal(size=(7, 3))
    R = rotation_from_cayley(q)
    assert R.shape == (7, 3, 3)
    assert rotation_from_cayley(q[0]).shape == (3, 3)
    np.testing.assert_array_equal(R[3], rotation_from_cayley(q[3]))
    assert_rotation(R)
    assert cayley_from_rotation(R).shape == (7, 3)
    assert cayley_from_rotation(R[0]).shape == (3,)
    assert rotation_from_cayley(q[:1]).shape == (1, 3, 3)
    assert cayley_from_rotation(R[:1]).shape == (1, 3)


@pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1), (0.3, -0.2, 0.9)])
def test_cayley_from_180_degree_rotation_raises(axis):
    axis = np.array(axis, dtype=float) / np.linalg.norm(axis)
    R = Rotation.from_rotvec(np.pi * axis).as_matrix()
    with pytest.raises(GeometryError, match="180"):
        cayley_from_rotation(R)
    # also inside a batch, and the error is a DmaisError (user-facing)
    with pytest.raises(DmaisError):
        cayley_from_rotation(np.stack([np.eye(3), R]))


@settings(deadline=None, max_examples=100)
@given(st.lists(st.floats(-50, 50, allow_subnormal=False), min_size=3, max_size=3))
def test_property_cayley_round_trip(q):
    q = np.array(q)
    R = rotation_from_cayley(q)
    assert_rotation(R, atol=1e-12)
    np.testing.assert_allclose(cayley_from_rotation(R), q, rtol=1e-7, atol=1e-12)


# --------------------------------------------------------------------------------- quaternions


def literal_rotation_from_quat(w, x, y, z):
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def test_rotation_from_quat_is_scalar_first():
    rng = np.random.default_rng(5)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    R = rotation_from_quat(q)
    assert R.shape == (50, 3, 3)
    np.testing.assert_allclose(R, Rotation.from_quat(q, scalar_first=True).as_matrix(), atol=1e-15)
    for qi, Ri in zip(q, R):
        np.testing.assert_allclose(Ri, literal_rotation_from_quat(*qi), atol=1e-14)
    assert rotation_from_quat(q[0]).shape == (3, 3)
    # q and -q are the same rotation
    np.testing.assert_allclose(rotation_from_quat(-q), R, atol=1e-15)
    # 90 degrees about z: (cos 45, 0, 0, sin 45)
    np.testing.assert_allclose(rotation_from_quat([np.sqrt(0.5), 0, 0, np.sqrt(0.5)]), Rz(np.pi / 2), atol=1e-15)


def test_exp_so3_and_rotation_from_quat_are_scipys_to_the_last_bit():
    """Computed without scipy (a marker job does not import scipy.spatial), they are scipy's bits: on
    1e5 rotation vectors of every scale, about the 1e-3 rad switch to the series, and 1e5 quaternions
    of any norm, both as arrays and one at a time."""
    rng = np.random.default_rng(40)
    scales = [1e-9, 1e-6, 1e-4, 5e-4, 9.99e-4, 1e-3, 1.001e-3, 0.01, 0.3, 1.0, np.pi, 7.0]
    phi = rng.normal(size=(100_000, 3)) * rng.choice(scales, (100_000, 1))
    edges = np.array([[1e-3, 0, 0], [np.nextafter(1e-3, 1), 0, 0], [0, 0, 0], [0, 0, np.pi], [0, 2 * np.pi, 0]])
    phi = np.vstack([phi, edges])
    np.testing.assert_array_equal(exp_so3(phi), Rotation.from_rotvec(phi).as_matrix())
    for one in phi[::997]:
        np.testing.assert_array_equal(exp_so3(one), Rotation.from_rotvec(one).as_matrix())
    q = rng.normal(size=(100_000, 4)) * rng.choice([1e-3, 1.0, 1e3], (100_000, 1))
    q[:1000] /= np.linalg.norm(q[:1000], axis=1, keepdims=True)
    np.testing.assert_array_equal(rotation_from_quat(q), Rotation.from_quat(q, scalar_first=True).as_matrix())
    for one in q[::997]:
        np.testing.assert_array_equal(rotation_from_quat(one), Rotation.from_quat(one, scalar_first=True).as_matrix())


def test_rotation_from_quat_refuses_a_zero_quaternion_as_scipy_does():
    for q in ([0.0, 0.0, 0.0, 0.0], [[1.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 0.0]]):
        with pytest.raises(ValueError, match="zero norm"):
            rotation_from_quat(q)
        with pytest.raises(ValueError, match="zero norm"):
            Rotation.from_quat(q, scalar_first=True)


def test_quat_from_rotation_canonical_and_round_trip():
    R = random_rotations(100, 6)
    q = quat_from_rotation(R)
    assert q.shape == (100, 4)
    assert (q[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(rotation_from_quat(q), R, atol=1e-14)
    expected = Rotation.from_matrix(R).as_quat(scalar_first=True)
    expected *= np.where(expected[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q, expected, atol=1e-15)
    assert quat_from_rotation(R[0]).shape == (4,)
    np.testing.assert_allclose(quat_from_rotation(np.eye(3)), [1, 0, 0, 0], atol=1e-15)
    # a quaternion given with w < 0 comes back with w > 0
    q_neg = np.array([-0.5, 0.5, -0.5, 0.5])
    np.testing.assert_allclose(quat_from_rotation(rotation_from_quat(q_neg)), -q_neg, atol=1e-15)


# ----------------------------------------------------------------------------------- Euler ZYX


def test_rotation_from_euler_zyx_is_Rz_Ry_Rx():
    rng = np.random.default_rng(7)
    angles = np.column_stack([
        rng.uniform(-np.pi, np.pi, 30), rng.uniform(-np.pi / 2, np.pi / 2, 30), rng.uniform(-np.pi, np.pi, 30)
    ])
    R = rotation_from_euler_zyx(angles)
    assert R.shape == (30, 3, 3)
    for (z, y, x), Ri in zip(angles, R):
        np.testing.assert_allclose(Ri, Rz(z) @ Ry(y) @ Rx(x), atol=1e-14)
    assert rotation_from_euler_zyx(angles[0]).shape == (3, 3)
    np.testing.assert_allclose(euler_zyx_from_rotation(R), angles, atol=1e-12)
    assert euler_zyx_from_rotation(R[0]).shape == (3,)


def test_euler_zyx_round_trip_from_rotation():
    R = random_rotations(100, 8)
    angles = euler_zyx_from_rotation(R)
    assert (np.abs(angles[:, 1]) <= np.pi / 2 + 1e-12).all()
    np.testing.assert_allclose(rotation_from_euler_zyx(angles), R, atol=1e-12)


@pytest.mark.parametrize(
    "angles_deg, tilt_deg",
    [((-179.811, -0.152, 46.233), 46.2), ((-90.048, -1.170, 44.758), 44.8),
     ((0.150, -0.047, 44.038), 44.0), ((90.140, 1.180, 45.615), 45.6)],
)
def test_paper_extrinsics_table_tilts(angles_deg, tilt_deg):
    """tab:extrinsics_R (z, y, x) deg: the tilted cameras' optical axes are ~45 deg from C0's."""
    R = rotation_from_euler_zyx(np.radians(angles_deg))
    assert_rotation(R)
    optical_axis = R @ np.array([0.0, 0.0, 1.0])
    tilt = np.degrees(np.arccos(optical_axis @ np.array([0.0, 0.0, 1.0])))
    assert tilt == pytest.approx(tilt_deg, abs=0.1)
    np.testing.assert_allclose(np.degrees(euler_zyx_from_rotation(R)), angles_deg, atol=1e-10)


# ------------------------------------------------------------------------------------- metrics


def test_rotation_error_small_angle_accuracy():
    R_ref = random_rotations(20, 9)
    rng = np.random.default_rng(10)
    axes = rng.normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for angle in (1e-9, 1e-7, 1e-5, 0.3):
        dR = Rotation.from_rotvec(angle * axes).as_matrix()
        for R_est in (dR @ R_ref, R_ref @ dR):
            errors = rotation_error(R_est, R_ref)
            assert errors.shape == (20,)
            np.testing.assert_allclose(errors, angle, rtol=1e-3)
    assert rotation_error(R_ref[0], R_ref[0]) == pytest.approx(0.0, abs=1e-15)
    single = rotation_error(Rotation.from_rotvec([1e-9, 0, 0]).as_matrix(), np.eye(3))
    assert np.ndim(single) == 0 and single == pytest.approx(1e-9, rel=1e-3)


def test_rotation_error_is_symmetric_and_large_angles():
    R_a, R_b = random_rotations(50, 11), random_rotations(50, 12)
    np.testing.assert_allclose(rotation_error(R_a, R_b), rotation_error(R_b, R_a), atol=1e-12)
    expected = np.linalg.norm(Rotation.from_matrix(R_a @ np.swapaxes(R_b, 1, 2)).as_rotvec(), axis=1)
    np.testing.assert_allclose(rotation_error(R_a, R_b), expected, atol=1e-12)
    assert rotation_error(Rz(np.pi), np.eye(3)) == pytest.approx(np.pi, abs=1e-7)


def test_rotation_angle():
    rng = np.random.default_rng(13)
    axes = rng.normal(size=(50, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(0.01, np.pi - 0.01, 50)
    R = Rotation.from_rotvec(angles[:, None] * axes).as_matrix()
    measured = rotation_angle(R)
    assert measured.shape == (50,)
    np.testing.assert_allclose(measured, angles, atol=1e-10)
    assert rotation_angle(np.eye(3)) == 0.0
    assert rotation_angle(Rx(np.pi)) == pytest.approx(np.pi, abs=1e-7)
    assert rotation_angle(Rz(np.radians(30))) == pytest.approx(np.radians(30), abs=1e-12)
    # never NaN, even for slightly non-orthonormal input whose trace exceeds 3
    assert rotation_angle(np.eye(3) * (1 + 1e-12)) == 0.0


def test_translation_error():
    assert translation_error([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == 0.0
    assert translation_error([3.0, 4.0, 0.0], [0.0, 0.0, 0.0]) == pytest.approx(5.0)
    np.testing.assert_allclose(translation_error(np.ones((4, 3)), np.zeros((4, 3))), np.full(4, np.sqrt(3)))


# ----------------------------------------------------------------------------------- averaging


def markley_average(quats: np.ndarray, weights=None) -> np.ndarray:
    """Markley et al. 2007: eigenvector of the largest eigenvalue of sum w q q^T, as a matrix."""
    weights = np.ones(len(quats)) if weights is None else np.asarray(weights, dtype=float)
    M = np.einsum("i,ij,ik->jk", weights, quats, quats)
    eigenvalues, eigenvectors = np.linalg.eigh(M)
    q = eigenvectors[:, np.argmax(eigenvalues)]
    return literal_rotation_from_quat(*q)


def test_average_rotations_is_markley():
    rng = np.random.default_rng(14)
    center = Rotation.from_rotvec([0.3, -1.2, 2.0])
    noise = Rotation.from_rotvec(rng.normal(scale=0.05, size=(12, 3)))
    R = (noise * center).as_matrix()
    quats = Rotation.from_matrix(R).as_quat(scalar_first=True)
    np.testing.assert_allclose(average_rotations(R), markley_average(quats), atol=1e-12)
    weights = rng.uniform(0.1, 3.0, 12)
    np.testing.assert_allclose(average_rotations(R, weights=weights), markley_average(quats, weights), atol=1e-12)
    assert_rotation(average_rotations(R))


def test_average_rotations_invariant_to_quaternion_signs():
    rng = np.random.default_rng(15)
    R = (Rotation.from_rotvec(rng.normal(scale=0.1, size=(9, 3))) * Rotation.from_rotvec([0, 0, 2.0])).as_matrix()
    quats = Rotation.from_matrix(R).as_quat(scalar_first=True)
    signs = rng.choice([-1.0, 1.0], size=(9, 1))
    signs[0] = -1.0
    np.testing.assert_allclose(markley_average(quats * signs), markley_average(quats), atol=1e-12)
    # the library takes matrices built from sign-flipped quaternions and gives the same average
    flipped = rotation_from_quat(quats * signs)
    np.testing.assert_allclose(average_rotations(flipped), average_rotations(R), atol=1e-12)
    np.testing.assert_allclose(average_rotations(flipped), markley_average(quats), atol=1e-12)


def test_average_rotations_across_the_quaternion_hemisphere_boundary():
    """Rotations about z by 180 +- 1 degrees: canonical quaternions (w >= 0) flip sign between them,
    so a naive quaternion mean would be wrong; Markley's average is 180 degrees about z."""
    R = np.stack([Rz(np.radians(a)) for a in (179.0, -179.0, 178.5, -178.5)])
    canonical = quat_from_rotation(R)
    assert np.sign(canonical[0, 3]) != np.sign(canonical[1, 3])
    np.testing.assert_allclose(average_rotations(R), Rz(np.pi), atol=1e-12)
    assert rotation_error(average_rotations(R), Rz(np.pi)) < 1e-12


def test_average_of_identical_rotations_is_that_rotation():
    R = random_rotations(1, 16)[0]
    np.testing.assert_allclose(average_rotations(np.stack([R] * 5)), R, atol=1e-14)


# -------------------------------------------------------------------------------------- Rigid3


def random_rigid(seed: int) -> Rigid3:
    rng = np.random.default_rng(seed)
    return Rigid3(Rotation.random(random_state=seed).as_matrix(), rng.normal(scale=10.0, size=3))


def test_rigid3_apply_compose_inverse():
    a_from_b, b_from_c = random_rigid(20), random_rigid(21)
    points_c = np.random.default_rng(22).normal(scale=100, size=(30, 3))
    a_from_c = a_from_b * b_from_c
    np.testing.assert_allclose(a_from_c.apply(points_c), a_from_b.apply(b_from_c.apply(points_c)), atol=1e-10)
    np.testing.assert_allclose(a_from_b.apply(points_c), points_c @ a_from_b.R.T + a_from_b.t, atol=1e-12)
    # apply on a single point
    assert a_from_b.apply(points_c[0]).shape == (3,)
    np.testing.assert_allclose(a_from_b.apply(points_c[0]), a_from_b.R @ points_c[0] + a_from_b.t, atol=1e-12)
    # inverse
    b_from_a = a_from_b.inverse()
    np.testing.assert_allclose(b_from_a.apply(a_from_b.apply(points_c)), points_c, atol=1e-10)
    identity = a_from_b * b_from_a
    np.testing.assert_allclose(identity.R, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(identity.t, 0.0, atol=1e-13)
    np.testing.assert_allclose((a_from_c.inverse()).R, (b_from_c.inverse() * b_from_a).R, atol=1e-14)
    np.testing.assert_allclose((a_from_c.inverse()).t, (b_from_c.inverse() * b_from_a).t, atol=1e-12)
    # associativity
    c_from_d = random_rigid(23)
    left, right = (a_from_b * b_from_c) * c_from_d, a_from_b * (b_from_c * c_from_d)
    np.testing.assert_allclose(left.R, right.R, atol=1e-14)
    np.testing.assert_allclose(left.t, right.t, atol=1e-12)


def test_rigid3_identity():
    identity = Rigid3.identity()
    np.testing.assert_array_equal(identity.R, np.eye(3))
    np.testing.assert_array_equal(identity.t, np.zeros(3))
    other = random_rigid(24)
    np.testing.assert_allclose((identity * other).t, other.t)
    np.testing.assert_allclose((other * identity).R, other.R)


def test_rigid3_center():
    cam_from_world = random_rigid(25)
    center = cam_from_world.center
    np.testing.assert_allclose(cam_from_world.apply(center), 0.0, atol=1e-12)
    np.testing.assert_allclose(center, cam_from_world.inverse().t, atol=1e-12)
    np.testing.assert_allclose(center, -cam_from_world.R.T @ cam_from_world.t, atol=1e-12)


def test_rigid3_coerces_shapes():
    transform = Rigid3(np.eye(3).tolist(), [[1.0], [2.0], [3.0]])
    assert transform.R.shape == (3, 3) and transform.t.shape == (3,)
    assert transform.R.dtype == float and transform.t.dtype == float


def test_rigid3_to_dict_from_dict_round_trip():
    transform = random_rigid(26)
    data = transform.to_dict()
    assert set(data) == {"R", "t"}
    assert np.shape(data["R"]) == (3, 3) and np.shape(data["t"]) == (3,)
    np.testing.assert_array_equal(np.array(data["R"]), transform.R)  # row-major
    restored = Rigid3.from_dict(json.loads(json.dumps(data)))
    np.testing.assert_array_equal(restored.R, transform.R)
    np.testing.assert_array_equal(restored.t, transform.t)


def test_rigid3_from_quat_and_quat():
    q = np.array([0.5, -0.5, 0.5, 0.5])
    t = np.array([1.0, -2.0, 3.0])
    transform = Rigid3.from_quat(q, t)
    np.testing.assert_allclose(transform.R, literal_rotation_from_quat(*q), atol=1e-15)
    np.testing.assert_array_equal(transform.t, t)
    np.testing.assert_allclose(transform.quat, q, atol=1e-15)
    np.testing.assert_allclose(Rigid3.from_quat(-q, t).quat, q, atol=1e-15)
    other = random_rigid(27)
    again = Rigid3.from_quat(other.quat, other.t)
    np.testing.assert_allclose(again.R, other.R, atol=1e-14)
    assert other.quat[0] >= 0
