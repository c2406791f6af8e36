"""`dmais simulate CONFIG --out DATASET`: a seeded synthetic DMAIS dataset with ground truth.

The dataset is assembled in a temporary sibling folder and renamed into place at the end, so an
interrupted run never leaves something that looks like a complete dataset.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
import zlib
from dataclasses import fields
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pandas as pd

from ..dataset import POINT_SIGMA, write_dataset
from ..errors import ConfigError, DmaisError
from ..files import write_bytes_atomic, write_csv_atomic, write_png_atomic, write_yaml_atomic
from ..geo import Geo, GeoError, ned_attitude
from ..geometry import Rigid3, exp_so3, rotation_from_quat
from . import pos
from ..rig import Rig
from .config import load_config, settings_to_write
from .render import RenderSettings, render_image
from .scene import (
    Frame,
    Marker,
    Shot,
    build_field,
    build_rig,
    flight_frames,
    horizontal_cameras,
    intrinsic_shots,
    placement_poses,
    small_rotation,
    visible_points,
)

log = logging.getLogger(__name__)

STAGES = ("intrinsics", "extrinsics", "flight")


def stream(seed: int, name: str) -> np.random.Generator:
    """An independent random stream per named component, so that changing one leaves the rest."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def simulate(config_path: str | Path, out: str | Path, jobs: int = 1) -> Path:
    """Write a complete dataset (with `truth/`) to `out` from the simulator YAML `config_path`.

    An existing `out` is replaced only if it is empty or an earlier simulated dataset.
    """
    config = load_config(config_path)
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not (out / "truth" / "simulation.yaml").is_file():
        raise DmaisError(f"{out}: exists and is not a simulated dataset; refusing to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.", suffix=".partial"))
    try:
        start = time.perf_counter()
        world = build_world(config)
        write_world(config, world, staging, jobs)
        if out.exists():
            shutil.rmtree(out)
        staging.rename(out)
        log.info("simulated dataset %s in %.1f s", out, time.perf_counter() - start)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out


# ------------------------------------------------------------------------------ the world


def build_world(config: dict) -> dict:
    """All ground truth: rig, field and ground markers, shots, frames."""
    seed = config["seed"]
    rig = build_rig(config["rig"])
    field = build_field(config, stream(seed, "field"))
    shots = intrinsic_shots(config, rig, field, stream(seed, "intrinsics"))
    shots += extrinsic_shots(config, rig, field, stream(seed, "extrinsics"))
    frames, ground = flight_frames(config, rig, stream(seed, "flight"))
    shots += flight_shots(rig, frames)
    return {"rig": rig, "field": field, "ground": ground, "shots": shots, "frames": frames}


def extrinsic_shots(config: dict, rig: Rig, field: list[Marker], rng) -> list[Shot]:
    """Images of the horizontal cameras at every placement that see enough control points."""
    shots = []
    for j, rig_from_world in enumerate(placement_poses(config, rig, rng)):
        for name in horizontal_cameras(rig, rig_from_world.R.T):
            cam_from_world = rig.cam_from_rig[name] * rig_from_world
            seen = visible_points(rig.cameras[name], cam_from_world, field, 20.0)
            if len(seen) >= config["extrinsics"]["min_points"]:
                shots.append(Shot(f"extr_p{j}_{name}", name, "extrinsics", cam_from_world, placement=f"p{j}"))
    return shots


def flight_shots(rig: Rig, frames: list[Frame]) -> list[Shot]:
    """One image per camera per flight frame, with the in-flight (deviated) mounting."""
    return [
        Shot(f"flight_{frame.frame}_{name}", name, "flight", frame.cam_from_rig[name] * frame.rig_from_world,
             placement=frame.frame)
        for frame in frames
        for name in rig.cameras
    ]


def markers_for(shot: Shot, world: dict, frames_by_id: dict[str, Frame]) -> list[Marker]:
    if shot.stage == "flight":
        site = frames_by_id[shot.placement].site
        return [m for m in world["ground"] if m.group == site]
    return world["field"]


def truth_observations(config: dict, world: dict) -> pd.DataFrame:
    """Noise-free projections of every marker corner every shot sees (image, point_id, u, v, size_px)."""
    rows = []
    frames_by_id = {frame.frame: frame for frame in world["frames"]}
    for shot in world["shots"]:
        margin = config["flight"]["border_margin_px"] if shot.stage == "flight" else 20.0
        camera = world["rig"].cameras[shot.camera]
        for point_id, uv, size in visible_points(camera, shot.cam_from_world, markers_for(shot, world, frames_by_id), margin):
            rows.append((shot.image, point_id, uv[0], uv[1], size))
    return pd.DataFrame(rows, columns=["image", "point_id", "u", "v", "size_px"])


