"""The written-out numerical kernels of the pose solver (`_kernels.pyx`): the eigenvalues of the
action matrix (balancing, Householder Hessenberg reduction, Francis QR) and the eigenvector entries
by inverse iteration, against numpy's LAPACK on the same matrices."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.pose import pose_statistics
from dmais_pipe.pose._kernels import action_matrix_eigen

from pose_scenes import dmais_scene
from test_pose_solver import reference_action_matrix


def _matched(values, reference):
    """For each reference eigenvalue, the distance to the nearest of values."""
    return np.abs(values[None, :] - reference[:, None]).min(axis=1)


def _random_with_real_spectrum(rng, graded: bool) -> np.ndarray:
    """A (40, 40) matrix V diag(lambda) V^-1 with 24 real and 8 complex-pair eigenvalues; graded:
    V's rows scaled over 10 orders of magnitude, which balancing must undo."""
    real = rng.uniform(-3, 3, 24)
    pairs = rng.uniform(-2, 2, 8) + 1j * rng.uniform(0.1, 2, 8)
    blocks = [np.diag(real)] + [np.array([[z.real, z.imag], [-z.imag, z.real]]) for z in pairs]
    D = np.zeros((40, 40))
    i = 0
    for block in blocks:
        D[i:i + len(block), i:i + len(block)] = block
        i += len(block)
    V = rng.normal(size=(40, 40)) + 4 * np.eye(40)
    if graded:
        V = np.diag(10.0 ** rng.uniform(-5, 5, 40)) @ V
    return V @ D @ np.linalg.inv(V)


@pytest.mark.parametrize("graded", [False, True])
def test_eigenvalues_equal_numpy_on_random_matrices(graded):
    rng = np.random.default_rng(3)
    for _ in range(20):
        A = _random_with_real_spectrum(rng, graded)
        values, vectors = action_matrix_eigen(A, (0, 1, 2, 3))
        reference = np.linalg.eigvals(A)
        scale = np.abs(reference).max()
        assert _matched(values, reference).max() <= 1e-7 * scale
        assert _matched(reference, values).max() <= 1e-7 * scale  # no eigenvalue twice
        # conjugate pairs: positive imaginary part first
        complex_index = np.flatnonzero(values.imag != 0)
        assert np.all(values.imag[complex_index[::2]] > 0)
        np.testing.assert_allclose(values[complex_index[::2]], values[complex_index[1::2]].conj())
        # the eigenvector entries at rows 0..3 for each real eigenvalue, up to scale
        _, reference_vectors = np.linalg.eig(A)
        for i in np.flatnonzero(values.imag == 0):
            j = np.argmin(np.abs(reference - values[i]))
            expected = reference_vectors[:4, j].real
            got = vectors[i] * (expected @ vectors[i]) / (vectors[i] @ vectors[i])
            assert np.abs(got - expected).max() <= 1e-6 * np.abs(expected).max()


def test_eigenvalues_of_action_matrices_equal_numpy():
    rng = np.random.default_rng(11)
    for _ in range(10):
        origins, directions, points, R, _ = dmais_scene(rng, 5)
        stats = pose_statistics(origins, directions, points)
        P = Rotation.from_rotvec(rng.normal(scale=0.3, size=3)).as_matrix() @ R
        A, _ = reference_action_matrix(stats.H, stats.g, P)
        values, _ = action_matrix_eigen(A)
        reference = np.linalg.eigvals(A)
        real = np.abs(reference.imag) < 1e-6 * (1 + np.abs(reference))
        # Real roots (the ones the solver keeps) to LAPACK's accuracy: some action matrices are so
        # ill-conditioned that LAPACK's eigenvalues of A and of A^T differ by 1e-2, the measure here.
        conditioning = _matched(np.linalg.eigvals(A.T), reference).max()
        tolerance = max(1e-6 * (1 + np.abs(reference[real]).max()), 10 * conditioning)
        assert _matched(values, reference[real]).max() <= tolerance


def test_wrong_shape_is_refused():
    with pytest.raises(ValueError, match=r"\(40, 40\)"):
        action_matrix_eigen(np.eye(3))
