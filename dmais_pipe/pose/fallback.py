"""Global fallback of the generalized pose solver (issue 31): more starts where the template's
solution is not proven.

The template's roots are inaccurate where eq. objfun is ill-conditioned: few narrow cameras
over flat ground (one camera of 0.5-2 deg, or two of the rig's 5.4 deg cameras with few points
each). There its real roots can miss the global minimum, and the least-cost candidate is then a
pose far away or the mirror pose with the points behind the cameras. `solver.solve_generalized_pose`
calls `search` only when the Lagrangian dual does not certify its solution or the solution puts
most points behind their rays; a certified front-facing solution is the global minimum already.
The dual can also fail where the template is right: on the simulator's hovering 2 x 1,100-frame
flight, 80 frames of the whole rig (40 points, 5 cameras) are not certified, the least eigenvalue
of the dual's matrix -6.5e-3 to -9.2e-3 against a tolerance of 6.4e-3 (1e-9 of trace H 6.4e6),
the same after further Newton steps (the pose is stationary to 1e-10): the relaxation (R^T R = I
alone) is not tight there, not rounded. The search found the template's pose again in every one of
them, after refining ~43 starts (~11 ms); the solver now proves those poses first by the dual with
SO(3)'s redundant constraints (`certificate.py`, ~3 ms), and searches only where that fails too.

`search` refines starts from every side of SO(3), in this order (`starts`):

1. the template's CANDIDATE_STARTS least costly candidates, for planar points with the mirrors (180 deg about the points'
   normal) of those with most points behind and the flips of the front-facing ones (the plane's
   normal mirrored about the line of sight: through a narrow field of view a plane and its flip
   look alike);
2. the caller's attitude prior (rig_from_world), with its mirror or flip;
3. for planar points, per camera (rays sharing an origin) with at least 4 of them, the rotations
   of the homography from the plane to that camera's image decomposed (OpenCV's
   `decomposeHomographyMat`);
4. only if the best pose of those is not certified by the dual, and no homography of all the
   points (one camera) gave starts: the SAMPLED_STARTS least costly (quadratic form) of
   SAMPLED_ROTATIONS, a fixed set spread over SO(3).

Starts within DUPLICATE_DISTANCE of an earlier one are dropped.

Each start is refined by Levenberg-Marquardt on the angular residuals (`refine.refine_pose`,
compiled, which does not see the depths: a minimum it reaches with most points behind puts its
mirror first in the queue). The distinct front-facing minima it reaches then descend on eq.
objfun itself (`descend`: damped Newton on the residuals summed exactly, which the quadratic form
cannot resolve at 0.5 deg). The answer is the least cost among them with at least half of the
points in front (the solver's rule), and whether the dual certifies it.

Time budget: no LM refinement starts after TIME_BUDGET_S (30 ms) of the calling thread's CPU time
from the start of `search`, less Python's garbage collections meanwhile; the refinement under way
and the descent of the minima found finish (bounded by LM_ITERATIONS and DESCENT_ITERATIONS
steps). CPU time, not wall time, and without the collections (one of a large process took 44 ms
in `dmais bench pose-hard`, and cut a 5 ms search short): other processes and the caller's
allocations delay a search but do not change its result (a virtual machine's stolen time still
counts as CPU time); the CPU clock is read only as the wall clock, which it cannot outrun, nears
the budget (`_Budget`: a read cost up to 2 ms on the busy 2-core machine, where the 80 searches of
a 2,200-frame flight read it 3,500 times), and collections are timed only during a search. The
starts come in the order above, so a search cut short has tried the most promising. On the 2-core
development machine one search of 4-10 points takes ~3 ms (`dmais bench pose`'s fallback rows,
`dmais bench pose-hard`); the budget binds with many points or many candidates.
"""

from __future__ import annotations

import gc
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import PoseError
from ..geometry import rotation_from_cayley, skew
from .refine import refine_pose
from .statistics import PoseStatistics

