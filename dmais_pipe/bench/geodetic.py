"""`dmais bench geodetic`: the same observations solved in real-world coordinates and in a local ENU
frame (issue 41's figures).

From a simulator preset with `geodetic` settings (default config/simulate/geodetic.yaml: UTM 33N at
the zone's edge, flights 15 km from the field), three runs of the chain (intrinsics `ours`,
extrinsics, pose with every camera), each in WORK/<run>:

- `local`: the preset with `geodetic.crs` null: the same world, observations and noise draws (each
  part of the simulation draws from its own stream), written in the ENU frame at the origin, no crs;
- `crs`: the preset as it is: the survey in crs, POS and RTK priors in pos_crs, dataset.yaml's
  origin the simulator's;
- `crs_default_origin`: the same files without dataset.yaml's origin, so the computation frame is
  the topocentric frame at the control points' mean instead;
- `crs_sbet`: the preset with `geodetic.trajectory: sbet`: frames.csv gives each frame's time, the
  POS positions and INS attitudes come from a 200 Hz SBET (sim/pos.py);
- `utm_as_metric`: the mistake the pipeline used to invite: the crs dataset's files with the POS and
  RTK positions converted to the crs too (pyproj) and no crs in dataset.yaml, so that the map
  projection's coordinates are taken as a metric frame; its x, y, z read as UTM with ellipsoidal
  heights, its heading, pitch, roll (grid east, north, up) as the NED attitude, as a user would.

Per run, against truth/frames.csv (its lat_deg, lon_deg, h_m and ned_* angles): the RMS over the
frames of the rig centre's 3-D error (the estimate's WGS 84 lat/lon/h, or for `local` its ENU x, y,
z, and the truth's, both to geocentric by pyproj), its mean north, east and down errors, and the RMS
attitude error (the angle of ned_from_rig estimated times the truth's inverse; for `local`
rig_from_world's, the same angle); then the largest distance between poses.csv's x, y, z and
pyproj's conversion of its lat/lon/h into crs, each camera's calibrated fx, fy against the local
run's, and (evaluate) the largest difference of the rig centres, the lever arm's components (mm) and
the boresight's (arc-min) from the `crs` run's. The CSV has one row per run.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from ..files import write_csv_atomic, write_yaml_atomic
from ..geo import crs_from_ecef, ecef_from_crs, ecef_from_enu, ecef_from_geodetic, ned_from_ecef
from ..geometry import rotation_error, rotation_from_euler_zyx, rotation_from_quat
from ..sim.config import load_config
from ..sim.simulate import simulate
from ..stages import evaluate, extrinsics, intrinsics, pose
from ..workspace import CENTER, QUAT, Workspace

log = logging.getLogger(__name__)

ARCMIN_PER_RAD = 60.0 * 180.0 / np.pi
RUNS = ("local", "crs", "crs_default_origin", "crs_sbet", "utm_as_metric")
#: NED axes from east-north-up ones.
NED_FROM_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
NED_ANGLES = ("ned_heading_deg", "ned_pitch_deg", "ned_roll_deg")


def bench_geodetic(csv: Path, preset: Path = Path("config/simulate/geodetic.yaml"),
                   work: Path | None = None) -> pd.DataFrame:
    """The table of the three runs (module docstring), written to `csv`."""
    config = load_config(preset)
    if config["geodetic"]["crs"] is None:
        raise ValueError(f"{preset}: the preset has no geodetic.crs")
    with tempfile.TemporaryDirectory(prefix="dmais-bench-geodetic-") as scratch:
        root = Path(work) if work is not None else Path(scratch)
        datasets = simulated_pair(preset, root)
        results = {run: calibrated_poses(datasets[run], root / run) for run in RUNS}
        truth = pd.read_csv(datasets["crs"] / "truth" / "frames.csv", dtype={"frame": str}).set_index("frame")
        table = pd.DataFrame([{**run_row(run, *results[run], results["local"][1], truth, config),
                               **pos_calibration_row(results[run][0], results["crs"][0])} for run in RUNS])
    write_csv_atomic(csv, table)
    return table


def simulated_pair(preset: Path, root: Path) -> dict[str, Path]:
    """The preset simulated as it is (crs), with geodetic.crs null (local), and the crs dataset's
    copy without dataset.yaml's origin (crs_default_origin); {run: dataset folder}."""
    settings = yaml.safe_load(Path(preset).read_text())
    local = {**settings, "geodetic": {**settings["geodetic"], "crs": None}}
    folders = {}
    sbet = {**settings, "geodetic": {**settings["geodetic"], "trajectory": "sbet"}}
    for run, chosen in (("crs", settings), ("local", local), ("crs_sbet", sbet)):
        write_yaml_atomic(root / f"{run}.yaml", chosen)
        folders[run] = simulate(root / f"{run}.yaml", root / run / "dataset")
    copy = root / "crs_default_origin" / "dataset"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(folders["crs"], copy)
    manifest = yaml.safe_load((copy / "dataset.yaml").read_text())
    manifest.pop("origin")
    write_yaml_atomic(copy / "dataset.yaml", manifest)
    folders["crs_default_origin"] = copy
    folders["utm_as_metric"] = utm_as_metric(folders["crs"], root / "utm_as_metric" / "dataset")
    return folders