# ------------------------------------------------------------------------------ writing


def write_world(config: dict, world: dict, root: Path, jobs: int) -> None:
    seed = config["seed"]
    truth = truth_observations(config, world)
    seen = set(truth["image"])
    shots = [shot for shot in world["shots"] if shot.image in seen]
    dropped = len(world["shots"]) - len(shots)
    if dropped:
        log.info("%d simulated images see no marker and are left out", dropped)
    rendered = {stage for stage in STAGES if config["render"][stage]}

    control_truth = _points_frame(world["field"])
    ground_truth = _points_frame(world["ground"])
    control = _survey(control_truth, config["field"]["survey_sigma_m"], stream(seed, "survey-field"))
    # the survey report's sigma per axis (the largest, where the axes differ), as a surveyor gives it
    control[POINT_SIGMA] = float(np.max(config["field"]["survey_sigma_m"]))
    ground = _survey(ground_truth, config["flight"]["survey_sigma_m"], stream(seed, "survey-ground"))
    observations = _measured(config, truth, shots, rendered, stream(seed, "pixels"))
    images = _images_frame(config, shots, rendered, stream(seed, "priors"))
    frames = _frames_frame(config, world["frames"], stream(seed, "pos"))
    geo = world_geo(config)
    kind = config["geodetic"]["trajectory"]
    if geo is not None and kind:  # frames.csv gives times; the POS trajectory beside it
        frames, trajectory = _with_trajectory(frames, geo, kind)
        write_bytes_atomic(root / TRAJECTORY_PATHS[kind], trajectory)
    if geo is not None:  # the survey in crs, the POS and RTK in pos_crs
        control, ground = (_in_crs(points, ["x", "y", "z"], geo) for points in (control, ground))
        images = _in_crs(images, ["prior_x", "prior_y", "prior_z"], geo, pos=True)
        frames = _in_crs(frames, ["pos_x", "pos_y", "pos_z"], geo, pos=True)

    write_dataset(
        root,
        _manifest(config),
        control,
        images,
        ground_points=ground,
        frames=frames,
        observations=observations,
    )
    _write_truth(config, world, shots, truth, control_truth, ground_truth, root / "truth")
    _render_all(config, world, [s for s in shots if s.stage in rendered], root, jobs)


def _manifest(config: dict) -> dict:
    """dataset.yaml's content; a camera's `model` only where it is not the default radial1."""
    rig = config["rig"]
    cameras = {
        name: {"width": rig["width"], "height": rig["height"], "focal_px": rig["nominal_focal_px"],
               **({"model": entry["model"]} if entry.get("model", "radial1") != "radial1" else {})}
        for name, entry in rig["cameras"].items()
    }
    geodetic = config["geodetic"]
    crs = {} if geodetic["crs"] is None else {
        "crs": geodetic["crs"], "pos_crs": geodetic["pos_crs"],
        "origin": dict(zip(("lat_deg", "lon_deg", "h_m"), map(float, geodetic["origin"]))),
        **({"trajectory": {"path": TRAJECTORY_PATHS[geodetic["trajectory"]], "format": geodetic["trajectory"]}}
           if geodetic["trajectory"] else {})}
    return {
        "name": config["name"],
        "description": f"DMAIS simulator, seed {config['seed']}",
        "reference_camera": rig["reference_camera"],
        "cameras": cameras,
        "marker_size_m": config["marker_size_m"],
        **crs,
    }


def world_geo(config: dict) -> Geo | None:
    """The simulated world's coordinate systems (its frame the topocentric ENU frame at the origin),
    None for a local frame; ConfigError naming a CRS pyproj does not know."""
    geodetic = config["geodetic"]
    if geodetic["crs"] is None:
        return None
    geo = Geo(geodetic["crs"], geodetic["pos_crs"], tuple(float(v) for v in geodetic["origin"]))
    for key in ("crs", "pos_crs"):
        try:
            geo.crs_from_enu(np.zeros((1, 3)), pos=key == "pos_crs")
        except GeoError as error:
            raise ConfigError(f"simulator setting 'geodetic.{key}': {error}") from None
    return geo


#: Where a geodetic world's trajectory is written, per format.
TRAJECTORY_PATHS = {"sbet": "pos/trajectory.sbet", "csv": "pos/trajectory.csv"}