#: Budget of one `search`, seconds of the calling thread's CPU time less garbage collections
#: (module docstring).
TIME_BUDGET_S = 0.03
#: Levenberg-Marquardt iterations per start.
LM_ITERATIONS = 50
#: Points count as planar when the least spread of the centred points (sum of squared distances
#: along their normal) is below this fraction of the middle one: the mirror, flip and homography
#: starts apply.
PLANAR_SPREAD = 1e-2
#: LM results within this Frobenius distance (~ sqrt 2 x their angle in radians) are one minimum
#: (the flat direction of a narrow field of view leaves copies of one minimum ~1e-5 apart).
DUPLICATE_DISTANCE = 1e-3
#: Levenberg-Marquardt iterations on eq. objfun (`descend`) from the distinct LM results.
DESCENT_ITERATIONS = 30
#: A start of `descend` ends when its next step is predicted to lower the cost by less than this fraction.
COST_TOLERANCE = 1e-13
#: ... or when a step shorter than this (radians) is refused: where the cost is nearly flat in one
#: direction (a narrow field of view), its model there is unreliable to that length, and damping
#: barely shortens the step.
REFUSED_STEP = 1e-6
#: A start of `descend` whose first step is longer than this (radians) is no LM result near a
#: minimum of eq. objfun (the angular minima it comes from lie within ~2e-3 rad of one).
FAR_STEP = 0.05
#: A start of `descend` whose damping grows beyond this (steps refused one after another) has converged.
MAX_DAMPING = 1e10
#: The fallback's pose replaces a front-facing solution of the template only when it is cheaper
#: by more than this fraction: the same minimum polished twice differs by the rounding of the
#: quadratic form (~1e-4 of the cost at 0.5 deg, though mostly far less).
IMPROVEMENT = 1e-6


