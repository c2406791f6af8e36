"""Elimination template of the action-matrix solver for eq. EF6, built over a prime field.

This is the automatic-generator recipe of Kukelova, Bujnak and Pajdla (ECCV 2008), with exact
arithmetic modulo a prime on random instances of the six equations (whose coefficient structure
comes from `_equations.py`):

1. Multiply every equation by all monomials up to a total degree and reduce the resulting
   Macaulay matrix (columns in grevlex order, descending) to echelon form: the monomials that are
   not leading monomials of any row are the standard monomials B of the quotient ring, a basis of
   it when their count is stable under growing degree (here 40 = the number of solutions).
2. For an action variable x, the monomials x*b (b in B) outside B form the set R that the
   template must reduce to B. Order the columns as [E (everything else), R, B]; the expansion
   works when every R column is a pivot of the echelon form.
3. Drop expansion rows one at a time (highest multiplier degree first) while step 2 still holds,
   then keep only the E columns that are independent (the rest are linear combinations of those
   kept on generic data, so their constraints are implied). The result is a square block
   [C_E C_R] next to C_B, so the runtime does one Gaussian elimination.

The template is checked on further random instances. `main` of `dmais_pipe.pose.generate`
writes it to `_template.json`; the runtime (`dmais_pipe.pose.solver`) loads it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from .equations import COEFFICIENTS, MONOMIALS

#: The prime of the field in which templates are built (p^2 < 2^63 keeps numpy int64 exact).
PRIME = 32003
#: Degree of the Macaulay expansion: the smallest at which all reducible monomials are pivots.
EXPANSION_DEGREE = 8
#: Seeds of the random instances: the first builds the template, the others check it.
BUILD_SEED = 20261122
CHECK_SEEDS = (1, 2, 3, 4, 5)
N_SOLUTIONS = 40
EQUATION_DEGREE = int(MONOMIALS.sum(axis=1).max())

Monomial = tuple[int, int, int]


@dataclass(frozen=True)
class Template:
    """An elimination template (all monomials are exponent triples of (qx, qy, qz)).

    rows: (equation index, multiplier monomial) per template row, m of them;
    columns: monomials in column order, the m eliminated ones ([E, R]) then the 40 basis ones;
    n_reducible: |R|, the columns just before the basis; action_variable: 0, 1 or 2 (qx, qy, qz).
    """

    action_variable: int
    rows: tuple[tuple[int, Monomial], ...]
    columns: tuple[Monomial, ...]
    n_reducible: int

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.rows), len(self.columns)

    @property
    def basis(self) -> tuple[Monomial, ...]:
        return self.columns[len(self.rows):]

    @property
    def reducible(self) -> tuple[Monomial, ...]:
        m = len(self.rows)
        return self.columns[m - self.n_reducible : m]

    def to_json(self) -> str:
        data = {
            "generator": "python -m dmais_pipe.pose.generate",
            "prime": PRIME,
            "build_seed": BUILD_SEED,
            "action_variable": self.action_variable,
            "shape": list(self.shape),
            "n_reducible": self.n_reducible,
            "rows": [[e, list(mono)] for e, mono in self.rows],
            "columns": [list(mono) for mono in self.columns],
        }
        return json.dumps(data, indent=None, separators=(",", ":")).replace("],[", "],\n[") + "\n"

    @classmethod
    def from_json(cls, text: str) -> Template:
        data = json.loads(text)
        return cls(
            action_variable=int(data["action_variable"]),
            rows=tuple((int(e), tuple(int(x) for x in mono)) for e, mono in data["rows"]),
            columns=tuple(tuple(int(x) for x in mono) for mono in data["columns"]),
            n_reducible=int(data["n_reducible"]),
        )


# ------------------------------------------------------------------------------ prime field


def random_instance(seed: int) -> np.ndarray:
    """(6, n_monomials) equation coefficients mod PRIME for a random symmetric H and random g."""
    rng = np.random.default_rng(seed)
    H = rng.integers(0, PRIME, size=(9, 9))
    H = np.triu(H) + np.triu(H, 1).T
    g = rng.integers(0, PRIME, size=9)
    parameters = np.concatenate([H[np.triu_indices(9)], g])
    integer_coefficients = COEFFICIENTS.astype(np.int64) % PRIME
    return (integer_coefficients @ parameters % PRIME).reshape(6, len(MONOMIALS))


def echelon_pivots(matrix: np.ndarray) -> list[int]:
    """Pivot columns of the row echelon form of an integer matrix mod PRIME, (rows, cols) -> list."""
    A = np.asarray(matrix, dtype=np.int64) % PRIME
    pivots, row = [], 0
    for col in range(A.shape[1]):
        if row == A.shape[0]:
            break
        nonzero = np.flatnonzero(A[row:, col])
        if nonzero.size == 0:
            continue
        k = row + nonzero[0]
        if k != row:
            A[[row, k]] = A[[k, row]]
        A[row] = A[row] * pow(int(A[row, col]), PRIME - 2, PRIME) % PRIME
        below = row + 1 + np.flatnonzero(A[row + 1 :, col])
        if below.size:
            A[below] = (A[below] - A[below, col][:, None] * A[row]) % PRIME
        pivots.append(col)
        row += 1
    return pivots


# ------------------------------------------------------------------------------ monomials


def grevlex_descending(monomials) -> list[Monomial]:
    """Sort exponent triples in descending graded reverse lexicographic order (qx > qy > qz)."""
    return sorted({tuple(int(x) for x in m) for m in monomials}, key=lambda m: (-sum(m), m[2], m[1]))


def monomials_up_to(degree: int) -> list[Monomial]:
    return grevlex_descending(
        (a, b, d - a - b) for d in range(degree + 1) for a in range(d + 1) for b in range(d + 1 - a)
    )


def _add(a: Monomial, b: Monomial) -> Monomial:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def expansion(degree: int) -> list[tuple[int, Monomial]]:
    """All (equation, multiplier) pairs whose product has total degree <= `degree`."""
    multipliers = monomials_up_to(degree - EQUATION_DEGREE)
    return [(e, mult) for mult in multipliers for e in range(6)]


def template_entries(rows, columns) -> tuple[np.ndarray, np.ndarray]:
    """Where each equation coefficient lands in a template: flat indices (k,) into the
    (len(rows), len(columns)) template and flat indices (k,) into the (6, n_monomials) coefficients.

    Terms that fall in a monomial missing from `columns` are dropped (see step 3 above).
    """
    index = {mono: j for j, mono in enumerate(columns)}
    equation_monomials = [tuple(int(x) for x in m) for m in MONOMIALS]
    target, source = [], []
    for i, (e, mult) in enumerate(rows):
        for k, mono in enumerate(equation_monomials):
            j = index.get(_add(mono, mult))
            if j is not None:
                target.append(i * len(columns) + j)
                source.append(e * len(equation_monomials) + k)
    return np.array(target, dtype=np.int64), np.array(source, dtype=np.int64)


def coefficient_matrix(coeffs: np.ndarray, rows, columns) -> np.ndarray:
    """Integer template matrix (len(rows), len(columns)) of `coeffs` (6, n_monomials) mod PRIME."""
    target, source = template_entries(rows, columns)
    matrix = np.zeros(len(rows) * len(columns), dtype=np.int64)
    matrix[target] = np.asarray(coeffs).reshape(-1)[source]
    return matrix.reshape(len(rows), len(columns))


def standard_monomials(coeffs: np.ndarray, degree: int = EXPANSION_DEGREE + 1) -> list[Monomial]:
    """The monomials that lead no polynomial of the degree-`degree` expansion (grevlex order)."""
    columns = monomials_up_to(degree)
    pivots = set(echelon_pivots(coefficient_matrix(coeffs, expansion(degree), columns)))
    return [mono for j, mono in enumerate(columns) if j not in pivots]


# ------------------------------------------------------------------------------ template


def _reduces(matrix: np.ndarray, n_excessive: int, n_reducible: int) -> bool:
    pivots = set(echelon_pivots(matrix))
    return all(n_excessive + j in pivots for j in range(n_reducible))


def _split_columns(basis: list[Monomial], action_variable: int, degree: int):
    unit = tuple(int(i == action_variable) for i in range(3))
    basis_set = set(basis)
    reducible = grevlex_descending({_add(b, unit) for b in basis} - basis_set)
    excessive = [m for m in monomials_up_to(degree) if m not in basis_set and m not in set(reducible)]
    return excessive, reducible


def build_template(action_variable: int, seed: int = BUILD_SEED, degree: int = EXPANSION_DEGREE) -> Template:
    """Build the template for one action variable (0, 1, 2 = qx, qy, qz) on a random instance."""
    coeffs = random_instance(seed)
    basis = standard_monomials(coeffs)
    if len(basis) != N_SOLUTIONS:
        raise RuntimeError(f"expected {N_SOLUTIONS} standard monomials, found {len(basis)}")
    excessive, reducible = _split_columns(basis, action_variable, degree)
    rows = expansion(degree)
    matrix = coefficient_matrix(coeffs, rows, excessive + reducible + basis)
    n_e, n_r = len(excessive), len(reducible)
    if not _reduces(matrix, n_e, n_r):
        raise RuntimeError(f"degree {degree} expansion does not reduce x{action_variable} * basis")
    keep = np.ones(len(rows), dtype=bool)
    for i in range(len(rows)):
        keep[i] = False
        if not _reduces(matrix[keep], n_e, n_r):
            keep[i] = True
    matrix = matrix[keep]
    kept_excessive = [excessive[j] for j in echelon_pivots(matrix[:, :n_e])]
    template = Template(
        action_variable=action_variable,
        rows=tuple(row for row, k in zip(rows, keep) if k),
        columns=tuple(kept_excessive + reducible + basis),
        n_reducible=n_r,
    )
    if template.shape[0] != len(kept_excessive) + n_r:
        raise RuntimeError(f"template {template.shape} is not square in its eliminated part")
    return template


def check_template(template: Template, seeds=CHECK_SEEDS) -> None:
    """Raise RuntimeError unless the template reduces R to B on other random instances too."""
    m = template.shape[0]
    reduced_or_basis = set(template.columns[m - template.n_reducible :])
    equation_monomials = [tuple(int(x) for x in mono) for mono in MONOMIALS]
    for seed in seeds:
        coeffs = random_instance(seed)
        if tuple(standard_monomials(coeffs)) != template.basis:
            raise RuntimeError(f"instance {seed}: the standard monomials differ from the template's basis")
        matrix = coefficient_matrix(coeffs, template.rows, template.columns)
        if len(echelon_pivots(matrix[:, :m])) != m:
            raise RuntimeError(f"instance {seed}: the eliminated block of the template is singular")
        # The E columns left out must be combinations of those kept, else the reductions carry
        # terms in monomials the template ignores (a square, nonsingular block does not show it).
        excessive = [mono for mono in grevlex_descending(_add(mono, mult) for _, mult in template.rows
                                                         for mono in equation_monomials)
                     if mono not in reduced_or_basis]
        if len(echelon_pivots(coefficient_matrix(coeffs, template.rows, excessive))) != m - template.n_reducible:
            raise RuntimeError(f"instance {seed}: the template drops excessive monomials its rows need")