def _with_trajectory(frames: pd.DataFrame, geo: Geo, kind: str) -> tuple[pd.DataFrame, bytes]:
    """frames.csv's table (world frame) with each frame's time instead of its POS position and INS
    attitude, and the trajectory file's bytes that give them back at those times (sim/pos.py)."""
    times = pos.frame_times(frames["group"])
    enu = frames[["pos_x", "pos_y", "pos_z"]].to_numpy(float)
    imu_from_world = rotation_from_quat(frames[["prior_qw", "prior_qx", "prior_qy", "prior_qz"]].to_numpy(float))
    ned_from_imu = geo.ned_from_enu(enu) @ np.swapaxes(imu_from_world, 1, 2)
    samples = pos.samples(times, frames["group"].to_numpy(object), geo.geodetic_from_enu(enu), ned_from_imu)
    kept = frames.drop(columns=["pos_x", "pos_y", "pos_z", "prior_qw", "prior_qx", "prior_qy", "prior_qz"])
    return kept.assign(time=times), pos.trajectory_file(kind, *samples)


def _in_crs(table: pd.DataFrame, columns: list[str], geo: Geo, pos: bool = False) -> pd.DataFrame:
    """`table` with its world `columns` (n rows, NaN where absent) in geo's crs (pos: pos_crs)."""
    if not set(columns) <= set(table.columns):
        return table
    out = table.copy()
    xyz = table[columns].to_numpy(float, copy=True)
    given = np.isfinite(xyz).all(axis=1)
    if given.any():
        xyz[given] = geo.crs_from_enu(xyz[given], pos=pos)
        out[columns] = xyz
    return out


def _points_frame(markers: list[Marker]) -> pd.DataFrame:
    rows = [(pid, *xyz) for m in markers for pid, xyz in zip(m.point_ids, m.board.corners())]
    return pd.DataFrame(rows, columns=["point_id", "x", "y", "z"])


def _survey(points: pd.DataFrame, sigma, rng) -> pd.DataFrame:
    """Surveyed coordinates: truth plus N(0, sigma^2) per axis (sigma scalar or (3,))."""
    surveyed = points.copy()
    surveyed[["x", "y", "z"]] += rng.normal(0.0, 1.0, (len(points), 3)) * np.broadcast_to(sigma, 3)
    return surveyed


def _measured(config, truth: pd.DataFrame, shots: list[Shot], rendered: set[str], rng) -> pd.DataFrame:
    """Observations of the images that are not rendered: truth plus pixel noise."""
    stage_of = {shot.image: shot.stage for shot in shots}
    stages = truth["image"].map(stage_of)
    keep = ~stages.isin(rendered)
    sigma = np.where(stages[keep] == "flight", config["flight"]["pixel_sigma_px"], config["calibration_pixel_sigma_px"])
    measured = truth.loc[keep, ["image", "point_id", "u", "v"]].copy()
    measured[["u", "v"]] += rng.normal(0.0, 1.0, (len(measured), 2)) * sigma[:, None]
    return measured.reset_index(drop=True)


def _images_frame(config, shots: list[Shot], rendered: set[str], rng) -> pd.DataFrame:
    """images.csv rows; calibration images carry RTK centre and approximate attitude priors."""
    p = config["calibration_priors"]
    rows = []
    for shot in shots:
        row = {"image": shot.image, "camera": shot.camera, "stage": shot.stage, "split": shot.split,
               "placement": shot.placement,
               "path": f"images/{shot.stage}/{shot.image}.png" if shot.stage in rendered else ""}
        if shot.stage != "flight":
            center = shot.cam_from_world.center + rng.normal(0.0, p["center_sigma_m"], 3)
            attitude = Rigid3(small_rotation(rng, np.radians(p["attitude_sigma_deg"])) @ shot.cam_from_world.R, np.zeros(3))
            row.update(zip(("prior_x", "prior_y", "prior_z"), center))
            row.update(zip(("prior_qw", "prior_qx", "prior_qy", "prior_qz"), attitude.quat))
        rows.append(row)
    return pd.DataFrame(rows)


def _frames_frame(config, frames: list[Frame], rng) -> pd.DataFrame:
    """frames.csv: POS position (rig origin + lever arm + noise) and INS attitude prior (the rig's
    attitude turned by the boresight imu_from_rig, + noise)."""
    fl = config["flight"]
    lever = np.asarray(fl["lever_arm_m"], dtype=float)
    imu_from_rig = exp_so3(np.radians(fl["ins_boresight_deg"]))
    rows = []
    for frame in frames:
        world_from_rig = frame.rig_from_world.inverse()
        pos = world_from_rig.apply(lever) + rng.normal(0.0, 1.0, 3) * np.asarray(fl["pos_sigma_m"])
        ins = small_rotation(rng, np.radians(fl["ins_attitude_sigma_deg"])) @ imu_from_rig @ frame.rig_from_world.R
        rows.append({"frame": frame.frame, "group": frame.group,
                     **dict(zip(("pos_x", "pos_y", "pos_z"), pos)),
                     **dict(zip(("prior_qw", "prior_qx", "prior_qy", "prior_qz"), Rigid3(ins, np.zeros(3)).quat))})
    return pd.DataFrame(rows)


