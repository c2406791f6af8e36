"""`dmais bench pose`: tab:time_points regenerated side by side with pycolmap and the paper.

For each point count, seeded DMAIS-like frames (the paper's rig: C0 nadir, C1..C4 tilted 45 deg,
f = 45000 px, 4096 x 3000 px, at 350 m, 4 px pixel noise, points spread evenly over the five
cameras) are solved by ours (`solve_generalized_pose`) and by pycolmap's generalized absolute
pose (`estimate_and_refine_generalized_absolute_pose`: LO-RANSAC over GP3P + refinement) on the
same observations, in one run; the median wall time per solve is reported with the paper's C++
figures (dmais_pipe/report/paper_tables/time_points.csv), and the fraction of our solutions that the Lagrangian
dual certifies as global minima (`GeneralizedPose.certified`). Batch throughput is frames per second of
`solve_batch` over many 50-point frames, in one thread and in as many as the machine has cores.
OpenBLAS runs single-threaded meanwhile (see `single_threaded_blas`).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from ..blas import single_threaded_blas
from ..files import write_csv_atomic
from ..geometry import rotation_error
from .solver import solve_batch, solve_generalized_pose

POINT_COUNTS = (10, 50, 100, 200, 300, 400, 500)
PAPER_TABLE = Path(__file__).resolve().parents[1] / "report" / "paper_tables" / "time_points.csv"
FOCAL_PX, WIDTH, HEIGHT, NOISE_PX = 45000.0, 4096, 3000, 4.0
#: (tilt, azimuth) in degrees of the optical axes of C0..C4 in the rig frame (C0's camera frame).
DMAIS_AXES = ((0, 0), (45, 0), (45, 90), (45, 180), (45, 270))


def dmais_cam_from_rig(k: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, centre) of camera k of the paper's rig: R (3, 3) maps rig to camera coordinates,
    centre (3,) in the rig frame (0.1 m from C0's)."""
    tilt, azimuth = DMAIS_AXES[k]
    rig_from_cam = Rotation.from_euler("ZX", np.deg2rad([azimuth, tilt])).as_matrix()
    centre = 0.1 * np.array([np.cos(k), np.sin(k), 0.0]) if k else np.zeros(3)
    return rig_from_cam.T, centre


def _bearings(uv: np.ndarray) -> np.ndarray:
    """Camera-frame ray directions (n, 3), unnormalized, of ideal pinhole pixels uv (n, 2)."""
    return np.column_stack([(uv - [(WIDTH - 1) / 2, (HEIGHT - 1) / 2]) / FOCAL_PX, np.ones(len(uv))])


def dmais_frame(rng, n_points: int):
    """One frame: camera index (n,), pixels (n, 2), world points (n, 3), true (R, t)."""
    world_from_rig = Rotation.from_euler("zxy", [rng.uniform(0, 2 * np.pi), np.pi + rng.uniform(-0.05, 0.05),
                                                 rng.uniform(-0.05, 0.05)]).as_matrix()
    centre = np.array([5e5, 4e6, 350.0]) + rng.uniform(-50, 50, 3)
    cams = np.arange(n_points) % 5
    uv = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], size=(n_points, 2))
    points = np.empty((n_points, 3))
    for k in range(5):
        R_c, centre_c = dmais_cam_from_rig(k)
        m = cams == k
        direction = (_bearings(uv[m]) @ R_c) @ world_from_rig.T
        origin = centre + world_from_rig @ centre_c
        depth = (rng.uniform(-10, 10, m.sum()) - origin[2]) / direction[:, 2]
        points[m] = origin + depth[:, None] * direction
    uv = uv + NOISE_PX * rng.normal(size=uv.shape)
    return cams, uv, points, (world_from_rig.T, -world_from_rig.T @ centre)


#: rig_from_cam rotations (5, 3, 3) and camera centres in the rig frame (5, 3), built once like
#: pycolmap's cameras, outside the timed solves.
_RIG_FROM_CAM = np.array([dmais_cam_from_rig(k)[0].T for k in range(5)])
_CENTRES = np.array([dmais_cam_from_rig(k)[1] for k in range(5)])


