"""A tighter dual certificate of the generalized pose: where the solver's does not hold, it spares the
global fallback's search (issue 40).

The solver's certificate (`_kernels.certified`) relaxes eq. objfun3 to x = [r; y] (r = vec(R) row-major)
under R^T R = I and y^2 = 1 alone: the Lagrange multipliers are then fixed by stationarity, and the dual
proves the pose where that one Hessian is positive semidefinite. The relaxation is not always tight: on the
simulator's hovering 2 x 1,100-frame flight, 80 of 2,200 whole-rig frames fail it by a least eigenvalue
of -6.5e-3 to -1.1e-2 (tolerance 6.4e-3), along the scale direction [-r / 2 sqrt 3; sqrt 3 / 2] that
trades R's size against y (nearly a central camera's invariance). With the redundant constraints of SO(3)
(Briales and Gonzalez-Jimenez, CVPR 2017) the relaxation is tight there:

- R R^T = I (6), and the handedness of the columns and rows, c_i x c_j = y c_k and r_i x r_j = y r_k
  for (i, j, k) cyclic (18; they hold on SO(3) only, not on its reflections).

Their multipliers are no longer fixed by stationarity: they form an affine family (31 multipliers, 10
equations S x = 0 at x = [r; 1]), and a point of it whose Hessian S is positive semidefinite is found by a
barrier method on the least eigenvalue of S on the complement of x (a small semidefinite program). Any
such point proves the pose, however it was found: for every feasible x, x^T Q x = x^T S x + sum lambda_k
b_k >= sum lambda_k b_k = x*^T Q x*. The test is the solver's: the least eigenvalue of the whole S above
-CERTIFICATE_TOLERANCE (trace H + |g| + |c|).
"""

from __future__ import annotations

import numpy as np

from . import _certificate

#: As `_kernels.CERTIFICATE_TOLERANCE`: the least eigenvalue allowed, relative to trace H + |g| + |c|.
CERTIFICATE_TOLERANCE = 1e-9
#: Barrier-method iterations before the search gives up (the certified frames take 6-8).
ITERATIONS = 40


def _symmetric_product(p: int, q: int) -> np.ndarray:
    """(10, 10) A with x^T A x = x_p x_q."""
    A = np.zeros((10, 10))
    A[p, q] += 0.5
    A[q, p] += 0.5
    return A


def _constraints() -> np.ndarray:
    """(31, 10, 10) the quadratic forms of the constraints on x = [vec(R) row-major; y] (module docstring):
    R^T R and R R^T (upper triangles), y^2, then the columns' and the rows' handedness."""
    def r(i, j):
        return 3 * i + j

    forms = []
    for pairs in (lambda a, b, i: (r(i, a), r(i, b)), lambda a, b, j: (r(a, j), r(b, j))):
        forms += [sum(_symmetric_product(*pairs(a, b, i)) for i in range(3)) for a in range(3) for b in range(a, 3)]
    forms.append(_symmetric_product(9, 9))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        for m in range(3):
            m1, m2 = (m + 1) % 3, (m + 2) % 3
            forms.append(_symmetric_product(r(m1, i), r(m2, j)) - _symmetric_product(r(m2, i), r(m1, j))
                         - _symmetric_product(9, r(m, k)))
            forms.append(_symmetric_product(r(i, m1), r(j, m2)) - _symmetric_product(r(i, m2), r(j, m1))
                         - _symmetric_product(9, r(k, m)))
    return np.array(forms)


CONSTRAINTS = _constraints()
_FLAT = CONSTRAINTS.reshape(len(CONSTRAINTS), 100)
_EYE9 = np.eye(9)


def tight_certified(H: np.ndarray, g: np.ndarray, c: float, R: np.ndarray) -> bool:
    """Whether the dual with SO(3)'s redundant constraints (module docstring) proves R (3, 3) the global
    minimum of r^T H r - 2 g^T r + c (H (9, 9), g (9,): the solver's statistics) over SO(3): the compiled
    `_certificate.tight_certified` (`tight_certified_numpy`'s steps; ~0.3 against ~0.8 ms)."""
    as_rows = [np.ascontiguousarray(a, dtype=float) for a in (H, g, R)]
    return _certificate.tight_certified(as_rows[0], as_rows[1], float(c), as_rows[2], _FLAT, CERTIFICATE_TOLERANCE,
                                        ITERATIONS)