def utm_as_metric(source: Path, copy: Path) -> Path:
    """A copy of the crs dataset `source` with its pos_crs positions (frames.csv pos_*, images.csv
    prior_x..z) converted to its crs and dataset.yaml without crs, pos_crs and origin."""
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(source, copy)
    manifest = yaml.safe_load((copy / "dataset.yaml").read_text())
    crs, pos_crs = manifest.pop("crs"), manifest.pop("pos_crs")
    manifest.pop("origin", None)
    write_yaml_atomic(copy / "dataset.yaml", manifest)
    for name, columns in (("frames.csv", ["pos_x", "pos_y", "pos_z"]), ("images.csv", ["prior_x", "prior_y", "prior_z"])):
        table = pd.read_csv(copy / name, dtype=str, keep_default_na=False)
        xyz = table[columns].replace("", "nan").to_numpy(float)
        given = np.isfinite(xyz).all(axis=1)
        xyz[given] = crs_from_ecef(crs, ecef_from_crs(pos_crs, xyz[given]))
        table[columns] = [[repr(float(v)) if np.isfinite(v) else "" for v in row] for row in xyz]
        table.to_csv(copy / name, index=False)
    return copy


def calibrated_poses(dataset: Path, folder: Path) -> tuple[Workspace, dict, pd.DataFrame]:
    """The chain on `dataset` into `folder`: the workspace, the calibrated {camera: (fx, fy)} and
    poses.csv as written (x, y, z in the dataset's crs)."""
    workspace = Workspace.open(dataset, folder)
    intrinsics.run(workspace, intrinsics.CONFS["ours"])
    extrinsics.run(workspace)
    pose.run(workspace)
    evaluate.run(workspace)
    rig = workspace.load_rig()
    focal = {name: (camera.fx, camera.fy) for name, camera in rig.cameras.items()}
    written = pd.read_csv(workspace.poses_path(), dtype={"frame": str, "group": str})
    return workspace, focal, written


