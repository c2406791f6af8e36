"""`dmais bench pose-hard`: the generalized pose solver on hard narrow-field scenes (issue 31).

Each kind (`KINDS`) is a scene of the paper's rig (the simulator's: its cameras' orientations and
centres, ideal pinholes of the kind's field of view) over flat ground, seen through few narrow
cameras: down-looking at 350 m over UTM-like coordinates, random yaw, tilt within 3 deg, pixels
uniform over the 4096 x 3000 px images, the world points where the rays meet the plane z = 0,
then pixel noise (`hard_scene`). Through a narrow field of view a plane and its flip look alike
and eq. objfun is ill-conditioned: the template's roots can miss the minimum, and a pose far
away (or the mirror pose, the points behind the cameras) can be the solver's least-cost candidate.

The reference (`multistart_reference`) is independent of the solver: Levenberg-Marquardt on eq.
objfun with t eliminated (variable projection, exact Jacobian), from the 24 axis-aligned
rotations, `REFERENCE_RANDOM_STARTS` random ones and the scene's true rotation, vectorized over
the starts, on the world points centred on their mean; its answer is the least cost among the
minima with at least half of the points in front of their rays (the solver's rule). A solve
reaches it when its cost (summed over the centred points, not the rounded quadratic form) is at
most REACHED_TOLERANCE above, or its rotation within REACHED_ANGLE_DEG of the reference's (the
same minimum, polished less finely); a solve cheaper than the reference counts as reached (and
is counted, as a sign of a weak reference).

Every case is solved twice: as before issue 31 (`fallback=False`: the template's roots alone)
and with the global fallback (`pose/fallback.py`, which runs only where the certificate fails or
the solution has most points behind). The table has, per kind and solver: the share reaching
the reference, the misses (gross: more than GROSS_DEG from the reference's rotation), their
largest angle and cost ratio, the solutions with most points behind their rays, the solves that
found no pose (PoseError), the uncertified solutions, how often the fallback ran and how often
its pose was returned, its median and largest time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from ..blas import single_threaded_blas
from ..errors import PoseError
from ..files import write_csv_atomic
from ..geometry import rotation_error
from ..pose.solver import solve_generalized_pose
from ..sim.config import DEFAULTS
from ..sim.scene import build_rig

WIDTH, HEIGHT = DEFAULTS["rig"]["width"], DEFAULTS["rig"]["height"]

#: A solve reaches the reference when its cost is at most this fraction above the reference's, or
#: its rotation within REACHED_ANGLE_DEG of the reference's: the same minimum, polished by the
#: solver to the rounding of its quadratic form (through 2 deg, 0.002 deg can cost 3e-6).
REACHED_TOLERANCE = 1e-6
REACHED_ANGLE_DEG = 0.01
#: A miss farther than this from the reference's rotation (degrees) is gross.
GROSS_DEG = 30.0
#: Random starts of the reference, beside the 24 axis-aligned rotations and the truth.
REFERENCE_RANDOM_STARTS = 64
#: Levenberg-Marquardt iterations of the reference.
REFERENCE_ITERATIONS = 80


@dataclass(frozen=True)
class HardKind:
    """A kind of hard scene: `cameras` of the rig see `points_per_camera` points each (1: C0 alone,
    else a random subset of that size), their horizontal field of view drawn uniformly from
    fov_deg (min, max), pixel noise noise_px (per axis), the ground flat."""

    name: str
    cameras: int
    points_per_camera: int
    fov_deg: tuple[float, float]
    noise_px: float
    note: str


KINDS = (
    HardKind("narrow_10pt", 1, 10, (0.5, 2.0), 0.3, "one camera of 0.5-2 deg, 10 points, 0.3 px (issue 31)"),
    HardKind("two_cams_5pt", 2, 5, (5.4, 5.4), 0.3, "two of the rig's 5.4 deg cameras, 5 points each, 0.3 px (issue 31)"),
    HardKind("subset0_8pt", 1, 8, (5.4, 5.4), 3.0, "C0 alone (subset #0), 8 points, 3 px (the flight's markers, noise)"),
    HardKind("narrow_4pt", 1, 4, (0.5, 2.0), 0.3, "one camera of 0.5-2 deg, 4 points, 0.3 px"),
    HardKind("two_narrow_4pt", 2, 4, (0.5, 2.0), 0.3, "two of the rig's cameras of 0.5-2 deg, 4 points each, 0.3 px"),
    HardKind("two_cams_2pt", 2, 2, (2.0, 5.4), 0.3, "two of the rig's cameras of 2-5.4 deg, 2 points each, 0.3 px"),
)


@dataclass(frozen=True)
class Scene:
    """Rays origins (n, 3), unit directions (n, 3) in the rig frame, world points (n, 3) and the true
    rig_from_world R (3, 3), t (3,) (x_rig = R @ M + t); fov_deg the cameras' field of view."""

    origins: np.ndarray
    directions: np.ndarray
    points: np.ndarray
    R: np.ndarray
    t: np.ndarray
    fov_deg: float


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _rig_pose(rng) -> tuple[np.ndarray, np.ndarray]:
    """world_from_rig (3, 3) of a down-looking rig (random yaw, tilt within 3 deg) and its centre
    (3,) at 350 m over UTM-like ground."""
    tilt = np.deg2rad(rng.uniform(-3.0, 3.0, size=2))
    world_from_rig = Rotation.from_euler("zxy", [rng.uniform(0, 2 * np.pi), np.pi + tilt[0], tilt[1]]).as_matrix()
    return world_from_rig, np.array([5e5, 4e6, 350.0]) + rng.uniform(-50, 50, size=3)


