"""`dmais bench pose --whole-stage`: the whole `dmais pose` stage on generated flights, as a user runs it.

Everything the stage does with its default settings is timed: loading the dataset, solving every frame,
the error model behind the sigmas, the rig watched in flight of every group (pose.mounting, whose normal
equations pose.group_normal solves) and writing the files. A calibration is simulated once
(observation-only, `CALIBRATION`) and calibrated by `dmais intrinsics` and `dmais extrinsics` in a work
folder; flights are then generated from the simulator's truth rig (`generated_flight`) into copies of
that dataset, and each is run as `dmais pose DATASET --out RESULTS` in a process of its own: its wall
time and peak resident memory.

Flights (the simulator's noise budget, docs/simulator.md: per group a site on its terrain, the rig 350 m
above it drifting by 1 m and 0.2 deg, 8 markers in each camera's footprint, 0.5 px pixel noise, 0.3
arc-min of vibration per axis and image, a survey of 1.5 cm horizontally and 2.5 cm vertically):

- `hover`: every frame of a group sees the group's markers (the simulator's hover pattern);
- `own`: every frame sees markers of its own (no point shared by two frames);
- `line`: frames 20 m apart along a line, markers placed for every frame, each image seeing every
  marker of its group in view (a marker is seen by a few frames).

Rows:

1. throughput: the simulator's flights (`simulated`: the paper's rig, noise and terrain, observation-only,
   two sites of one hovering group each) of 2 groups of 100 and of 1,100 frames, calibrated by the
   pipeline, as they are (`hover`) and with each frame's points given ids of their own (`own`,
   `own_points`); frames per second of the difference (2,200 frames less 200: the process's start and
   imports cancel). The simulator's flights, not generated ones: on these the solver's certificate fails
   and its global fallback runs on ~9% of the frames, on the simulator's on ~0.5%;
2. scaling: one group of 200 and one of 10,000 frames hovering and along a line (`SCALING_FRAMES`):
   seconds per frame and their ratio, peak memory;
3. dense reference: 2 groups of 40 frames of each kind through the stage in this process, once as it
   is and once with every solve of the group adjustment's normal equations replaced by a dense solve of
   the whole matrix (`dense_solve`, `dense_rig_columns`): the largest relative difference of mounting.csv's
   numbers, of poses.csv's sigmas and of the error budget.
"""

from __future__ import annotations

import logging
import os
from contextlib import nullcontext
import shutil
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd
from scipy import linalg
from scipy.spatial.transform import Rotation

from ..errors import DmaisError
from ..files import write_csv_atomic, write_yaml_atomic

log = logging.getLogger(__name__)

#: The calibration: the simulator's paper rig and field, observation-only, one flight frame per group.
CALIBRATION = {"name": "pose_stage_calibration", "seed": 5,
               "render": {"intrinsics": False, "extrinsics": False, "flight": False},
               "flight": {"frames_per_group": 1}}
MARKERS_PER_CAMERA, HEIGHT_M, LINE_SPACING_M = 8, 350.0, 20.0
PIXEL_NOISE_PX, VIBRATION_ARCMIN, SURVEY_M = 0.5, 0.3, (0.015, 0.015, 0.025)
#: A line's markers placed for frames this many before and after a frame are looked for in its images
#: (the tilted cameras look ~350 m ahead and behind: 18 frames at 20 m).
LINE_REACH_FRAMES = 25
THROUGHPUT_FRAMES, REFERENCE_FRAMES = (100, 1100), 40
#: Frames of the scaling rows' two groups per kind: a line's frames are tied over ~38 frames (C0 sees the
#: markers the forward camera saw 17 frames before, the backward camera 18 after): its frames' band factor
#: (group_normal._FramesBand) would hold F L 39 L numbers, 0.94 GiB at 10,000 frames of L = 18, and is made a
#: segment at a time instead.
SCALING_FRAMES = {"hover": (200, 10_000), "line": (200, 10_000)}


