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

Refinement (`--refine`) and robust mode (`--robust`) on the same frames, each beside a C++ reference:

- refine: `refine_pose` from our solver's solution against PoseLib's generalized refinement
  (`poselib.refine_generalized_absolute_pose`, LM with the plain squared loss) from the same pose.
  The costs differ in their units, not in their minima at this field of view: ours is the sum of
  squared sines of the ray angles (the tangent-plane residuals of `refine.py`), PoseLib's the sum
  of squared pixel reprojection errors. PoseLib is given the points centred on their mean (in map
  coordinates it needs ~15 iterations instead of 2) and its per-camera lists, built outside the
  timing; ours centres inside it. The two are timed back to back on each frame, REFINE_ROUNDS
  times over the frames (a busy machine then slows both alike), and their ratio is printed for the
  fewest and most points. PoseLib is optional (`pip install -e '.[bench]'`): without it
  its columns are NaN and the bench says so.
- robust: `solve_robust` (LO-RANSAC over gP3P, then the global solver on the inliers) against
  pycolmap's generalized LO-RANSAC with refinement (`estimate_and_refine_generalized_absolute_pose`)
  on the frames with 40% wrong ids (each of a random 40% of the observations given the world
  point of another one of them), both with a 12 px threshold; rotation errors against the truth
  and the count of frames where a method found no pose.

Fallback rows (`bench_fallback`): how often the solver's global fallback (`pose/fallback.py`)
ran on the DMAIS frames above and on hard frames of `bench.pose_hard` (one narrow camera over flat
ground; C0 alone), with its median and largest time per fallback solve.