def _pose_columns(pose: Rigid3) -> dict:
    return {**dict(zip(("qw", "qx", "qy", "qz"), pose.quat)), **dict(zip(("tx", "ty", "tz"), pose.t))}


def _write_truth(config, world, shots, truth, control_truth, ground_truth, folder: Path) -> None:
    rig: Rig = world["rig"]
    rig.save(folder / "rig.json")
    write_csv_atomic(folder / "control_points.csv", control_truth)
    write_csv_atomic(folder / "ground_points.csv", ground_truth)
    write_csv_atomic(folder / "observations.csv", truth)
    write_csv_atomic(folder / "images.csv", pd.DataFrame(
        [{"image": s.image, "camera": s.camera, "stage": s.stage, **_pose_columns(s.cam_from_world)} for s in shots]))
    frames = pd.DataFrame(
        [{"frame": f.frame, "group": f.group, "site": f.site, **_pose_columns(f.rig_from_world),
          **dict(zip(("x", "y", "z"), f.rig_from_world.center))} for f in world["frames"]])
    write_csv_atomic(folder / "frames.csv", _with_geodetic_truth(frames, world["frames"], world_geo(config)))
    write_csv_atomic(folder / "flight_cam_from_rig.csv", pd.DataFrame(
        [{"frame": f.frame, "camera": name, **_pose_columns(pose)}
         for f in world["frames"] for name, pose in f.cam_from_rig.items()]))
    write_yaml_atomic(folder / "simulation.yaml", settings_to_write(config))


def _with_geodetic_truth(table: pd.DataFrame, frames: list[Frame], geo: Geo | None) -> pd.DataFrame:
    """truth/frames.csv's table with, in a geodetic world, each rig centre's WGS 84 lat_deg, lon_deg,
    h_m and ned_heading_deg, ned_pitch_deg, ned_roll_deg (ned_from_rig's ZYX angles at it)."""
    if geo is None or not frames:
        return table
    centres = np.array([f.rig_from_world.center for f in frames])
    world_from_rig = np.array([f.rig_from_world.R.T for f in frames])
    values = np.column_stack([geo.geodetic_from_enu(centres), ned_attitude(geo.ned_from_enu(centres), world_from_rig)])
    return table.assign(**dict(zip(("lat_deg", "lon_deg", "h_m", "ned_heading_deg", "ned_pitch_deg",
                                    "ned_roll_deg"), values.T)))


# ------------------------------------------------------------------------------ rendering


def render_settings(config: dict) -> RenderSettings:
    overrides = config["render"]["settings"] or {}
    known = {f.name for f in fields(RenderSettings)}
    unknown = set(overrides) - known
    if unknown:
        raise ConfigError(f"unknown render setting(s) {sorted(unknown)}; known: {sorted(known)}")
    return RenderSettings(**overrides)


def _render_all(config, world, shots: list[Shot], root: Path, jobs: int) -> None:
    if not shots:
        return
    settings = render_settings(config)
    frames_by_id = {frame.frame: frame for frame in world["frames"]}
    tasks = [
        (root / f"images/{shot.stage}/{shot.image}.png", world["rig"].cameras[shot.camera], shot.cam_from_world,
         [m.board for m in markers_for(shot, world, frames_by_id)],
         [int(config["seed"]), zlib.crc32(shot.image.encode())], settings, config["render"]["png_compression"])
        for shot in shots
    ]
    start = time.perf_counter()
    if jobs > 1:
        with get_context("fork").Pool(jobs) as pool:
            for k, _ in enumerate(pool.imap_unordered(_render_one, tasks), 1):
                _progress(k, len(tasks), start)
    else:
        for k, task in enumerate(tasks, 1):
            _render_one(task)
            _progress(k, len(tasks), start)


def _render_one(task) -> str:
    path, camera, cam_from_world, boards, seed, settings, compression = task
    image = render_image(camera, cam_from_world, boards, np.random.default_rng(seed), settings)
    write_png_atomic(path, image, compression)
    return str(path)


def _progress(done: int, total: int, start: float) -> None:
    if done == total or done % 10 == 0:
        elapsed = time.perf_counter() - start
        log.info("rendered %d/%d images (%.1f s, %.2f s/image)", done, total, elapsed, elapsed / done)