def _rays(cams, uv):
    """Ray origins and directions (n, 3) in the rig frame of pixels uv (n, 2) of cameras cams (n,)."""
    return _CENTRES[cams], np.einsum("nij,nj->ni", _RIG_FROM_CAM[cams], _bearings(uv))


def _pycolmap_solver():
    import pycolmap

    camera = pycolmap.Camera(model="PINHOLE", width=WIDTH, height=HEIGHT,
                             params=[FOCAL_PX, FOCAL_PX, (WIDTH - 1) / 2 + 0.5, (HEIGHT - 1) / 2 + 0.5])
    cams_from_rig = []
    for k in range(5):
        R, centre = dmais_cam_from_rig(k)
        cams_from_rig.append(pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre))
    options = pycolmap.RANSACOptions()
    options.max_error = 12.0

    def solve(cams, uv, points):
        # COLMAP puts the centre of the top-left pixel at (0.5, 0.5)
        result = pycolmap.estimate_and_refine_generalized_absolute_pose(
            uv + 0.5, points, [int(c) for c in cams], cams_from_rig, [camera] * 5, options)
        pose = result["rig_from_world"]
        return pose.rotation.matrix(), np.asarray(pose.translation)

    return solve


def _median_ms(solve, frames) -> tuple[float, float]:
    """Median time per solve (ms) and median rotation error (arc-min) over frames."""
    times, errors = [], []
    for cams, uv, points, (R, _) in frames:
        start = time.perf_counter()
        R_est, _ = solve(cams, uv, points)
        times.append(time.perf_counter() - start)
        errors.append(rotation_error(R_est, R))
    return float(np.median(times) * 1e3), float(np.rad2deg(np.median(errors)) * 60)


def bench_pose(csv: Path, repeats: int = 200, batch_frames: int = 200, seed: int = 0) -> pd.DataFrame:
    """Run the benchmark, print the table and write it (and the batch throughput) as CSV."""
    rng = np.random.default_rng(seed)
    paper = pd.read_csv(PAPER_TABLE).set_index("n_points")["paper_ms"] if PAPER_TABLE.is_file() else {}

    certified = []

    def ours(cams, uv, points):
        origins, directions = _rays(cams, uv)
        pose = solve_generalized_pose(origins, directions, points)
        certified.append(pose.certified)
        return pose.R, pose.t

    colmap = _pycolmap_solver()
    rows = []
    with single_threaded_blas():
        for n in POINT_COUNTS:
            frames = [dmais_frame(rng, n) for _ in range(repeats)]
            certified.clear()
            ours_ms, ours_err = _median_ms(ours, frames)
            colmap_ms, colmap_err = _median_ms(colmap, frames)
            rows.append({"n_points": n, "ours_ms": ours_ms, "pycolmap_ms": colmap_ms,
                         "paper_ms": float(paper.get(n, np.nan)), "ours_rot_err_arcmin": ours_err,
                         "pycolmap_rot_err_arcmin": colmap_err, "ours_certified": float(np.mean(certified))})
        frames = [dmais_frame(rng, 50) for _ in range(batch_frames)]
        problems = [(*_rays(cams, uv), points) for cams, uv, points, _ in frames]
        batch = []
        for workers in sorted({1, os.cpu_count() or 1}):
            start = time.perf_counter()
            solve_batch(problems, workers=workers)
            batch.append({"points_per_frame": 50, "frames": batch_frames, "workers": workers,
                          "frames_per_s": batch_frames / (time.perf_counter() - start)})
    table = pd.DataFrame(rows)
    print(table.to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    for run in batch:
        print(f"batch: {run['frames_per_s']:.0f} frames/s in {run['workers']} thread(s) "
              f"(50 points per frame, rays precomputed, {batch_frames} frames)")
    write_csv_atomic(csv, table)
    write_csv_atomic(Path(csv).with_name(Path(csv).stem + "_batch.csv"), pd.DataFrame(batch))
    return table