def generated_flight(rng, rig, kind: str, n_groups: int, frames_per_group: int):
    """(frames, ground_points, observations) tables of a flight of `kind` (module docstring): frames
    frame, group, pos_x, pos_y, pos_z; ground points point_id, x, y, z (surveyed); observations image,
    point_id, u, v with images <frame>_<camera>."""
    from ..sim.scene import look_rotation
    from .pose import _footprint_markers

    frames, points, observations = [], [], []
    for g in range(n_groups):
        site = np.array([1500.0 + 3e3 * g, -800.0, 45.0])  # the simulator's site A, groups 3 km apart
        nominal = look_rotation([0.0, 0.0, -1.0], down_hint=[np.cos(g), np.sin(g), 0.0])  # world_from_rig
        along = nominal @ [0.0, -1.0, 0.0] * (LINE_SPACING_M if kind == "line" else 0.0)
        k = np.arange(frames_per_group)
        planned = site + [0.0, 0.0, HEIGHT_M] + k[:, None] * along
        centres = planned + rng.normal(0, 1.0, (len(k), 3))
        world_from_rig = Rotation.from_rotvec(rng.normal(0, np.radians(0.2), (len(k), 3))).as_matrix() @ nominal
        names = np.array([f"g{g}f{i:05d}" for i in k])
        frames.append(pd.DataFrame({"frame": names, "group": f"g{g}", "pos_x": centres[:, 0],
                                    "pos_y": centres[:, 1], "pos_z": centres[:, 2]}))
        if kind == "hover":
            placed = [_footprint_markers(rng, rig, nominal, planned[0], site[2], f"G{g}_")]
        else:
            placed = [_footprint_markers(rng, rig, nominal if kind == "line" else world_from_rig[i],
                                         planned[i] if kind == "line" else centres[i], site[2], f"G{g}F{i:05d}_")
                      for i in k]
        placed = [_on_terrain(markers, site) for markers in placed]
        points.append(pd.concat(placed))
        for i in k:
            nearby = slice(max(0, i - LINE_REACH_FRAMES), i + LINE_REACH_FRAMES + 1)
            seen = placed[0] if kind == "hover" else placed[i] if kind == "own" else pd.concat(placed[nearby])
            observations.append(_observed(rng, rig, world_from_rig[i], centres[i], seen, names[i]))
    points = pd.concat(points)
    surveyed = points[["x", "y", "z"]].to_numpy() + rng.normal(0, SURVEY_M, (len(points), 3))
    ground = pd.DataFrame(surveyed, columns=["x", "y", "z"]).assign(point_id=points.index.to_numpy())
    return (pd.concat(frames, ignore_index=True), ground[["point_id", "x", "y", "z"]],
            pd.concat(observations, ignore_index=True))


def _on_terrain(markers: pd.DataFrame, site: np.ndarray) -> pd.DataFrame:
    """`markers` (x, y, z by point_id) raised onto the simulator's terrain about `site` (sim.scene.terrain_height:
    +-3 m; over flat ground the narrow cameras leave the solver's certificate failing on a fifth of the frames)."""
    from ..sim.config import DEFAULTS
    from ..sim.scene import terrain_height

    z = terrain_height(DEFAULTS, site, markers[["x", "y"]].to_numpy()) - site[2]
    return markers.assign(z=markers["z"] + z)


def _observed(rng, rig, world_from_rig: np.ndarray, centre: np.ndarray, markers: pd.DataFrame,
              frame: str) -> pd.DataFrame:
    """The observations of `markers` (x, y, z by point_id) in the images of one frame, with the noise."""
    x_rig = (markers[["x", "y", "z"]].to_numpy() - centre) @ world_from_rig
    rows = []
    for name, camera in rig.cameras.items():
        vibration = Rotation.from_rotvec(rng.normal(0, np.radians(VIBRATION_ARCMIN / 60.0), 3)).as_matrix()
        uv = camera.project(rig.cam_from_rig[name].apply(x_rig) @ vibration.T)
        uv = uv + rng.normal(0, PIXEL_NOISE_PX, uv.shape)
        seen = np.isfinite(uv).all(axis=1) & camera.in_image(np.nan_to_num(uv, nan=-1e9), margin=5.0)
        uv = uv[seen]
        rows.append(pd.DataFrame({"image": f"{frame}_{name}", "point_id": markers.index.to_numpy()[seen],
                                  "u": uv[:, 0], "v": uv[:, 1]}))
    return pd.concat(rows, ignore_index=True)