def tight_certified_numpy(H: np.ndarray, g: np.ndarray, c: float, R: np.ndarray) -> bool:
    """`tight_certified` by numpy (the compiled one's reference, tests/test_pose_fallback.py)."""
    x = np.append(R.reshape(9), 1.0)
    Q = np.block([[H, -g[:, None]], [-g[None], np.array([[c]])]])
    tolerance = CERTIFICATE_TOLERANCE * (np.trace(H) + np.linalg.norm(g) + abs(c))
    base, directions, complement = _multiplier_family(Q, x)
    if base is None:
        return False
    return _least_eigenvalue_search(Q, base, directions, complement, tolerance)


def _multiplier_family(Q: np.ndarray, x: np.ndarray):
    """(lambda0 (31,), its free directions (d, 31), an orthonormal basis (10, 9) of x's complement): the
    multipliers with S(lambda) x = Q x - sum lambda_k A_k x = 0 (least squares: the A_k x span 7 dimensions,
    x's and the 6 normal to SO(3) at R, which hold Q x where R is stationary); (None, None, None) where the
    statistics are not finite."""
    B = (CONSTRAINTS @ x).T  # (10, 31)
    base, _, rank, _ = np.linalg.lstsq(B, Q @ x, rcond=None)
    Vt = np.linalg.svd(B)[2]
    if not np.isfinite(base).all():
        return None, None, None
    directions = Vt[rank:]  # (31 - rank, 31) the null space of B
    u = x / np.linalg.norm(x)
    complement = np.linalg.svd(np.eye(10) - np.outer(u, u))[0][:, :9]
    return base, directions, complement


def _least_eigenvalue_search(Q: np.ndarray, base: np.ndarray, directions: np.ndarray, complement: np.ndarray,
                             tolerance: float) -> bool:
    """Whether some multipliers base + directions^T z (directions (d, 31)) give S a least eigenvalue above
    -tolerance: a barrier method maximising s subject to P^T S P - s I > 0 (P the complement (10, 9)),
    stopped as soon as the whole S (10, 10) passes the test."""
    whole = Q - (base @ _FLAT).reshape(10, 10)
    changes, forms = _independent_changes(directions, complement)  # S moves by -w_e changes_e
    if changes is None:
        return np.linalg.eigvalsh(whole)[0] >= -tolerance
    ends = np.concatenate([forms, -_EYE9.reshape(1, 81)]).reshape(-1, 9, 9)  # P^T S P - s I per (w, s)
    w = np.zeros(len(forms))
    s = np.linalg.eigvalsh(complement.T @ whole @ complement)[0]
    s -= 1e-3 * abs(s) + tolerance  # strictly inside
    weight = 1.0
    for _ in range(ITERATIONS):
        S = whole - (w @ changes).reshape(10, 10)
        if np.linalg.eigvalsh(S)[0] >= -tolerance:
            return True
        X = complement.T @ S @ complement - s * _EYE9
        Y = (np.linalg.inv(X) @ ends).reshape(len(ends), 81)  # X^-1 E_e
        gradient = -Y[:, ::10].sum(axis=1)  # the gradient of -log det X: -tr(X^-1 E_e)
        gradient[-1] -= weight  # of -weight s
        hessian = Y @ Y.reshape(-1, 9, 9).transpose(0, 2, 1).reshape(len(ends), 81).T  # tr(X^-1 E_e X^-1 E_f)
        try:
            step = -np.linalg.solve(hessian, gradient)
        except np.linalg.LinAlgError:
            return False
        length = 1.0
        while np.linalg.eigvalsh(X + (length * step @ ends.reshape(len(ends), 81)).reshape(9, 9))[0] <= 0:
            length /= 2
            if length < 1e-8:
                return False
        w, s = w + 0.95 * length * step[:-1], s + 0.95 * length * step[-1]
        if step @ hessian @ step < 0.25:  # the Newton decrement below 1/2: the barrier's weight grows
            weight *= 4.0
    return False


def _independent_changes(directions: np.ndarray, complement: np.ndarray):
    """(changes (e, 100), forms (e, 81)): combinations of the free directions (d, 31) whose changes of
    P^T S P (forms, flattened) are orthonormal (the directions' forms are not independent: the Newton
    system would be singular), and their changes of S (flattened); (None, None) when they make none."""
    changes = -(directions @ _FLAT)
    forms = (complement.T @ changes.reshape(-1, 10, 10) @ complement).reshape(len(directions), 81)
    U, singular, Vt = np.linalg.svd(forms, full_matrices=False)
    kept = singular > 1e-12 * singular[0] if len(singular) and singular[0] > 0 else np.zeros(0, bool)
    if not kept.any():
        return None, None
    combinations = U[:, kept] / singular[kept]  # (d, e)
    return -(combinations.T @ changes), Vt[kept]