Stage throughput (`bench_stage`): a generated observation-only flight (`stage_flight`: the
simulator's paper rig hovering at 350 m over flat sites, 8 ground markers per camera footprint,
every marker seen in every frame of its group, 3 px pixel noise; `--stage-frames`, 10,000 by
default) through the pose stage's `estimate_poses` (indexing, rays, solves, residuals,
covariances, the tables), timed alone (frames per wall second, and per CPU second of the process,
which a busy machine disturbs less), then once more under tracemalloc for its peak memory; with the
process's peak resident size.
"""

from __future__ import annotations

import os
import resource
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from ..blas import single_threaded_blas
from ..dataset import CameraSpec, Dataset
from ..files import write_csv_atomic
from ..geometry import Rigid3, rotation_error
from ..errors import PoseError
from ..pose.refine import refine_pose
from ..pose.robust import solve_robust
from ..pose.solver import solve_batch, solve_generalized_pose

POINT_COUNTS = (10, 50, 100, 200, 300, 400, 500)
PAPER_TABLE = Path(__file__).resolve().parents[1] / "report" / "paper_tables" / "time_points.csv"
FOCAL_PX, WIDTH, HEIGHT, NOISE_PX = 45000.0, 4096, 3000, 4.0
#: Robust columns: the fraction of observations given a wrong id, and both methods' inlier threshold.
WRONG_IDS, ROBUST_THRESHOLD_PX = 0.4, 12.0
#: Refine columns: passes over the frames, each timing ours and PoseLib back to back per frame.
REFINE_ROUNDS = 5
COSTS_NOTE = ("refine costs: ours sum of squared sines of the ray angles (tangent-plane residuals), PoseLib sum of "
              "squared pixel reprojection errors (plain loss); robust: both LO-RANSAC, {threshold:g} px threshold, "
              "{wrong:.0%} wrong ids")
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
#: The same for `_rays`: pixel to rig-frame direction of each camera as an affine map, (5, 3, 3)
#: on (u, v, 1): rig_from_cam @ [[1/f, 0, -cx/f], [0, 1/f, -cy/f], [0, 0, 1]].
_RIG_FROM_PIXEL = _RIG_FROM_CAM @ np.array([[1 / FOCAL_PX, 0, -(WIDTH - 1) / 2 / FOCAL_PX],
                                            [0, 1 / FOCAL_PX, -(HEIGHT - 1) / 2 / FOCAL_PX], [0, 0, 1]])


def _rays(cams, uv):
    """Ray origins and directions (n, 3) in the rig frame of pixels uv (n, 2) of cameras cams (n,)."""
    A = _RIG_FROM_PIXEL[cams]
    return _CENTRES[cams], A[:, :, 0] * uv[:, :1] + A[:, :, 1] * uv[:, 1:] + A[:, :, 2]


def _pycolmap_solver():
    import pycolmap

    camera = pycolmap.Camera(model="PINHOLE", width=WIDTH, height=HEIGHT,
                             params=[FOCAL_PX, FOCAL_PX, (WIDTH - 1) / 2 + 0.5, (HEIGHT - 1) / 2 + 0.5])
    cams_from_rig = []
    for k in range(5):
        R, centre = dmais_cam_from_rig(k)
        cams_from_rig.append(pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre))
    options = pycolmap.RANSACOptions()
    options.max_error = ROBUST_THRESHOLD_PX

    def solve(cams, uv, points):
        # COLMAP puts the centre of the top-left pixel at (0.5, 0.5)
        result = pycolmap.estimate_and_refine_generalized_absolute_pose(
            uv + 0.5, points, [int(c) for c in cams], cams_from_rig, [camera] * 5, options)
        if result is None:
            raise PoseError("pycolmap found no pose")
        pose = result["rig_from_world"]
        return pose.rotation.matrix(), np.asarray(pose.translation)

    return solve


def _poselib_refiner():
    """PoseLib's generalized refinement as refine(cams, uv, points, R0, t0) -> (R, t), timing only
    the call (inputs per camera and centred beforehand), or None when poselib is not installed."""
    try:
        import poselib
    except ImportError:
        return None
    rig = []
    for k in range(5):
        R, centre = dmais_cam_from_rig(k)
        pose = poselib.CameraPose()
        pose.R, pose.t = R, -R @ centre
        rig.append(pose)
    # PoseLib's pixel centres are at integer coordinates, like ours
    camera = {"model": "PINHOLE", "width": WIDTH, "height": HEIGHT,
              "params": [FOCAL_PX, FOCAL_PX, (WIDTH - 1) / 2, (HEIGHT - 1) / 2]}
    options = {"loss_type": "TRIVIAL"}

    def refine(cams, uv, points, R0, t0):
        centroid = points.mean(axis=0)
        pixels = [np.ascontiguousarray(uv[cams == k]) for k in range(5)]
        world = [np.ascontiguousarray(points[cams == k] - centroid) for k in range(5)]
        start = poselib.CameraPose()
        start.R, start.t = R0, t0 + R0 @ centroid
        begin = time.perf_counter()
        pose, _ = poselib.refine_generalized_absolute_pose(pixels, world, start, rig, [camera] * 5, options)
        elapsed = time.perf_counter() - begin
        return pose.R, pose.t - pose.R @ centroid, elapsed

    return refine


def with_wrong_ids(rng, points: np.ndarray, fraction: float = WRONG_IDS) -> np.ndarray:
    """Points (n, 3) with a random `fraction` of them given the world point of another one of them
    (a cyclic shift within that subset: every one of them is wrong)."""
    points = points.copy()
    wrong = rng.permutation(len(points))[: int(round(fraction * len(points)))]
    points[wrong] = points[np.roll(wrong, 1)]
    return points


def _median_ms(solve, frames) -> tuple[float, float, int]:
    """Median time per solve (ms), median rotation error (arc-min) and the number of frames with no
    pose (a PoseError or a non-finite rotation) over frames; solve returns (R, t) or (R, t, seconds)
    where it times itself."""
    times, errors, failed = [], [], 0
    for cams, uv, points, (R, _) in frames:
        start = time.perf_counter()
        try:
            found = solve(cams, uv, points)
        except PoseError:
            found = None
        times.append(found[2] if found is not None and len(found) == 3 else time.perf_counter() - start)
        if found is None or not np.isfinite(found[0]).all():
            failed += 1
            errors.append(np.pi)
        else:
            errors.append(rotation_error(found[0], R))
    return float(np.median(times) * 1e3), float(np.rad2deg(np.median(errors)) * 60), failed


def _paired_median_ms(refine, reference, frames, rounds: int = REFINE_ROUNDS) -> tuple[float, float, float, float]:
    """Median time per call (ms) and median rotation error (arc-min) of two refinements that time
    themselves (each returns (R, t, seconds)), called back to back on every frame, `rounds` passes
    over the frames: (refine ms, arc-min, reference ms, arc-min); NaN for a reference of None."""
    times, errors = ([], []), ([], [])
    for _ in range(rounds):
        for cams, uv, points, (R_true, _) in frames:
            for k, method in enumerate((refine, reference)):
                if method is not None:
                    R, _, seconds = method(cams, uv, points)
                    times[k].append(seconds)
                    errors[k].append(rotation_error(R, R_true))
    ms = [float(np.median(x) * 1e3) if x else np.nan for x in times]
    arcmin = [float(np.rad2deg(np.median(x)) * 60) if x else np.nan for x in errors]
    return ms[0], arcmin[0], ms[1], arcmin[1]


#: Stage throughput flight: frames per group (one hover site each), pixel noise per axis.
STAGE_FRAMES_PER_GROUP, STAGE_NOISE_PX, STAGE_MARKERS_PER_CAMERA = 500, 3.0, 8


def stage_flight(rng, n_frames: int):
    """An observation-only flight of n_frames frames for the pose stage, built in memory.

    Returns (Dataset, truth Rig, observations (image, camera, point_id, u, v)). Each group of
    STAGE_FRAMES_PER_GROUP frames hovers (1 m, 0.2 deg) at 350 m above a flat site with
    STAGE_MARKERS_PER_CAMERA ground markers inside each camera's footprint; every marker inside an
    image is observed with STAGE_NOISE_PX pixel noise.
    """
    from ..sim.config import DEFAULTS
    from ..sim.scene import build_rig, look_rotation

    rig = build_rig(DEFAULTS["rig"])
    frames, points, observations = [], [], []
    for g, start in enumerate(range(0, n_frames, STAGE_FRAMES_PER_GROUP)):
        count = min(STAGE_FRAMES_PER_GROUP, n_frames - start)
        site = np.array([5e5 + 3e3 * g, 4e6, 100.0])
        nominal = look_rotation([0.0, 0.0, -1.0], down_hint=[np.cos(g), np.sin(g), 0.0])  # world_from_rig
        centre = site + [0.0, 0.0, 350.0]
        markers = _footprint_markers(rng, rig, nominal, centre, site[2], f"G{g:03d}_")
        world_from_rig = Rotation.from_rotvec(rng.normal(0, np.radians(0.2), (count, 3))).as_matrix() @ nominal
        centres = centre + rng.normal(0, 1.0, (count, 3))
        names = np.array([f"f{start + k:05d}" for k in range(count)])
        frames.append(pd.DataFrame({"frame": names, "group": f"g{g}", "pos_x": centres[:, 0], "pos_y": centres[:, 1],
                                    "pos_z": centres[:, 2]}))
        points.append(markers)
        x_rig = np.einsum("fji,fmj->fmi", world_from_rig, markers[["x", "y", "z"]].to_numpy()[None] - centres[:, None])
        for name, camera in rig.cameras.items():
            uv = rig.project_rig_points(name, x_rig.reshape(-1, 3))
            seen = np.isfinite(uv).all(axis=1) & camera.in_image(np.nan_to_num(uv, nan=-1e9), margin=5.0)
            frame_of, marker_of = np.divmod(np.flatnonzero(seen), len(markers))
            observations.append(pd.DataFrame({
                "image": np.char.add(names[frame_of], f"_{name}"), "camera": name,
                "point_id": markers.index.to_numpy()[marker_of],
                "u": uv[seen, 0] + rng.normal(0, STAGE_NOISE_PX, seen.sum()),
                "v": uv[seen, 1] + rng.normal(0, STAGE_NOISE_PX, seen.sum())}))
    observations = pd.concat(observations, ignore_index=True)
    return flight_dataset(rig, pd.concat(frames, ignore_index=True), pd.concat(points), observations), rig, observations


def flight_dataset(rig, frames: pd.DataFrame, points: pd.DataFrame, observations: pd.DataFrame) -> Dataset:
    """An in-memory observation-only flight Dataset (not validated; for benchmarks and tests).

    frames: frame, group, pos_x, pos_y, pos_z (+ extra columns, as text); points: x, y, z indexed by
    point_id; observations: image, camera, point_id, u, v with images named <frame>_<camera>.
    """
    frames = frames.copy()
    for quaternion in ("prior_qw", "prior_qx", "prior_qy", "prior_qz"):
        frames.insert(frames.columns.get_loc("pos_z") + 1 + "wxyz".index(quaternion[-1]), quaternion, np.nan)
    images = observations.drop_duplicates("image")[["image", "camera"]].reset_index(drop=True)
    images = images.assign(stage="flight", split="", placement=images["image"].str.rsplit("_", n=1).str[0], path="")
    spec = {name: CameraSpec(c.width, c.height, c.fx) for name, c in rig.cameras.items()}
    return Dataset(root=Path("in-memory-flight"), name="in-memory-flight", reference_camera=rig.reference_camera,
                   cameras=spec, marker_size_m=2.0, description="generated flight", control_points=_points_table([]),
                   ground_points=points, images=images, frames=frames, observations=observations.drop(columns="camera"))


def _footprint_markers(rng, rig, world_from_rig: np.ndarray, centre: np.ndarray, ground_z: float,
                       prefix: str) -> pd.DataFrame:
    """STAGE_MARKERS_PER_CAMERA ground points (x, y, z indexed by point_id) on the plane z = ground_z
    inside each camera's footprint (15% image margin) for a rig at centre with world_from_rig."""
    rows = []
    for name, camera in rig.cameras.items():
        uv = rng.uniform([0.15 * camera.width, 0.15 * camera.height], [0.85 * camera.width, 0.85 * camera.height],
                         (STAGE_MARKERS_PER_CAMERA, 2))
        world_from_cam = (rig.cam_from_rig[name] * Rigid3(world_from_rig.T, -world_from_rig.T @ centre)).inverse()
        rays = camera.unproject(uv) @ world_from_cam.R.T
        rows.append(world_from_cam.t + rays * ((ground_z - world_from_cam.t[2]) / rays[:, 2])[:, None])
    xyz = np.vstack(rows)
    return _points_table(xyz, [f"{prefix}{k:03d}" for k in range(len(xyz))])