# ------------------------------------------------------------------------------ datasets and runs


def calibrated(work: Path) -> tuple[Path, Path]:
    """(dataset, results) of the simulated and calibrated `CALIBRATION` under `work`, made once."""
    return _simulated_and_calibrated(work, "calibration", CALIBRATION)


def _simulated_and_calibrated(work: Path, name: str, config: dict) -> tuple[Path, Path]:
    """(dataset, results) under work/name: the simulator's dataset of `config`, calibrated by dmais
    intrinsics and extrinsics; made once (kept while its rig.json is there)."""
    dataset, results = work / name / "dataset", work / name / "results"
    if (results / "rig.json").is_file():
        return dataset, results
    shutil.rmtree(work / name, ignore_errors=True)
    path = work / f"{name}.yaml"
    write_yaml_atomic(path, config)
    _dmais("simulate", str(path), "--out", str(dataset), "--jobs", "2")
    for stage in ("intrinsics", "extrinsics"):
        _dmais(stage, str(dataset), "--out", str(results))
    return dataset, results


def flight_folders(work: Path, calibration: tuple[Path, Path], name: str, flight) -> tuple[Path, Path]:
    """(dataset, results) folders of a generated `flight` (`generated_flight`) under work/name: the
    calibration's dataset with the flight in place of its own, and a copy of its results."""
    source, calibrated_results = calibration
    dataset, results = work / name / "dataset", work / name / "results"
    shutil.rmtree(work / name, ignore_errors=True)
    dataset.mkdir(parents=True)
    for file in ("dataset.yaml", "control_points.csv"):
        shutil.copy(source / file, dataset / file)
    frames, ground, observations = flight
    images = pd.read_csv(source / "images.csv", dtype=str, keep_default_na=False)
    images = images[images["stage"] != "flight"]
    flight_images = observations.drop_duplicates("image")[["image"]].assign(
        camera=lambda t: t["image"].str.rsplit("_", n=1).str[1], stage="flight", split="",
        placement=lambda t: t["image"].str.rsplit("_", n=1).str[0], path="")
    write_csv_atomic(dataset / "images.csv", pd.concat([images, flight_images], ignore_index=True))
    given = pd.read_csv(source / "observations.csv", dtype={"image": str, "point_id": str})
    given = given[given["image"].isin(set(images["image"]))]
    write_csv_atomic(dataset / "observations.csv", pd.concat([given, observations], ignore_index=True))
    write_csv_atomic(dataset / "frames.csv", frames)
    write_csv_atomic(dataset / "ground_points.csv", ground)
    shutil.copytree(calibrated_results, results)
    return dataset, results


def timed_pose(dataset: Path, results: Path) -> dict:
    """`dmais pose dataset --out results` in a process of its own: wall and CPU seconds (a busy machine
    slows the first more), peak RSS (MB)."""
    log_path = results.parent / "pose.log"
    with open(log_path, "wb") as log_file:
        start = time.perf_counter()
        process = subprocess.Popen(_command("pose", str(dataset), "--out", str(results)), stdout=log_file,
                                   stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)  # the child's own peak memory
        seconds = time.perf_counter() - start
    process.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
    if process.returncode:
        lines = log_path.read_text(errors="replace").strip().splitlines()
        raise DmaisError(f"bench pose: dmais pose {dataset} failed: {lines[-1] if lines else process.returncode}")
    return {"seconds": seconds, "cpu_seconds": usage.ru_utime + usage.ru_stime, "max_rss_mb": usage.ru_maxrss / 1024}


def _command(*args: str) -> list[str]:
    return [sys.executable, "-m", "dmais_pipe.cli", *args]


def _dmais(*args: str) -> None:
    done = subprocess.run(_command(*args), capture_output=True, text=True)
    if done.returncode:
        raise DmaisError(f"bench pose: dmais {' '.join(args)} failed: {done.stderr.strip().splitlines()[-1:]}")