@lru_cache(maxsize=1)
def _paper_rig():
    """The simulator's paper rig (`sim.config.DEFAULTS`): C0 nadir, C1..C4 tilted ~45 deg, ~0.1 m apart."""
    return build_rig(DEFAULTS["rig"])


def rig_camera(camera: int) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_rig rotation (3, 3) and centre (3,) in the rig frame of the paper rig's camera
    number `camera` (0 = C0)."""
    rig = _paper_rig()
    cam_from_rig = rig.cam_from_rig[rig.camera_names[camera]]
    return cam_from_rig.R, cam_from_rig.inverse().t


def _rig_directions(uv: np.ndarray, focal_px: float, camera: int) -> np.ndarray:
    """Unit rig-frame ray directions (n, 3) of pixels uv (n, 2) of rig camera `camera` as an ideal
    pinhole of focal length focal_px centred on the image."""
    bearing = np.column_stack([(uv - [(WIDTH - 1) / 2, (HEIGHT - 1) / 2]) / focal_px, np.ones(len(uv))])
    return _unit(bearing) @ rig_camera(camera)[0]


def hard_scene(rng, kind: HardKind) -> Scene:
    """One scene of `kind` (module docstring), drawn from the generator rng."""
    fov = rng.uniform(*kind.fov_deg)
    focal_px = (WIDTH / 2) / np.tan(np.deg2rad(fov) / 2)
    cameras = [0] if kind.cameras == 1 else sorted(rng.choice(5, kind.cameras, replace=False))
    world_from_rig, centre = _rig_pose(rng)
    origins, directions, points = [], [], []
    for camera in cameras:
        uv = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], size=(kind.points_per_camera, 2))
        offset = rig_camera(camera)[1]
        origin = centre + world_from_rig @ offset
        ray = _rig_directions(uv, focal_px, camera) @ world_from_rig.T
        points.append(origin + ray * (-origin[2] / ray[:, 2])[:, None])
        noisy = uv + kind.noise_px * rng.normal(size=uv.shape)
        directions.append(_rig_directions(noisy, focal_px, camera))
        origins.append(np.tile(offset, (len(uv), 1)))
    R = world_from_rig.T
    return Scene(np.vstack(origins), np.vstack(directions), np.vstack(points), R, -R @ centre, fov)


# ---------------------------------------------------------------- reference (slow, independent)


def _skew(x: np.ndarray) -> np.ndarray:
    """[x]x (..., 3, 3) of vectors x (..., 3)."""
    out = np.zeros(x.shape + (3,))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -x[..., 2], x[..., 1], -x[..., 0]
    return out - np.swapaxes(out, -1, -2)


def _projected(origins, directions, centred, R) -> tuple[np.ndarray, np.ndarray]:
    """Residuals [f]x (R M + t(R) - v) (S, n, 3) with t(R) (S, 3) the optimal translation, for
    rotations R (S, 3, 3); origins, unit directions, centred points (n, 3)."""
    Q = np.eye(3) - directions[:, :, None] * directions[:, None, :]
    X = np.einsum("sij,nj->sni", R, centred)
    t = np.linalg.solve(Q.sum(axis=0), np.einsum("nij,snj->si", Q, origins - X).T).T
    return np.cross(directions, X + t[:, None, :] - origins), t


def _projected_jacobian(directions, centred, R) -> np.ndarray:
    """Jacobian (S, 3n, 3) of the residuals of `_projected` for R <- exp([w]x) R at w = 0:
    dX_i = -[X_i]x w, and t(R) moves by T w, T = (sum Q_j)^-1 sum_j Q_j [X_j]x."""
    Q = np.eye(3) - directions[:, :, None] * directions[:, None, :]
    X = _skew(np.einsum("sij,nj->sni", R, centred))
    T = np.linalg.solve(Q.sum(axis=0), np.einsum("nij,snjk->sik", Q, X))
    J = np.einsum("nij,snjk->snik", _skew(directions), T[:, None] - X)
    return J.reshape(len(R), -1, 3)


def multistart_reference(scene: Scene, rng, n_random: int = REFERENCE_RANDOM_STARTS,
                         iterations: int = REFERENCE_ITERATIONS) -> tuple[float, np.ndarray | None, np.ndarray | None]:
    """`multistart_minimum` of the scene, its true rotation among the starts (module docstring)."""
    return multistart_minimum(scene.origins, scene.directions, scene.points, rng, n_random, iterations,
                              starts=scene.R[None])


def multistart_minimum(origins, directions, points, rng, n_random: int, iterations: int, starts=()
                       ) -> tuple[float, np.ndarray | None, np.ndarray | None]:
    """The least cost of eq. objfun (cost, R (3, 3), t (3,)) among the local minima that LM reaches
    from the 24 axis-aligned, n_random random (drawn from rng) and the `starts` (k, 3, 3) rotations
    and that put at least half of the points in front of their rays (the solver's rule: eq. objfun
    cannot tell a pose from its mirror behind the cameras); (inf, None, None) if none does.

    Independent of the solver: variable projection with t(R) from the 3x3 normal equations and its
    exact Jacobian (`_projected_jacobian`), vectorized over the starts, on the points (n, 3) centred
    on their mean (t is free, so the cost is unchanged, and UTM-sized coordinates do not drown the
    residuals of a narrow camera in rounding); origins, directions (n, 3).
    """
    directions = _unit(directions)
    centroid = points.mean(axis=0)
    centred = points - centroid
    R = np.concatenate([Rotation.create_group("O").as_matrix(), Rotation.random(n_random, rng).as_matrix(),
                        np.reshape(starts, (-1, 3, 3))])
    residual, _ = _projected(origins, directions, centred, R)
    cost = np.sum(residual**2, axis=(1, 2))
    damping = np.full(len(R), 1e-3)
    for _ in range(iterations):
        J = _projected_jacobian(directions, centred, R)
        JtJ = np.einsum("sra,srb->sab", J, J)
        gradient = np.einsum("sra,sr->sa", J, residual.reshape(len(R), -1))
        damped = JtJ + damping[:, None, None] * (np.einsum("saa->sa", JtJ)[:, :, None] * np.eye(3) + 1e-30)
        step = -np.linalg.solve(damped, gradient[:, :, None])[:, :, 0]
        trial = Rotation.from_rotvec(step).as_matrix() @ R
        trial_residual, _ = _projected(origins, directions, centred, trial)
        trial_cost = np.sum(trial_residual**2, axis=(1, 2))
        better = trial_cost < cost
        R[better], residual[better], cost[better] = trial[better], trial_residual[better], trial_cost[better]
        damping = np.where(better, damping / 3, damping * 4)
    _, t = _projected(origins, directions, centred, R)
    depth = np.einsum("snj,nj->sn", np.einsum("sij,nj->sni", R, centred) + t[:, None, :] - origins, directions)
    front = np.mean(depth > 0, axis=1) >= 0.5
    if not front.any():
        return np.inf, None, None
    best = np.flatnonzero(front)[np.argmin(cost[front])]
    return float(cost[best]), R[best], t[best] - R[best] @ centroid


def centred_cost(scene: Scene, R: np.ndarray, t: np.ndarray) -> float:
    """Eq. objfun at (R, t) summed over the rays, on the centred points (without the rounding of
    UTM-sized coordinates)."""
    directions = _unit(scene.directions)
    centroid = scene.points.mean(axis=0)
    residual = np.cross(directions, (scene.points - centroid) @ R.T + (t + R @ centroid) - scene.origins)
    return float(np.sum(residual**2))


def front_fraction(scene: Scene, R: np.ndarray, t: np.ndarray) -> float:
    """Fraction of the points in front of their rays (positive depth along the direction) at (R, t)."""
    centroid = scene.points.mean(axis=0)
    p = (scene.points - centroid) @ R.T + (t + R @ centroid) - scene.origins
    return float(np.mean(np.einsum("ij,ij->i", p, scene.directions) > 0))


# ---------------------------------------------------------------- the benchmark


def _solve_case(scene: Scene, reference: tuple, fallback: bool) -> dict:
    """One solve of scene against its reference (cost, R, t): the row of the per-case table. A
    PoseError (no pose with most points in front found) is a miss without an angle."""
    start = time.perf_counter()
    try:
        pose = solve_generalized_pose(scene.origins, scene.directions, scene.points, fallback=fallback)
    except PoseError:
        return {"cost": np.inf, "cost_ratio": np.inf, "reached": False, "angle_deg": np.nan, "front": np.nan,
                "certified": False, "error": True, "fallback_ran": True, "fallback_used": False,
                "solve_ms": (time.perf_counter() - start) * 1e3, "fallback_ms": np.nan}
    seconds = time.perf_counter() - start
    cost = centred_cost(scene, pose.R, pose.t)
    ratio = cost / reference[0] if reference[0] > 0 else np.inf
    angle = float(np.rad2deg(rotation_error(pose.R, reference[1])))
    return {"cost": cost, "cost_ratio": ratio, "angle_deg": angle,
            "reached": bool(cost <= reference[0] * (1 + REACHED_TOLERANCE) or angle <= REACHED_ANGLE_DEG),
            "front": front_fraction(scene, pose.R, pose.t), "certified": bool(pose.certified), "error": False,
            "fallback_ran": pose.fallback_ms is not None, "fallback_used": bool(pose.fallback),
            "solve_ms": seconds * 1e3, "fallback_ms": np.nan if pose.fallback_ms is None else pose.fallback_ms}


def _warm_up() -> None:
    """One untimed solve through the fallback: the template loads on first use."""
    scene = hard_scene(np.random.default_rng(0), KINDS[0])
    solve_generalized_pose(scene.origins, scene.directions, scene.points)


def run_cases(kind: HardKind, cases: int, seed: int) -> pd.DataFrame:
    """Per case of `kind` (cases of them, from seed): the scene's reference and both solves
    (before: fallback=False; after: the fallback where it runs), one row per case and solver."""
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    _warm_up()
    rows = []
    for case in range(cases):
        scene = hard_scene(rng, kind)
        reference = multistart_reference(scene, rng)
        for solver, fallback in (("before", False), ("after", True)):
            rows.append({"kind": kind.name, "case": case, "solver": solver, "fov_deg": scene.fov_deg,
                         "reference_cost": reference[0], **_solve_case(scene, reference, fallback)})
    return pd.DataFrame(rows)


def summary(cases: pd.DataFrame) -> pd.DataFrame:
    """Per kind and solver: the table of the module docstring, from `run_cases` rows."""
    rows = []
    for (kind, solver), group in cases.groupby(["kind", "solver"], sort=False):
        misses = group[~group["reached"]]
        ran = group[group["fallback_ran"]]
        rows.append({"kind": kind, "solver": solver, "cases": len(group), "reached": group["reached"].mean(),
                     "misses": len(misses), "gross": int((misses["angle_deg"] > GROSS_DEG).sum()),
                     "max_angle_deg": misses["angle_deg"].max() if len(misses) else 0.0,
                     "max_cost_ratio": misses["cost_ratio"].max() if len(misses) else 1.0,
                     "most_behind": int((group["front"] < 0.5).sum()), "no_pose": int(group["error"].sum()),
                     "cheaper_than_reference": int((group["cost_ratio"] < 1 - REACHED_TOLERANCE).sum()),
                     "uncertified": int((~group["certified"]).sum()), "fallback_runs": len(ran),
                     "fallback_used": int(group["fallback_used"].sum()),
                     "fallback_median_ms": ran["fallback_ms"].median() if len(ran) else np.nan,
                     "fallback_max_ms": ran["fallback_ms"].max() if len(ran) else np.nan,
                     "solve_median_ms": group["solve_ms"].median()})
    return pd.DataFrame(rows)


def bench_pose_hard(csv: Path, cases: int = 400, seed: int = 2031, kinds: tuple[str, ...] | None = None) -> pd.DataFrame:
    """Run the benchmark on `cases` fresh scenes per kind (from seed), print the summary table and
    write it to csv, the per-case rows beside it (<stem>_cases.csv)."""
    selected = [k for k in KINDS if kinds is None or k.name in kinds]
    with single_threaded_blas():
        per_case = pd.concat([run_cases(kind, cases, seed) for kind in selected], ignore_index=True)
    table = summary(per_case)
    print(table.to_string(index=False, float_format=lambda x: f"{x:.4g}"))
    for kind in selected:
        print(f"{kind.name}: {kind.note}")
    print(f"seed {seed}; reached: cost within {REACHED_TOLERANCE:g} of the multi-start reference's (24 axis-aligned + "
          f"{REFERENCE_RANDOM_STARTS} random starts + the truth) or rotation within {REACHED_ANGLE_DEG:g} deg of it; "
          f"gross: > {GROSS_DEG:g} deg away")
    write_csv_atomic(csv, table)
    write_csv_atomic(Path(csv).with_name(Path(csv).stem + "_cases.csv"), per_case)
    return table