def _points_table(xyz, ids=()) -> pd.DataFrame:
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    return pd.DataFrame(xyz, columns=["x", "y", "z"], index=pd.Index(list(ids), dtype=str, name="point_id"))


def bench_stage(n_frames: int, seed: int = 0) -> dict:
    """The pose stage on a generated flight of n_frames frames (`stage_flight`): frames/s of
    `estimate_poses` (paper conf) and its peak traced memory (MB)."""
    from ..pose.flight import estimate_poses

    dataset, rig, observations = stage_flight(np.random.default_rng(seed), n_frames)
    with single_threaded_blas():
        start, cpu_start = time.perf_counter(), time.process_time()
        table, _ = estimate_poses(dataset, rig, observations, rig.camera_names)
        seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu_start
        tracemalloc.start()
        estimate_poses(dataset, rig, observations, rig.camera_names)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return {"frames": n_frames, "observations": len(observations), "solved": len(table), "seconds": seconds,
            "frames_per_s": n_frames / seconds, "cpu_seconds": cpu_seconds, "frames_per_cpu_s": n_frames / cpu_seconds,
            "load_average": os.getloadavg()[0], "peak_traced_mb": peak / 2**20,
            "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "median_solve_ms": float(table["time_ms"].median()) if len(table) else np.nan}


#: Frames of the fallback rows beside the DMAIS frames above: kinds of `bench.pose_hard` where the
#: certificate often fails (one narrow camera over flat ground; the rig's C0 alone, subset #0).
FALLBACK_KINDS = ("narrow_10pt", "subset0_8pt")


def bench_fallback(dmais_fallback_ms: list[float], frames_per_kind: int, seed: int) -> pd.DataFrame:
    """The solver's global fallback (`pose/fallback.py`), one row per kind of frames: how often it
    ran (the certificate failed or the solution had most points behind) and its median and
    largest wall time per fallback solve (ms), beside its budget. dmais_fallback_ms: per solve of
    the DMAIS frames of the table, the fallback's time or NaN where it did not run; the hard
    kinds are solved here (frames_per_kind each, single-threaded BLAS)."""
    from ..pose.fallback import TIME_BUDGET_S
    from .pose_hard import KINDS, hard_scene

    runs = {"dmais (table above)": np.asarray(dmais_fallback_ms, dtype=float)}
    rng = np.random.default_rng([seed, 31])
    with single_threaded_blas():
        for kind in (k for k in KINDS if k.name in FALLBACK_KINDS):
            times = []
            for _ in range(frames_per_kind):
                scene = hard_scene(rng, kind)
                pose = solve_generalized_pose(scene.origins, scene.directions, scene.points)
                times.append(np.nan if pose.fallback_ms is None else pose.fallback_ms)
            runs[kind.name] = np.array(times)
    rows = []
    for name, ms in runs.items():
        ran = ms[np.isfinite(ms)]
        rows.append({"fallback_frames": name, "frames": len(ms), "fallback_runs": len(ran),
                     "fallback_share": len(ran) / max(len(ms), 1),
                     "fallback_median_ms": float(np.median(ran)) if len(ran) else np.nan,
                     "fallback_max_ms": float(ran.max()) if len(ran) else np.nan,
                     "budget_ms": TIME_BUDGET_S * 1e3})
    return pd.DataFrame(rows)


def bench_pose(csv: Path, repeats: int = 200, batch_frames: int = 200, seed: int = 0,
               stage_frames: int = 10_000) -> pd.DataFrame:
    """Run the benchmark, print the table and write it (and the batch and stage throughput) as CSV."""
    rng = np.random.default_rng(seed)
    paper = pd.read_csv(PAPER_TABLE).set_index("n_points")["paper_ms"] if PAPER_TABLE.is_file() else {}

    certified, fallback_ms = [], []

    def ours(cams, uv, points):
        origins, directions = _rays(cams, uv)
        pose = solve_generalized_pose(origins, directions, points)
        certified.append(pose.certified)
        fallback_ms.append(np.nan if pose.fallback_ms is None else pose.fallback_ms)
        return pose.R, pose.t

    starts = {}  # our solver's solution per frame: where both refinements start

    def ours_refine(cams, uv, points):
        origins, directions = _rays(cams, uv)
        R0, t0 = starts[id(points)]
        begin = time.perf_counter()
        refined = refine_pose(origins, directions, points, R0, t0)
        return refined.R, refined.t, time.perf_counter() - begin

    poselib_refine = _poselib_refiner()

    def poselib(cams, uv, points):
        return poselib_refine(cams, uv, points, *starts[id(points)])

    def ours_robust(cams, uv, points):
        origins, directions = _rays(cams, uv)
        result = solve_robust(origins, directions, points, ROBUST_THRESHOLD_PX / FOCAL_PX)
        return result.R, result.t

    colmap = _pycolmap_solver()
    rows = []
    with single_threaded_blas():
        for n in POINT_COUNTS:
            frames = [dmais_frame(rng, n) for _ in range(repeats)]
            certified.clear()
            ours_ms, ours_err, _ = _median_ms(ours, frames)
            colmap_ms, colmap_err, _ = _median_ms(colmap, frames)
            for cams, uv, points, _ in frames:
                pose = solve_generalized_pose(*_rays(cams, uv), points)
                starts[id(points)] = (pose.R, pose.t)
            refine_ms, refine_err, poselib_ms, poselib_err = _paired_median_ms(
                ours_refine, poselib if poselib_refine is not None else None, frames)
            starts.clear()
            wrong = [(cams, uv, with_wrong_ids(rng, points), truth) for cams, uv, points, truth in frames]
            robust_ms, robust_err, robust_failed = _median_ms(ours_robust, wrong)
            colmap_robust_ms, colmap_robust_err, colmap_failed = _median_ms(colmap, wrong)
            rows.append({"n_points": n, "ours_ms": ours_ms, "pycolmap_ms": colmap_ms,
                         "paper_ms": float(paper.get(n, np.nan)), "ours_rot_err_arcmin": ours_err,
                         "pycolmap_rot_err_arcmin": colmap_err, "ours_certified": float(np.mean(certified)),
                         "ours_refine_ms": refine_ms, "poselib_refine_ms": poselib_ms,
                         "refine_vs_poselib": refine_ms / poselib_ms,
                         "ours_refine_rot_err_arcmin": refine_err, "poselib_refine_rot_err_arcmin": poselib_err,
                         "ours_robust_ms": robust_ms, "pycolmap_robust_ms": colmap_robust_ms,
                         "ours_robust_rot_err_arcmin": robust_err, "pycolmap_robust_rot_err_arcmin": colmap_robust_err,
                         "ours_robust_failed": robust_failed, "pycolmap_robust_failed": colmap_failed})
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
    print(COSTS_NOTE.format(threshold=ROBUST_THRESHOLD_PX, wrong=WRONG_IDS))
    if poselib_refine is None:
        print("poselib_refine_ms: skipped: poselib not installed (pip install -e '.[bench]')")
    else:
        print("refine vs PoseLib (same start and points, back to back per frame): " + "; ".join(
            f"{row.n_points} points: ours {row.ours_refine_ms:.4f} ms, PoseLib {row.poselib_refine_ms:.4f} ms "
            f"({row.refine_vs_poselib:.2f}x)" for row in table.iloc[[0, -1]].itertuples()))
    for run in batch:
        print(f"batch: {run['frames_per_s']:.0f} frames/s in {run['workers']} thread(s) "
              f"(50 points per frame, rays precomputed, {batch_frames} frames)")
    fallback = bench_fallback(fallback_ms, repeats, seed)
    print(fallback.to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    write_csv_atomic(csv, table)
    write_csv_atomic(Path(csv).with_name(Path(csv).stem + "_batch.csv"), pd.DataFrame(batch))
    write_csv_atomic(Path(csv).with_name(Path(csv).stem + "_fallback.csv"), fallback)
    if stage_frames > 0:
        stage = bench_stage(stage_frames, seed)
        print(f"stage: {stage['frames_per_s']:.0f} frames/s through estimate_poses ({stage['frames']} frames, "
              f"{stage['observations']} observations, {stage['seconds']:.2f} s wall, {stage['cpu_seconds']:.2f} s CPU = "
              f"{stage['frames_per_cpu_s']:.0f} frames per CPU second, load average {stage['load_average']:.1f}, "
              f"median solve {stage['median_solve_ms']:.3f} ms); peak memory {stage['peak_traced_mb']:.0f} MB traced, "
              f"process max RSS {stage['max_rss_mb']:.0f} MB")
        write_csv_atomic(Path(csv).with_name(Path(csv).stem + "_stage.csv"), pd.DataFrame([stage]))
    return table