def simulated(work: Path, frames_per_group: int) -> tuple[Path, Path]:
    """(dataset, results) of the simulator's flight of 2 hovering groups of `frames_per_group` frames (one per
    site), calibrated by dmais intrinsics and extrinsics, under `work`; made once."""
    name = f"simulated_{frames_per_group}"
    sites = {"A": {"center_m": [1500.0, -800.0, 45.0], "groups": [1]},
             "B": {"center_m": [-2200.0, 1800.0, 120.0], "groups": [2]}}
    return _simulated_and_calibrated(work, name, {**CALIBRATION, "name": name, "flight": {
        "frames_per_group": frames_per_group, "sites": sites}})


def own_points(source: tuple[Path, Path], out: Path) -> tuple[Path, Path]:
    """(dataset, results) under `out`: the dataset `source` with every flight frame's ground points given
    ids of their own (the same coordinates, one copy per frame), its results copied."""
    dataset, results = out / "dataset", out / "results"
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(source[0], dataset)
    shutil.copytree(source[1], results)
    observations = pd.read_csv(dataset / "observations.csv", dtype={"image": str, "point_id": str})
    images = pd.read_csv(dataset / "images.csv", dtype=str, keep_default_na=False)
    frame_of = images.loc[images["stage"] == "flight"].set_index("image")["placement"]
    flight = observations["image"].isin(frame_of.index).to_numpy()
    old = observations.loc[flight, "point_id"].to_numpy()
    new = frame_of.loc[observations.loc[flight, "image"]].to_numpy() + "_" + old
    points = pd.read_csv(dataset / "ground_points.csv", dtype={"point_id": str}).set_index("point_id")
    copies = points.loc[old].set_index(pd.Index(new, name="point_id"))
    observations.loc[flight, "point_id"] = new
    write_csv_atomic(dataset / "observations.csv", observations)
    write_csv_atomic(dataset / "ground_points.csv", copies[~copies.index.duplicated()].reset_index())
    return dataset, results


def fresh_results(folders: tuple[Path, Path], out: Path) -> tuple[Path, Path]:
    """(dataset, a copy of results under `out`): a run's own results folder beside the calibration's."""
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(folders[1], out)
    return folders[0], out


# ------------------------------------------------------------------------------ the dense reference


def dense_solve(normal, right):
    """pose.group_normal.solve's result by a dense solve of the whole normal matrix (the reference): LU
    with partial pivoting and two steps of iterative refinement."""
    s = normal.structure
    matrix = normal.dense()
    right = np.asarray(right, dtype=float).reshape(s.size, -1 if np.size(right) else 0)
    first = s.n_frames * s.local_size
    rig = np.zeros((s.size, s.rig_size))
    rig[first + np.arange(s.rig_size), np.arange(s.rig_size)] = 1.0
    right_sides = np.hstack([right, rig])
    lu = linalg.lu_factor(matrix)
    solution = linalg.lu_solve(lu, right_sides)
    for _ in range(2):  # iterative refinement: the whole matrix is ill-conditioned along the rig's weak directions
        solution += linalg.lu_solve(lu, right_sides - matrix @ solution)
    return solution[:, :right.shape[1]], solution[first:first + s.rig_size, right.shape[1]:]


def dense_rig_columns(normal):
    """pose.group_normal.rig_columns's result by `dense_solve` of the rig's unit columns."""
    s = normal.structure
    unit = np.zeros((s.size, s.rig_size))
    unit[s.n_frames * s.local_size + np.arange(s.rig_size), np.arange(s.rig_size)] = 1.0
    return dense_solve(normal, unit)