def run_row(run: str, workspace: Workspace, focal: dict, poses: pd.DataFrame, local_focal: dict,
            truth: pd.DataFrame, config: dict) -> dict:
    """One row of the table (module docstring); truth: the crs run's truth/frames.csv by frame (the
    local run's has no geodetic columns; the world is the same)."""
    truth = truth.loc[poses["frame"]]
    true_ecef = ecef_from_geodetic(truth[["lat_deg", "lon_deg", "h_m"]].to_numpy(float))
    true_ned = rotation_from_euler_zyx(np.radians(truth[list(NED_ANGLES)].to_numpy(float)))
    geo = workspace.dataset.geo
    if run == "utm_as_metric":  # x, y, z read as crs coordinates, the world's axes as east, north, up
        ecef = ecef_from_crs(config["geodetic"]["crs"], poses[list(CENTER)].to_numpy(float))
        taken = NED_FROM_ENU @ np.swapaxes(rotation_from_quat(poses[list(QUAT)].to_numpy(float)), 1, 2)
        attitude = rotation_error(taken, true_ned)
        xyz_mm = np.nan
    elif geo is None:  # local: x, y, z in the ENU frame at the simulator's origin
        origin = tuple(config["geodetic"]["origin"])
        ecef = ecef_from_enu(origin, poses[list(CENTER)].to_numpy(float))
        attitude = rotation_error(rotation_from_quat(poses[list(QUAT)].to_numpy(float)),
                                  rotation_from_quat(truth[list(QUAT)].to_numpy(float)))
        xyz_mm = np.nan
    else:
        ecef = ecef_from_geodetic(poses[["lat_deg", "lon_deg", "h_m"]].to_numpy(float))
        estimated_ned = rotation_from_euler_zyx(np.radians(poses[list(NED_ANGLES)].to_numpy(float)))
        attitude = rotation_error(estimated_ned, true_ned)
        in_crs = crs_from_ecef(geo.crs, ecef)
        xyz_mm = 1e3 * float(np.max(np.linalg.norm(in_crs - poses[list(CENTER)].to_numpy(float), axis=1)))
    ned_error = np.einsum("fij,fj->fi", ned_from_ecef(truth[["lat_deg", "lon_deg", "h_m"]].to_numpy(float)),
                          ecef - true_ecef)
    row = {"run": run, "n_frames": len(poses),
           "pos_rms_m": float(np.sqrt(np.mean(np.sum((ecef - true_ecef) ** 2, axis=1)))),
           **{f"mean_{axis}_m": float(v) for axis, v in zip(("north", "east", "down"), ned_error.mean(axis=0))},
           "att_rms_arcmin": float(np.sqrt(np.mean(attitude ** 2))) * ARCMIN_PER_RAD,
           "xyz_vs_pyproj_max_mm": xyz_mm,
           "focal_vs_local_max_px": max(abs(a - b) for name in focal for a, b in zip(focal[name], local_focal[name]))}
    row.update({f"{name}_fx": fx for name, (fx, _) in focal.items()})
    return row


def pos_calibration_row(workspace: Workspace, reference: Workspace) -> dict:
    """The largest difference of the rig centres (mm), of tables/lever_arm.csv's lever arm (mm) and
    boresight (arc-min) of `workspace` from those of `reference` (the crs run)."""
    tables = [w.load_table("lever_arm").set_index("parameter")["value"] for w in (workspace, reference)]
    lever = [f"lever_{a}" for a in "xyz"]
    boresight = [f"boresight_{a}" for a in "xyz"]
    centres = [w.load_poses()[list(CENTER)].to_numpy(float) for w in (workspace, reference)]
    comparable = workspace.dataset.geo is not None and workspace.dataset.geo.origin == reference.dataset.geo.origin
    return {"centres_vs_crs_max_mm": 1e3 * float(np.abs(centres[0] - centres[1]).max()) if comparable else np.nan,
            "lever_vs_crs_max_mm": 1e3 * float(np.abs(tables[0][lever] - tables[1][lever]).max()),
            "boresight_vs_crs_max_arcmin": float(np.abs(tables[0][boresight] - tables[1][boresight]).max())}


def print_table(table: pd.DataFrame, csv: Path) -> None:
    """The table, then the issue's figures: each crs run's position and attitude RMS against
    1.05 x the local run's (+ 2 mm, + 0.02')."""
    print(table.to_string(index=False, float_format="{:.6g}".format))
    local = table.set_index("run").loc["local"]
    for row in table[table["run"] != "local"].itertuples(index=False):
        position_ok = row.pos_rms_m <= 1.05 * local.pos_rms_m + 0.002
        attitude_ok = row.att_rms_arcmin <= 1.05 * local.att_rms_arcmin + 0.02
        print(f"{row.run}: position {row.pos_rms_m:.4f} m vs local {local.pos_rms_m:.4f} m "
              f"({'within' if position_ok else 'NOT within'} 1.05x + 2 mm); attitude {row.att_rms_arcmin:.3f}' vs "
              f"{local.att_rms_arcmin:.3f}' ({'within' if attitude_ok else 'NOT within'} 1.05x + 0.02'); x, y, z vs "
              f"pyproj {row.xyz_vs_pyproj_max_mm:.2g} mm; focal lengths vs local {row.focal_vs_local_max_px:.2g} px; "
              f"lever arm vs crs {row.lever_vs_crs_max_mm:.2g} mm, boresight {row.boresight_vs_crs_max_arcmin:.2g}'")
    print(f"\ntable: {csv}")