class _CollectionClock:
    """Seconds of CPU time spent in Python's garbage collections while a search runs (`gc.callbacks`),
    so that they do not count against the budget. The collections of the rest of the process are
    not timed: a timing reads the thread's CPU clock twice (`_Budget`), and a budget spans only its
    search (a collection holds the interpreter lock: none straddles a search's start)."""

    def __init__(self):
        self.seconds, self._began, self._searches = 0.0, None, 0
        self._lock = threading.Lock()
        gc.callbacks.append(self._observe)

    @contextmanager
    def searching(self):
        """Within the block, a search runs: collections are timed."""
        with self._lock:
            self._searches += 1
        try:
            yield
        finally:
            with self._lock:
                self._searches -= 1

    def _observe(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._began = time.thread_time() if self._searches else None
        elif self._began is not None:
            self.seconds += time.thread_time() - self._began


_COLLECTIONS = _CollectionClock()


def _search_time() -> float:
    """The thread's CPU time less the garbage collections (seconds): the budget's clock."""
    return time.thread_time() - _COLLECTIONS.seconds


class _Budget:
    """A search's budget: `seconds` of `_search_time` from now. A thread's CPU time (less
    collections) cannot grow faster than the wall time, so the CPU clock is read only once the wall
    clock has run half of what was left at the last read: the answers are those of reading it every
    time, and it costs 20 us to 2 ms a read on a busy virtual machine (0.3 us idle), ~44 a search."""

    def __init__(self, seconds: float):
        wall = time.perf_counter()  # before the CPU clock: the bound then holds from the wall's reading
        self.deadline = _search_time() + seconds
        self.surely_left_until = wall + seconds / 2

    def left(self) -> bool:
        """Whether the budget is not spent (`_search_time` before the deadline)."""
        wall = time.perf_counter()
        if wall < self.surely_left_until:
            return True
        remaining = self.deadline - _search_time()
        self.surely_left_until = wall + remaining / 2
        return remaining > 0


def _sampled_rotations() -> np.ndarray:
    """(72, 3, 3): the rotations of the octahedral and icosahedral groups (those of the tetrahedral
    group, in both, once): every rotation lies within 45 deg of one, 29 deg on average."""
    octahedral = Rotation.create_group("O").as_matrix()
    icosahedral = Rotation.create_group("I").as_matrix()
    rotations = np.concatenate([octahedral, icosahedral])
    distinct = [0] + [i for i in range(1, len(rotations))
                      if np.min(np.linalg.norm(rotations[:i] - rotations[i], axis=(1, 2))) > 1e-9]
    return rotations[distinct]


SAMPLED_ROTATIONS = _sampled_rotations()
#: Of SAMPLED_ROTATIONS, the starts refined: the least costly (quadratic form) ones.
SAMPLED_STARTS = 12
#: Of the template's candidates, the starts refined: the least costly ones.
CANDIDATE_STARTS = 8


@dataclass(frozen=True)
class FallbackPose:
    """The least-cost front-facing pose of `search`: R (3, 3), t (3,) (x_rig = R @ M + t, world
    frame); cost: eq. objfun summed over the centred points; front: the fraction of points in
    front of their rays; certified: by the Lagrangian dual; minima: the distinct minima LM reached;
    seconds: the search's wall time."""

    R: np.ndarray
    t: np.ndarray
    cost: float
    front: float
    certified: bool
    minima: int
    seconds: float


@dataclass
class _Problem:
    """Checked rays (origins v (n, 3), unit directions f (n, 3)), the world points centred on
    their mean (n, 3), and their statistics."""

    v: np.ndarray
    f: np.ndarray
    centred: np.ndarray
    stats: PoseStatistics

    @property
    def planar(self) -> bool:
        return bool(self.stats.point_spread[0] < PLANAR_SPREAD * self.stats.point_spread[1])

    @property
    def central(self) -> bool:
        """Whether every ray leaves the same origin (one camera)."""
        return bool(np.all(self.v == self.v[0]))

    @property
    def normal(self) -> np.ndarray:
        """(3,) the normal of the points' best-fitting plane, world frame."""
        return self.stats.point_axes[:, 0]

    def centred_translation(self, R: np.ndarray) -> np.ndarray:
        """Optimal t (m, 3) of rotations R (3, 3) or (m, 3, 3) for the centred points (eq. t)."""
        return R.reshape(-1, 9) @ self.t_map + self.stats.t_offset

    @cached_property
    def t_map(self) -> np.ndarray:
        """(9, 3) the transposed translation map of eq. t."""
        return np.ascontiguousarray(self.stats.t_matrix.T)

    @cached_property
    def mean_origin(self) -> np.ndarray:
        """(3,) the mean ray origin, rig frame."""
        return self.v.mean(axis=0)

    @cached_property
    def cross(self) -> np.ndarray:
        """[f_i]x (n, 3, 3)."""
        return skew(self.f)

    @cached_property
    def projector(self) -> tuple[np.ndarray, np.ndarray]:
        """Q_i = I - f_i f_i^T (n, 3, 3) and (sum Q_i)^-1 (3, 3)."""
        Q = np.eye(3) - self.f[:, :, None] * self.f[:, None, :]
        return Q, np.linalg.inv(Q.sum(axis=0))

    def front(self, R: np.ndarray) -> float:
        """The fraction of points in front of their rays at rotation R (3, 3) and its optimal t."""
        p = self.centred @ R.T + (self.centred_translation(R)[0] - self.v)
        return float(np.count_nonzero(np.einsum("nj,nj->n", p, self.f) > 0)) / len(p)

    def costs(self, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eq. objfun summed over the points (S,) and the fraction of points in front (S,) of
        rotations R (S, 3, 3) at their optimal translations."""
        p = np.einsum("sij,nj->sni", R, self.centred) + self.centred_translation(R)[:, None, :] - self.v
        cost = np.sum(np.einsum("nij,snj->sni", self.cross, p) ** 2, axis=(1, 2))
        front = np.mean(np.einsum("snj,nj->sn", p, self.f) > 0, axis=1)
        return cost, front

    def residuals(self, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals [f_i]x (X_i + t(R) - v_i) (S, 3n), their squared sums (S,) and X_i = R m_i
        (S, n, 3) of rotations R (S, 3, 3), t(R) by its normal equations (`descend`)."""
        Q, S_inverse = self.projector
        X = np.einsum("sij,nj->sni", R, self.centred)
        t = np.einsum("ij,sj->si", S_inverse, np.einsum("nij,snj->si", Q, self.v - X))
        r = np.einsum("nij,snj->sni", self.cross, X + t[:, None, :] - self.v).reshape(len(R), -1)
        return r, np.sum(r**2, axis=1), X

    def descent_step(self, X: np.ndarray, r: np.ndarray, damping: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Damped Newton steps w (S, 3) at X (S, n, 3), residuals r (S, 3n), damping (S,), and the
        decrease of the cost their quadratic model predicts (S,).

        Half the Hessian of the cost is J^T J + sum_i (u_i X_i^T + X_i u_i^T) / 2 - (u_i . X_i) I
        with u_i = [f_i]x^T r_i (the second derivative of exp([w]x) X_i; that of t(R) drops out,
        as sum_i [f_i]x^T r_i = 0 at the optimal t); where it is not positive definite (far from a
        minimum), J^T J alone (Gauss-Newton). Newton converges where Gauss-Newton crawls: along
        the nearly flat direction of a narrow field of view the residuals are not small.
        """
        Q, S_inverse = self.projector
        Xx = skew(X.reshape(-1, 3)).reshape(X.shape + (3,))
        T = np.einsum("ij,sjk->sik", S_inverse, np.einsum("nij,snjk->sik", Q, Xx))
        J = np.einsum("nij,snjk->snik", self.cross, T[:, None] - Xx).reshape(len(X), -1, 3)
        JtJ = np.einsum("sra,srb->sab", J, J)
        gradient = np.einsum("sra,sr->sa", J, r)
        u = -np.einsum("nij,snj->sni", self.cross, r.reshape(X.shape))
        outer = np.einsum("sni,snj->sij", u, X)
        hessian = JtJ + 0.5 * (outer + np.swapaxes(outer, 1, 2)) - np.trace(outer, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        convex = np.all(np.linalg.eigvalsh(hessian) > 0, axis=1)
        hessian = np.where(convex[:, None, None], hessian, JtJ)
        damped = hessian + damping[:, None, None] * np.einsum("saa->sa", hessian)[:, :, None] * np.eye(3)
        step = -np.linalg.solve(damped, gradient[:, :, None])[:, :, 0]
        predicted = -2 * np.einsum("sa,sa->s", gradient, step) - np.einsum("sa,sab,sb->s", step, hessian, step)
        return step, predicted


def centred_costs(v: np.ndarray, f: np.ndarray, M: np.ndarray, stats: PoseStatistics,
                  R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. objfun summed over the centred points (S,) and the fraction of points in front (S,) of
    rotations R (S, 3, 3) at their optimal translations; v, f (unit), M (n, 3), their stats."""
    return _Problem(v, f, M - stats.centroid, stats).costs(R)


def mirror(R: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """R (3, 3) composed with the half turn about the world plane's normal (3,): for planar points
    the pose with every point on the other side of the rays at the same cost (central camera)."""
    return R @ (2.0 * np.outer(normal, normal) - np.eye(3))


def flip(problem: _Problem, R: np.ndarray) -> np.ndarray | None:
    """The flip of R (3, 3) for planar points: R turned about n x s by twice the angle between the
    plane's normal n and the line of sight s (the mean ray origin to the points' centroid, rig
    frame), i.e. the Cayley rotation q = (n x s) / (n . s); None when the plane is seen edge-on."""
    n = R @ problem.normal
    s = problem.centred_translation(R)[0] - problem.mean_origin
    dot = float(n @ s)
    if abs(dot) < 1e-3 * float(np.sqrt(s @ s)):
        return None
    return _cayley(_cross(n, s) / dot) @ R


def _cayley(q: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) of Cayley parameters q (3,) (`geometry.rotation_from_cayley` without its
    vectorization, which costs more than the arithmetic here)."""
    qq = float(q @ q)
    Q = np.array([[0.0, -q[2], q[1]], [q[2], 0.0, -q[0]], [-q[1], q[0], 0.0]])
    return ((1.0 - qq) * np.eye(3) + 2.0 * np.outer(q, q) + 2.0 * Q) / (1.0 + qq)


def homography_rotations(problem: _Problem) -> list[np.ndarray]:
    """rig_from_world rotations (3, 3) from the homography of the points' plane to each camera's
    image (rays sharing an origin, at least 4), decomposed by OpenCV: up to 4 per camera.

    In the plane's frame the points are X = (s1, s2, 1) (E A^T (M - m) + e3 with A the principal
    axes, normal first, and E the cyclic shift to (s1, s2, normal)); a camera's normalized image
    of them is H X with H = R_c + t n^T, n = e3, so R_c maps that frame to the camera's, and the
    rig's rotation is C^T R_c E A^T for the camera frame C (rows: the rig-frame axes, the mean
    ray direction last).
    """
    axes = problem.stats.point_axes * np.sign(np.linalg.det(problem.stats.point_axes))
    shift = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    plane = problem.centred @ axes[:, 1:]
    rotations = []
    for rows in _cameras(problem):
        if rows.sum() < 4:
            continue
        C = _frame_along(problem.f[rows].mean(axis=0))
        image = problem.f[rows] @ C.T
        if np.any(image[:, 2] <= 0):
            continue
        H, _ = cv2.findHomography(plane[rows], image[:, :2] / image[:, 2:], 0)
        if H is None or not np.isfinite(H).all():
            continue
        _, Rs, _, _ = cv2.decomposeHomographyMat(H, np.eye(3))
        rotations.extend(C.T @ R_c @ shift @ axes.T for R_c in Rs)
    return rotations


def _cameras(problem: _Problem) -> list[np.ndarray]:
    """Masks (n,) of the rays of each camera (the rays sharing an origin)."""
    if problem.central:
        return [np.ones(len(problem.v), bool)]
    _, camera_of = np.unique(problem.v, axis=0, return_inverse=True)
    return [camera_of.reshape(-1) == camera for camera in range(camera_of.max() + 1)]


def _frame_along(axis: np.ndarray) -> np.ndarray:
    """A rotation (3, 3) whose last row is the unit vector along axis (3,)."""
    z = axis / np.linalg.norm(axis)
    x = _cross(np.eye(3)[np.argmin(np.abs(z))], z)
    x /= np.linalg.norm(x)
    return np.stack([x, _cross(z, x), z])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two vectors (3,) (numpy's cross costs more than the arithmetic here)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def starts(problem: _Problem, candidates: np.ndarray, fronts: np.ndarray,
           prior: np.ndarray | None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The start rotations (3, 3) of the module docstring: the first three kinds, then the sampled
    ones; candidates (k, 3, 3) the template's, least cost first, with their fractions of points in
    front fronts (k,), prior (3, 3) or None."""
    found = []
    for R, front in zip(candidates[:CANDIDATE_STARTS], fronts[:CANDIDATE_STARTS]):
        found.append(R)
        if problem.planar:
            found.extend(_facing_and_flip(problem, R if front >= 0.5 else mirror(R, problem.normal), front >= 0.5))
    if prior is not None:
        found.append(prior)
        if problem.planar:
            front = problem.front(prior)
            found.extend(_facing_and_flip(problem, prior if front >= 0.5 else mirror(prior, problem.normal),
                                          front >= 0.5))
    homographies = homography_rotations(problem) if problem.planar else []
    found = _distinct(found + homographies)
    if homographies and problem.central:
        return found, []  # the homography of all the points is a global (linear) estimate already
    sampled = SAMPLED_ROTATIONS[np.argsort(problem.stats.cost(SAMPLED_ROTATIONS), kind="stable")[:SAMPLED_STARTS]]
    return found, list(sampled)


def _distinct(rotations: list[np.ndarray]) -> list[np.ndarray]:
    """rotations (3, 3) without those within DUPLICATE_DISTANCE of an earlier one (a candidate and
    the mirror of its twin behind the camera, for a central camera)."""
    if not rotations:
        return []
    rows = np.reshape(rotations, (-1, 9))
    near = np.sum((rows[:, None] - rows[None]) ** 2, axis=2) < DUPLICATE_DISTANCE**2
    return [R for i, R in enumerate(rotations) if not near[i, :i].any()]


class _RotationSet:
    """Rotations (3, 3) stored as rows (k, 9), to tell a new one from those within
    DUPLICATE_DISTANCE (Frobenius) of one stored."""

    def __init__(self):
        self.rows = np.empty((0, 9))

    def __len__(self) -> int:
        return len(self.rows)

    def add(self, R: np.ndarray) -> bool:
        """Store R unless it is near one stored; whether it was stored."""
        row = R.reshape(1, 9)
        if len(self.rows) and np.min(np.sum((self.rows - row) ** 2, axis=1)) < DUPLICATE_DISTANCE**2:
            return False
        self.rows = np.vstack([self.rows, row])
        return True


def _facing_and_flip(problem: _Problem, facing: np.ndarray, given: bool) -> list[np.ndarray]:
    """[facing (unless given: it is a start already), its flip (if any)], rotations (3, 3)."""
    flipped = flip(problem, facing)
    return ([] if given else [facing]) + ([] if flipped is None else [flipped])


def search(v: np.ndarray, f: np.ndarray, M: np.ndarray, stats: PoseStatistics, candidates: np.ndarray,
           fronts: np.ndarray, certify, prior: np.ndarray | None = None,
           budget_s: float = TIME_BUDGET_S) -> FallbackPose | None:
    """The least-cost pose with most points in front among the minima reached from `starts`
    (module docstring), or None if none has.

    v, f (unit), M: checked correspondences (n, 3); stats: their statistics; candidates (k, 3, 3)
    and fronts (k,): the template's; certify(R (3, 3)) -> bool: the dual certificate for these
    statistics; prior: (3, 3) rig_from_world or None; budget_s: no refinement starts after this
    much of the thread's CPU time (less garbage collections).
    The sampled starts are tried only when the others end without a certified pose.
    """
    with _COLLECTIONS.searching():
        begin, budget = time.perf_counter(), _Budget(budget_s)
        problem = _Problem(v, f, M - stats.centroid, stats)
        basins = _RotationSet()
        best = None
        for phase in starts(problem, candidates, fronts, prior):
            new = _refine_starts(problem, phase, basins, budget)
            if new:
                best = _least_front_facing(problem, descend(problem, np.array(new)), best)
            if best is not None and certify(np.ascontiguousarray(best[0])):
                break
    if best is None:
        return None
    R, cost, front = best
    t = problem.centred_translation(R)[0] - R @ stats.centroid
    return FallbackPose(R=R, t=t, cost=cost, front=front, certified=bool(certify(np.ascontiguousarray(R))),
                        minima=len(basins), seconds=time.perf_counter() - begin)


def _refine_starts(problem: _Problem, queue: list[np.ndarray], basins: _RotationSet,
                   budget: _Budget) -> list[np.ndarray]:
    """LM from the starts of queue until it is empty or the budget is spent: the new distinct
    minima (3, 3) with most points in front (every new minimum is appended to basins). A minimum with
    most points behind is followed by LM from its mirror (planar points), once: for a rig whose cameras
    are apart the mirror is no exact counterpart."""
    new, queue = [], [(R, False) for R in queue]
    while queue and budget.left():
        start, mirrored = queue.pop(0)
        R = _refined(problem, start)
        if R is None or not basins.add(R):
            continue
        if problem.front(R) >= 0.5:
            new.append(R)
        elif problem.planar and not mirrored:
            queue.insert(0, (mirror(R, problem.normal), True))
    return new


def _least_front_facing(problem: _Problem, R: np.ndarray, best: tuple | None) -> tuple | None:
    """(R (3, 3), cost, front) of the least cost among rotations R (S, 3, 3) with at least half of
    the points in front, or best if that costs less (or none of R is front-facing)."""
    cost, front = problem.costs(R)
    facing = np.flatnonzero(front >= 0.5)
    if len(facing) == 0:
        return best
    i = facing[np.argmin(cost[facing])]
    if best is not None and best[1] <= cost[i]:
        return best
    return R[i], float(cost[i]), float(front[i])


def descend(problem: _Problem, R: np.ndarray, iterations: int = DESCENT_ITERATIONS) -> np.ndarray:
    """Rotations (m, 3, 3) at the minima of eq. objfun (t eliminated, summed over the centred points)
    that damped Newton steps (`_Problem.descent_step`) reach from those of R (S, 3, 3) near one.

    Residuals r_i = [f_i]x (X_i + t(R) - v_i), X_i = R m_i, t(R) = S^-1 sum_j Q_j (v_j - X_j) with
    Q_j = I - f_j f_j^T and S = sum_j Q_j; for R <- exp([w]x) R, dX_i = -[X_i]x w and t moves by
    T w, T = S^-1 sum_j Q_j [X_j]x, so dr_i = [f_i]x (T - [X_i]x) w. The residuals are summed
    exactly, not through the quadratic form, which rounds at ~1e-4 of the cost at 0.5 deg. Steps
    are taken by the Cayley map (rotation_from_cayley(w / 2), exp([w]x) to second order). A start
    whose first step is longer than FAR_STEP is dropped: LM on the angular residuals, which do not
    see the depths, can end where eq. objfun has no minimum (points nearly at the ray origins).
    """
    R = np.array(R)
    r, cost, X = problem.residuals(R)
    damping = np.full(len(R), 1e-6)
    active, near = np.arange(len(R)), np.ones(len(R), bool)
    for iteration in range(iterations):
        step, predicted = problem.descent_step(X[active], r[active], damping[active])
        size = np.linalg.norm(step, axis=1)
        if iteration == 0:
            near = size <= FAR_STEP
            active, step, predicted, size = active[near], step[near], predicted[near], size[near]
        if len(active) == 0:
            break
        trial = rotation_from_cayley(step / 2).reshape(-1, 3, 3) @ R[active]
        trial_r, trial_cost, trial_X = problem.residuals(trial)
        better = trial_cost < cost[active]
        kept = active[better]
        R[kept], r[kept], cost[kept], X[kept] = trial[better], trial_r[better], trial_cost[better], trial_X[better]
        damping[active] = np.where(better, damping[active] / 10, damping[active] * 10)
        done = (predicted <= COST_TOLERANCE * cost[active]) | (~better & (size < REFUSED_STEP))
        active = active[~(done | (damping[active] > MAX_DAMPING))]
        if len(active) == 0:
            break
    return R[near]


def _refined(problem: _Problem, R: np.ndarray) -> np.ndarray | None:
    """The rotation (3, 3) that LM on the angular residuals reaches from R (3, 3), None if it fails."""
    t = problem.centred_translation(R)[0]
    try:
        return refine_pose(problem.v, problem.f, problem.centred, R, t, max_iterations=LM_ITERATIONS).R
    except PoseError:  # a start LM cannot refine is only skipped
        return None