def reference_differences(dataset: Path, results: Path) -> dict:
    """The stage run in this process as it is and with `dense_solve` (and `dense_rig_columns`): the largest
    relative differences
    of mounting.csv's numbers, poses.csv's sigmas and the error budget's numbers (relative to the
    largest magnitude of each column)."""
    from ..pose import group_normal
    from ..stages import pose as stage
    from ..workspace import Workspace

    tables = {}
    for name, patch in (("blocks", None), ("dense", dense_solve)):
        out = results.parent / f"results_{name}"
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(results, out)
        with (mock.patch.multiple(group_normal, solve=patch, rig_columns=dense_rig_columns) if patch else
              nullcontext()):
            stage.run(Workspace.open(dataset, out), stage.Conf())
        tables[name] = {kind: pd.read_csv(out / f"poses{suffix}") for kind, suffix in
                        (("mounting", ".mounting.csv"), ("poses", ".csv"), ("budget", ".budget.csv"))}
    return {f"{kind}_max_rel": _largest_relative(tables["blocks"][kind], tables["dense"][kind],
                                                 sigmas_only=kind == "poses") for kind in tables["blocks"]}


def _largest_relative(a: pd.DataFrame, b: pd.DataFrame, sigmas_only: bool) -> float:
    columns = [c for c in a.select_dtypes("number").columns if c != "time_ms" and (not sigmas_only or "sigma" in c)]
    x, y = a[columns].to_numpy(float), b[columns].to_numpy(float)
    scale = np.nanmax(np.abs(x), axis=0)
    return float(np.nanmax(np.abs(x - y) / np.where(scale > 0, scale, 1.0)))


# ------------------------------------------------------------------------------ the bench


def bench_whole_stage(csv: Path, work: Path, seed: int = 0) -> pd.DataFrame:
    """Run the rows of the module docstring; print the table and write it as CSV."""
    from ..sim.config import DEFAULTS
    from ..sim.scene import build_rig

    rig = build_rig(DEFAULTS["rig"])
    rng = np.random.default_rng(seed)
    work.mkdir(parents=True, exist_ok=True)
    calibration = calibrated(work)
    rows = []

    def run(kind: str, groups: int, frames: int) -> dict:
        flight = generated_flight(rng, rig, kind, groups, frames)
        folders = flight_folders(work, calibration, f"{kind}_{groups}x{frames}", flight)
        timing = timed_pose(*folders)
        shutil.rmtree(work / f"{kind}_{groups}x{frames}")
        row = {"kind": kind, "groups": groups, "frames_per_group": frames, "frames": groups * frames,
               "observations": len(flight[2]), **timing}
        log.info("bench pose: %s", row)
        return row

    simulations = {n: simulated(work, n) for n in THROUGHPUT_FRAMES}
    for kind in ("hover", "own"):
        timings = []
        for n, folders in simulations.items():
            out = work / f"throughput_{kind}_{n}"
            folders = own_points(folders, out) if kind == "own" else fresh_results(folders, out / "results")
            timings.append({"kind": kind, "groups": 2, "frames_per_group": n, "frames": 2 * n, **timed_pose(*folders)})
            shutil.rmtree(out)
        small, large = timings
        frames = large["frames"] - small["frames"]
        marginal = {"marginal_frames_per_s": frames / (large["seconds"] - small["seconds"]),
                    "marginal_frames_per_cpu_s": frames / (large["cpu_seconds"] - small["cpu_seconds"])}
        rows += [dict(small, measure="throughput"), dict(large, measure="throughput", **marginal)]
    for kind, sizes in SCALING_FRAMES.items():
        small, large = (run(kind, 1, n) for n in sizes)
        per_frame = [r["seconds"] / r["frames"] for r in (small, large)]
        rows += [dict(small, measure="scaling", s_per_frame=per_frame[0]),
                 dict(large, measure="scaling", s_per_frame=per_frame[1], per_frame_ratio=per_frame[1] / per_frame[0])]
    for kind in ("hover", "own", "line"):
        folders = flight_folders(work, calibration, f"reference_{kind}",
                                 generated_flight(rng, rig, kind, 2, REFERENCE_FRAMES))
        rows.append({"measure": "dense reference", "kind": kind, "groups": 2, "frames_per_group": REFERENCE_FRAMES,
                     "frames": 2 * REFERENCE_FRAMES, **reference_differences(*folders)})
        shutil.rmtree(work / f"reference_{kind}")
    table = pd.DataFrame(rows)
    print(table.to_string(index=False, float_format=lambda x: f"{x:.4g}"))
    write_csv_atomic(csv, table)
    return table
